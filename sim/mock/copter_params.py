"""The mock ArduCopter's parameters: a small, realistic subset of ArduCopter 4.5's, in its units
and types, and the store that holds them as ArduPilot does (ints stored rounded)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

from onboard.app.mavlink2 import mavlink

REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
INT8 = mavlink.MAV_PARAM_TYPE_INT8
INT16 = mavlink.MAV_PARAM_TYPE_INT16
INT32 = mavlink.MAV_PARAM_TYPE_INT32


@dataclass(frozen=True)
class ParamSpec:
    name: str
    default: float
    ptype: int = REAL32


# A small, realistic subset of ArduCopter 4.5 parameters, in ArduPilot's units (cm, cm/s).
PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("FORMAT_VERSION", 120, INT16),
    ParamSpec("SYSID_THISMAV", 1, INT16),
    ParamSpec("SYSID_MYGCS", 255, INT16),
    ParamSpec("FRAME_CLASS", 1, INT8),
    ParamSpec("FRAME_TYPE", 1, INT8),
    ParamSpec("ARMING_CHECK", 1, INT32),
    ParamSpec("DISARM_DELAY", 10, INT8),
    ParamSpec("WPNAV_SPEED", 1000),
    ParamSpec("WPNAV_SPEED_UP", 250),
    ParamSpec("WPNAV_SPEED_DN", 150),
    ParamSpec("WPNAV_ACCEL", 250),
    ParamSpec("WPNAV_ACCEL_Z", 100),
    ParamSpec("WPNAV_RADIUS", 200),
    ParamSpec("WPNAV_JERK", 1),
    ParamSpec("PSC_JERK_XY", 5),
    ParamSpec("PSC_JERK_Z", 5),
    ParamSpec("ATC_ACCEL_R_MAX", 110000),  # cdeg/s^2: with ATC_ACCEL_P_MAX, caps PSC_JERK_XY
    ParamSpec("ATC_ACCEL_P_MAX", 110000),
    ParamSpec("PILOT_SPEED_UP", 250, INT16),
    ParamSpec("PILOT_SPEED_DN", 0, INT16),
    ParamSpec("PILOT_TKOFF_ALT", 0),
    ParamSpec("LAND_SPEED", 50, INT16),
    ParamSpec("LAND_SPEED_HIGH", 0, INT16),
    ParamSpec("LAND_ALT_LOW", 1000, INT16),
    ParamSpec("RTL_ALT", 1500, INT32),
    ParamSpec("RTL_ALT_FINAL", 0, INT32),
    ParamSpec("RTL_SPEED", 0, INT16),
    ParamSpec("RTL_LOIT_TIME", 5000, INT32),
    ParamSpec("WP_YAW_BEHAVIOR", 2, INT8),
    ParamSpec("GUID_OPTIONS", 0, INT32),
    ParamSpec("GUID_TIMEOUT", 3),
    ParamSpec("FS_THR_ENABLE", 1, INT8),
    ParamSpec("FS_THR_VALUE", 975, INT16),
    ParamSpec("FS_GCS_ENABLE", 0, INT8),
    ParamSpec("FS_GCS_TIMEOUT", 5),
    ParamSpec("FS_EKF_ACTION", 1, INT8),
    ParamSpec("FS_EKF_THRESH", 0.8),
    ParamSpec("FS_CRASH_CHECK", 1, INT8),
    ParamSpec("FS_OPTIONS", 16, INT32),
    ParamSpec("FS_VIBE_ENABLE", 1, INT8),
    ParamSpec("FS_DR_ENABLE", 2, INT8),
    ParamSpec("BATT_MONITOR", 4, INT8),
    ParamSpec("BATT_CAPACITY", 3300, INT32),
    ParamSpec("BATT_LOW_VOLT", 10.5),
    ParamSpec("BATT_FS_LOW_ACT", 0, INT8),
    ParamSpec("FENCE_ENABLE", 0, INT8),
    ParamSpec("FENCE_ALT_MAX", 100),
    # stream rates (Hz) per serial port n = the mock's endpoint index; 0 as in ArduCopter SITL
    *(ParamSpec(f"SR{n}_{g}", 0, INT16) for n in range(4)
      for g in ("EXT_STAT", "POSITION", "EXTRA1", "EXTRA2", "EXTRA3")),
)


class Params:
    """Named parameter store with ArduPilot's typing (ints are stored rounded)."""

    def __init__(self, specs: Sequence[ParamSpec] = PARAMS, overrides: Mapping[str, float] = {}):
        self._specs = {s.name: s for s in specs}
        self._order = [s.name for s in specs]
        self._values = {s.name: float(s.default) for s in specs}
        for name, value in overrides.items():
            if not self.set(name, value):
                raise KeyError(f"unknown parameter {name!r}")

    def __len__(self) -> int:
        return len(self._order)

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def names(self) -> list[str]:
        return list(self._order)

    def index(self, name: str) -> int:
        return self._order.index(name)

    def ptype(self, name: str) -> int:
        return self._specs[name].ptype

    def set(self, name: str, value: float) -> bool:
        """Set a known parameter; False for unknown names or non-finite values."""
        if name not in self._specs or not math.isfinite(value):
            return False
        if self._specs[name].ptype != REAL32:
            value = float(round(value))
        self._values[name] = float(value)
        return True
