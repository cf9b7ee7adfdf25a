"""Mock ArduCopter autopilot speaking MAVLink 2, for software-in-the-loop tests.

It behaves, on the wire, like a stock ArduCopter SITL as far as pmon and ordinary
clients (pymavlink, MAVProxy, MAVSDK) can tell:

- several endpoints at once (UDP out/in, TCP servers), routed like ArduPilot's
  MAVLink_routing: routes are learned per (sysid, compid), targeted messages go to the
  link that component was seen on, broadcasts go to every other link with a route,
  heartbeats to every other active link; only parseable messages are forwarded;
- HEARTBEAT, COMMAND_LONG/COMMAND_INT with ArduPilot's COMMAND_ACK results, SET_MODE,
  parameters, an empty mission, SET_POSITION_TARGET_* with ArduPilot's type_mask rules;
- telemetry only as asked for, as ArduCopter does: a HEARTBEAT a second, and each link's streams
  at the rates of its SRn_ parameters (0 by default, as in ArduCopter SITL) or as a client
  sets them (SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM);
- ArduCopter's boot (``BootTimeline``, measured on its 4.4 SITL): no GPS position, no EKF origin
  and arming refused ("Arm: Need Position Estimate") until the EKF is ready, ~43 s;
- its defects a client must not trigger: a COMMAND_LONG take-off, home or ROI whose position
  fields are NaN aborts an armed ArduCopter 4.4 (floating point exception); the mock counts it
  (``defects``) and goes silent like the crashed firmware;
- modes GUIDED, LOITER, BRAKE, POSHOLD, ALT_HOLD, STABILIZE (hold), RTL, LAND;
- its own clock: time_boot_ms runs at `speedup` x wall time and the kinematic model
  (sim.vehicle, local NED with origin = home) is stepped at a fixed rate on that clock.

Geodetic <-> local conversions use pymap3d; the local frame is NED (MAVLink's), and
`AutopilotState.pos_enu` gives the ENU mission frame of the core.

Run in-process (``with MockAutopilot(...) as ap:``) or as a process::

    python -m sim.autopilot --udp 127.0.0.1:14550 --tcp 127.0.0.1:5760 \
        --speedup 5 --home=-35.363261,149.165230,584
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import math
import os
import select
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, replace
from enum import IntEnum
from typing import Callable, Iterable, Mapping, Optional, Sequence

# pymavlink picks its wire protocol from this variable at import time.
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402,F401  (imported after MAVLINK20 is set)
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

import numpy as np  # noqa: E402
import pymap3d  # noqa: E402

from sim import vehicle  # noqa: E402
from sim.vehicle import Setpoint, Vec3, VehicleState, limits_from_params  # noqa: E402

log = logging.getLogger("sim.autopilot")

FIRMWARE = "ArduCopter V4.5.7 (pmon mock)"
FW_VERSION = (4 << 24) | (5 << 16) | (7 << 8) | 255  # major.minor.patch, type OFFICIAL

MAGIC_FORCE_ARM = 2989.0
MAGIC_FORCE_DISARM = 21196.0


class Mode(IntEnum):
    """ArduCopter flight mode numbers (HEARTBEAT.custom_mode)."""

    STABILIZE = 0
    ACRO = 1
    ALT_HOLD = 2
    AUTO = 3
    GUIDED = 4
    LOITER = 5
    RTL = 6
    CIRCLE = 7
    LAND = 9
    DRIFT = 11
    SPORT = 13
    FLIP = 14
    AUTOTUNE = 15
    POSHOLD = 16
    BRAKE = 17
    THROW = 18
    AVOID_ADSB = 19
    GUIDED_NOGPS = 20
    SMART_RTL = 21


# Modes the mock flies; others are refused like a mode that fails its init checks.
FLOWN_MODES = {
    Mode.STABILIZE, Mode.ALT_HOLD, Mode.GUIDED, Mode.LOITER, Mode.RTL,
    Mode.LAND, Mode.POSHOLD, Mode.BRAKE,
}
ARMABLE_MODES = {Mode.STABILIZE, Mode.ALT_HOLD, Mode.GUIDED, Mode.LOITER, Mode.POSHOLD}
TAKEOFF_MODES = {Mode.GUIDED, Mode.LOITER, Mode.POSHOLD}  # has_user_takeoff(must_navigate)
HOLD_MODES = {Mode.STABILIZE, Mode.ALT_HOLD, Mode.LOITER, Mode.POSHOLD, Mode.BRAKE}
# autopilot s from an accepted take-off to the climb (landed_state ON_GROUND until then): 3.3 s
# measured on ArduCopter 4.4 SITL (GUIDED, stock parameters: 42.2 s accepted, 45.5 s TAKEOFF)
TAKEOFF_SPOOL_S = 3.3


# --------------------------------------------------------------------------- parameters

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


@dataclass(frozen=True)
class BootTimeline:
    """When ArduCopter is ready after boot, autopilot s, as measured on ArduCopter 4.4 SITL with
    stock parameters (the binary in ../shared/ardupilot): a GPS fix at 8.6 s (GLOBAL_POSITION_INT
    has lat = lon = 0 before), the EKF origin at 18.6 s (GPS_GLOBAL_ORIGIN and HOME_POSITION sent
    to every link unasked, none before), a position estimate good enough to arm at 42.6 s (an
    ARM before is refused, MAV_RESULT_FAILED, "Arm: Need Position Estimate"; SYS_STATUS's
    pre-arm bit unhealthy; "PreArm: Need Position Estimate" every 30 s) - except for one second
    from 24.0 s when the pre-arm bit reads healthy while arming is still refused (seen in three
    of three runs sampled often enough: 23-24 s, 24.0-25.0 s). ``scaled`` keeps the proportions
    for tests that need the behaviour but not the wait."""

    gps_s: float = 8.6
    origin_s: float = 18.6
    ready_s: float = 42.6
    blip_s: tuple[float, float] = (24.0, 25.0)  # pre-arm bit healthy, arming still refused

    @classmethod
    def scaled(cls, ready_s: float) -> "BootTimeline":
        k = max(ready_s, 0.0) / cls.ready_s
        return cls(cls.gps_s * k, cls.origin_s * k, cls.ready_s * k, (24.0 * k, 25.0 * k))



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


# --------------------------------------------------------------------------- flight logic

@dataclass(frozen=True)
class GuidedTarget:
    """GUIDED sub-mode target, in local NED (ArduPilot's ModeGuided::SubMode)."""

    kind: str  # "pos" | "posvel" | "vel" | "accel"
    pos: Optional[Vec3] = None
    vel: Optional[Vec3] = None
    acc: Optional[Vec3] = None
    yaw: Optional[float] = None
    yaw_rate: Optional[float] = None
    updated_s: float = 0.0


class Copter:
    """ArduCopter-like flight state machine around the kinematic model.

    No I/O: commands return MAV_RESULT values, `tick(dt)` advances the sim by dt
    seconds, and `events` collects (severity, text) STATUSTEXTs for the shell to send.
    """

    def __init__(self, home: tuple[float, float, float], params: Params,
                 rng: Optional[np.random.Generator], pos_noise: float = 0.02,
                 boot: BootTimeline = BootTimeline()):
        self.origin = home  # local NED origin (EKF origin) = home at boot
        self.home = home
        self.home_ned: Vec3 = (0.0, 0.0, 0.0)
        self.params = params
        self.rng = rng
        self.pos_noise = pos_noise
        self.limits = limits_from_params(params, pos_noise)
        self.state = VehicleState()
        self.t = 0.0
        self.mode = Mode.STABILIZE
        self.armed = False
        self.land_complete = True
        self.landed_since = 0.0
        self.takeoff_z: Optional[float] = None  # NED z of an active user takeoff
        self.hold_pos: Vec3 = (0.0, 0.0, 0.0)
        self.guided: Optional[GuidedTarget] = None
        self.fixed_yaw: Optional[float] = None  # CONDITION_YAW
        self.speed: dict[str, float] = {}  # DO_CHANGE_SPEED overrides (m/s)
        self.rtl_phase = "climb"
        self.rtl_z = 0.0
        self.rtl_loiter_start = 0.0
        self.battery_used_mah = 0.0
        self.events: list[tuple[int, str]] = []
        self.boot = boot
        self._prearm_said = 0.0
        self.spool_until: Optional[float] = None  # take-off accepted, climbing from then

    # ----- boot (BootTimeline)
    @property
    def gps_ok(self) -> bool:
        return self.t >= self.boot.gps_s

    @property
    def origin_set(self) -> bool:
        return self.t >= self.boot.origin_s

    @property
    def position_ok(self) -> bool:
        return self.t >= self.boot.ready_s

    @property
    def prearm_bit(self) -> bool:
        """SYS_STATUS's pre-arm bit: healthy when arming passes, and during the blip."""
        return self.position_ok or self.boot.blip_s[0] <= self.t < self.boot.blip_s[1]

    # ----- helpers
    def text(self, severity: int, msg: str) -> None:
        self.events.append((severity, msg))

    def params_changed(self) -> None:
        self.limits = limits_from_params(self.params, self.pos_noise)

    def ned_from_geodetic(self, lat: float, lon: float, alt_amsl: float) -> Vec3:
        n, e, d = pymap3d.geodetic2ned(lat, lon, alt_amsl, *self.origin)
        return (float(n), float(e), float(d))

    def geodetic_from_ned(self, ned: Vec3) -> tuple[float, float, float]:
        lat, lon, alt = pymap3d.ned2geodetic(ned[0], ned[1], ned[2], *self.origin)
        return (float(lat), float(lon), float(alt))

    def alt_above_home(self) -> float:
        return self.home_ned[2] - self.state.pos[2]

    def landed_state(self) -> int:
        if self.land_complete or self.spool_until is not None:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.mode == Mode.LAND or (self.mode == Mode.RTL and self.rtl_phase == "land"):
            return mavlink.MAV_LANDED_STATE_LANDING
        if self.takeoff_z is not None:
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def _stopping_point(self) -> Vec3:
        return vehicle.stopping_point(self.state, self.limits)

    # ----- commands
    def set_mode(self, number: int) -> bool:
        """Copter::set_mode: True if the vehicle is (now) in that mode."""
        try:
            mode = Mode(number)
        except ValueError:
            self.text(mavlink.MAV_SEVERITY_WARNING, "Flight mode change failed")
            return False
        if mode == self.mode:
            return True  # ArduPilot does not re-init the current mode
        if mode not in FLOWN_MODES:
            # AUTO with an empty mission, CIRCLE, ... fail their init() like this.
            self.text(mavlink.MAV_SEVERITY_WARNING, f"Flight mode change failed: {mode.name}")
            return False
        self.mode = mode
        self.state = replace(self.state, xy=None)  # each mode's init restarts the controller
        self.speed = {}
        self.fixed_yaw = None
        self.guided = None
        stop = self._stopping_point()
        if self.takeoff_z is not None and mode not in TAKEOFF_MODES:
            self.takeoff_z = None
        if mode in HOLD_MODES:
            self.hold_pos = stop if self.takeoff_z is None else self.state.pos
        elif mode == Mode.GUIDED:
            # ModeGuided::init: hold at the stopping point until a target arrives.
            self.guided = GuidedTarget("pos", pos=stop, updated_s=self.t)
        elif mode == Mode.LAND:
            self.hold_pos = stop
        elif mode == Mode.RTL:
            self.rtl_phase = "climb"
            rtl_alt = max(self.params["RTL_ALT"] / 100.0, self.alt_above_home())
            self.rtl_z = self.home_ned[2] - rtl_alt
            self.hold_pos = stop
        return True

    def arm(self, force: bool) -> bool:
        if self.armed:
            return True
        if not force and self.mode not in ARMABLE_MODES:
            self.text(mavlink.MAV_SEVERITY_CRITICAL, "Arm: Mode not armable")
            return False
        if not force and not self.position_ok:
            self.text(mavlink.MAV_SEVERITY_CRITICAL, "Arm: Need Position Estimate")
            return False
        self.armed = True
        self.landed_since = self.t
        self.text(mavlink.MAV_SEVERITY_INFO, "Arming motors")
        return True

    def disarm(self, force: bool, reason: str = "") -> bool:
        if not self.armed:
            return True
        self.spool_until = None
        if not force and not self.land_complete:
            # AP_Arming_Copter::disarm refuses a GCS disarm while flying unless forced.
            return False
        self.armed = False
        self.takeoff_z = None
        self.text(mavlink.MAV_SEVERITY_INFO, f"Disarming motors{reason}")
        return True

    def takeoff(self, alt_rel_m: float) -> bool:
        """Mode::do_user_takeoff: armed, landed, a takeoff-capable mode, going up."""
        if not self.armed or not self.land_complete or self.mode not in TAKEOFF_MODES:
            return False
        if not math.isfinite(alt_rel_m) or alt_rel_m <= self.alt_above_home():
            return False
        self.takeoff_z = self.home_ned[2] - alt_rel_m
        self.hold_pos = (self.state.pos[0], self.state.pos[1], self.takeoff_z)
        if self.mode == Mode.GUIDED:
            self.guided = GuidedTarget("pos", pos=self.hold_pos, updated_s=self.t)
        if self.spool_until is None:  # a repeat during the spool-up is accepted, changes nothing
            self.spool_until = self.t + TAKEOFF_SPOOL_S
        return True

    def guided_hold(self) -> None:
        """ModeGuided::init(true): a rejected target makes the vehicle stop and hold."""
        self.guided = GuidedTarget("pos", pos=self._stopping_point(), updated_s=self.t)
        self.takeoff_z = None

    def set_guided(self, target: GuidedTarget) -> None:
        if self.guided is None or self.guided.kind != target.kind:
            self.state = replace(self.state, xy=None)  # a new sub-mode restarts the controller
        self.guided = replace(target, updated_s=self.t)
        self.takeoff_z = None

    def set_home(self, lla: Optional[tuple[float, float, float]]) -> None:
        """MAV_CMD_DO_SET_HOME: a location, or None for the current position."""
        self.home = lla if lla is not None else self.geodetic_from_ned(self.state.pos)
        self.home_ned = self.ned_from_geodetic(*self.home)

    # ----- simulation
    def tick(self, dt: float) -> None:
        self.t += dt
        if not self.armed and not self.position_ok and self.t >= self._prearm_said + 30.0:
            self._prearm_said = self.t  # ArduPilot reports failing pre-arm checks every 30 s
            self.text(mavlink.MAV_SEVERITY_CRITICAL, "PreArm: Need Position Estimate")
        current_a = 0.3
        if not self.armed:
            if self.state.pos[2] < -0.01 or any(self.state.vel):
                self.state = vehicle.fall(self.state, dt, self._ground_z())
            if self.state.pos[2] >= self._ground_z() - 0.01 and not self.land_complete:
                self.land_complete = True
                self.landed_since = self.t
        elif self.spool_until is not None:  # take-off accepted: motors spooling, still landed
            current_a = 5.0
            if self.t >= self.spool_until:
                self.spool_until = None
                self.land_complete = False
        elif self.land_complete and self.takeoff_z is None:
            current_a = 2.0  # spinning at idle on the ground
            delay = self.params["DISARM_DELAY"]
            if delay > 0 and self.t - self.landed_since >= delay:
                self.disarm(True, reason=" (auto disarm)")
        else:
            current_a = 15.0
            sp = self._setpoint(dt)
            self.state = vehicle.on_ground(
                vehicle.step(self.state, sp, dt, self.limits, self.rng), self._ground_z()
            )
            self._update_takeoff_and_landing(sp)
        self.battery_used_mah += current_a * dt / 3.6

    def _ground_z(self) -> float:
        return 0.0  # flat ground at the altitude of the origin (home at boot)

    def _setpoint(self, dt: float) -> Setpoint:
        speeds = dict(
            speed_xy=self.speed.get("xy"), speed_up=self.speed.get("up"),
            speed_down=self.speed.get("down"),
        )
        if self.mode == Mode.GUIDED and self.guided is not None and self.takeoff_z is None:
            return self._guided_setpoint(dt, speeds)
        if self.mode == Mode.LAND:
            return Setpoint(pos=(self.hold_pos[0], self.hold_pos[1], self._ground_z() + 1.0),
                            speed_down=self._descent_speed(), speed_xy=speeds["speed_xy"])
        if self.mode == Mode.RTL:
            return self._rtl_setpoint()
        # Hold modes, and any takeoff in progress.
        pos = self.hold_pos
        if self.takeoff_z is not None:
            pos = (self.hold_pos[0], self.hold_pos[1], self.takeoff_z)
        return Setpoint(pos=pos, yaw=self.fixed_yaw, speed_up=self._takeoff_speed(), **{
            k: v for k, v in speeds.items() if k != "speed_up"})

    def _takeoff_speed(self) -> Optional[float]:
        if self.takeoff_z is None or self.mode == Mode.GUIDED:
            return self.speed.get("up")  # GUIDED takes off with wp_nav: WPNAV_SPEED_UP
        # _TakeOff::start: min(WPNAV_SPEED_UP, max(2/3 PILOT_SPEED_UP, PILOT_SPEED_UP - 50))
        pilot = self.params["PILOT_SPEED_UP"]
        return min(self.limits.speed_up, max(pilot * 2 / 3, pilot - 50) / 100.0)

    def _descent_speed(self) -> float:
        high = self.params["LAND_SPEED_HIGH"] / 100.0 or self.limits.speed_down
        if self.alt_above_home() > self.params["LAND_ALT_LOW"] / 100.0:
            return high
        return max(self.params["LAND_SPEED"], 30.0) / 100.0

    def _guided_setpoint(self, dt: float, speeds: dict) -> Setpoint:
        g = self.guided
        assert g is not None
        timed_out = self.t - g.updated_s > self.params["GUID_TIMEOUT"]
        yaw = g.yaw if g.yaw is not None else self.fixed_yaw
        yaw_rate = g.yaw_rate
        if g.kind == "pos":
            if yaw is None and yaw_rate is None:
                dn, de = g.pos[0] - self.state.pos[0], g.pos[1] - self.state.pos[1]
                if math.hypot(dn, de) > 2.0:  # WP_YAW_BEHAVIOR: face the destination
                    yaw = math.atan2(de, dn)
            return Setpoint(pos=g.pos, yaw=yaw, yaw_rate=yaw_rate, **speeds)
        if g.kind == "posvel":
            vel = (0.0, 0.0, 0.0) if timed_out else g.vel
            acc = None if timed_out else g.acc
            # The firmware moves the target on between messages (input_pos_vel_accel_xy).
            pos, moved = vehicle.advance_input(g.pos, vel, acc, dt)
            self.guided = replace(g, pos=pos, vel=g.vel if timed_out else moved)
            return Setpoint(pos=g.pos, vel=vel, acc=acc, yaw=yaw, yaw_rate=yaw_rate, **speeds)
        if g.kind == "vel":
            vel = (0.0, 0.0, 0.0) if timed_out else g.vel
            acc = None if timed_out else g.acc
            if yaw is None and yaw_rate is None and math.hypot(vel[0], vel[1]) > 1.0:
                yaw = math.atan2(vel[1], vel[0])
            return Setpoint(vel=vel, acc=acc, yaw=yaw, yaw_rate=yaw_rate, **speeds)
        acc = (0.0, 0.0, 0.0) if timed_out else g.acc
        return Setpoint(acc=acc, yaw=yaw, yaw_rate=yaw_rate, **speeds)

    def _rtl_setpoint(self) -> Setpoint:
        home = self.home_ned
        s = self.state
        if self.rtl_phase == "climb":
            if s.pos[2] - self.rtl_z < 0.5:
                self.rtl_phase = "return"
            return Setpoint(pos=(self.hold_pos[0], self.hold_pos[1], self.rtl_z))
        if self.rtl_phase == "return":
            target = (home[0], home[1], self.rtl_z)
            if math.dist(s.pos, target) < 1.0 and math.hypot(s.vel[0], s.vel[1]) < 0.5:
                self.rtl_phase = "loiter"
                self.rtl_loiter_start = self.t
            speed = self.params["RTL_SPEED"] / 100.0 or None
            return Setpoint(pos=target, speed_xy=speed,
                            yaw=math.atan2(home[1] - s.pos[1], home[0] - s.pos[0])
                            if math.hypot(home[0] - s.pos[0], home[1] - s.pos[1]) > 2 else None)
        if self.rtl_phase == "loiter":
            if self.t - self.rtl_loiter_start >= self.params["RTL_LOIT_TIME"] / 1000.0:
                self.rtl_phase = "land"
            return Setpoint(pos=(home[0], home[1], self.rtl_z))
        return Setpoint(pos=(home[0], home[1], self._ground_z() + 1.0),
                        speed_down=self._descent_speed())

    def _update_takeoff_and_landing(self, sp: Setpoint) -> None:
        s = self.state
        if self.takeoff_z is not None and abs(s.pos[2] - self.takeoff_z) < 0.2:
            self.takeoff_z = None  # takeoff complete: keep holding there
            self.text(mavlink.MAV_SEVERITY_INFO, "Takeoff complete")
        if self.takeoff_z is not None:
            return
        on_ground = s.pos[2] >= self._ground_z() - 0.01
        wants_down = (
            (sp.pos is not None and sp.pos[2] >= self._ground_z() - 0.1)
            or (sp.pos is None and sp.vel is not None and sp.vel[2] >= 0.0)
            or (sp.pos is None and sp.vel is None)
        )
        if on_ground and wants_down and not self.land_complete:
            self.land_complete = True
            self.landed_since = self.t
            self.state = replace(s, vel=(0.0, 0.0, 0.0), acc=(0.0, 0.0, 0.0))
            self.text(mavlink.MAV_SEVERITY_INFO, "Landed")
            if self.mode in (Mode.LAND, Mode.RTL):
                self.disarm(True)


# --------------------------------------------------------------------------- links

def _check_loopback(host: str) -> None:
    """Only loopback addresses: the mock must never talk to the network."""
    try:
        infos = socket.getaddrinfo(host, None, socket.AF_INET)
    except socket.gaierror as exc:
        raise ValueError(f"cannot resolve {host!r}: {exc}") from exc
    for info in infos:
        if not ipaddress.ip_address(info[4][0]).is_loopback:
            raise ValueError(f"{host!r} is not a loopback address")


@dataclass(frozen=True)
class Endpoint:
    """A MAVLink endpoint: kind 'udpout' (send to host:port), 'udpin' (listen) or 'tcpin'."""

    kind: str
    host: str
    port: int

    @staticmethod
    def parse(text: str) -> "Endpoint":
        """Parse 'udpout:127.0.0.1:14550', 'udpin:...', 'tcpin:...' (also 'udp:'/'tcp:')."""
        kind, _, rest = text.partition(":")
        host, _, port = rest.rpartition(":")
        kind = {"udp": "udpout", "tcp": "tcpin"}.get(kind, kind)
        if kind not in ("udpout", "udpin", "tcpin") or not host or not port.isdigit():
            raise ValueError(f"bad endpoint {text!r}; want udpout|udpin|tcpin:HOST:PORT")
        return Endpoint(kind, host, int(port))

    def __str__(self) -> str:
        return f"{self.kind}:{self.host}:{self.port}"


class _Sink:
    """File-like adapter so pymavlink's MAVLink.send writes through a link."""

    def __init__(self, link: "_Link"):
        self.link = link

    def write(self, data: bytes) -> None:
        self.link.write(data)


class _Link:
    """One MAVLink channel: its own parser, sequence numbers and stream rates."""

    MAX_PENDING = 256 * 1024

    def __init__(self, name: str, sysid: int, compid: int, intervals: Mapping[str, float]):
        self.name = name
        self.parser = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.parser.robust_parsing = True
        self.out = mavlink.MAVLink(_Sink(self), srcSystem=sysid, srcComponent=compid)
        self.intervals = dict(intervals)  # message name -> interval (sim s); 0 = off
        self.next_due: dict[str, float] = {}
        self.active = False  # has received a valid packet (ArduPilot's active channel)
        self.closed = False
        self.tx_errors = 0
        self.muted_until = -math.inf  # fault injection: sim time until which the link is dead
        self.muted = False
        self.port_index = 0  # the endpoint it belongs to (its SRn_ stream rates)

    def fileno(self) -> int:
        raise NotImplementedError

    def receive(self) -> bytes:
        raise NotImplementedError

    def write(self, data: bytes) -> None:
        raise NotImplementedError

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True

    def send(self, msg) -> None:
        self.out.send(msg)


class _UdpLink(_Link):
    def __init__(self, ep: Endpoint, sysid: int, compid: int, intervals: Mapping[str, float]):
        super().__init__(str(ep), sysid, compid, intervals)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if ep.kind == "udpin":
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self.sock.bind((ep.host, ep.port))
                self.peer: Optional[tuple] = None  # learned from the last sender
            else:
                self.sock.bind(("127.0.0.1", 0))
                self.peer = (ep.host, ep.port)
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.udpin = ep.kind == "udpin"
        self.local = self.sock.getsockname()

    def fileno(self) -> int:
        return self.sock.fileno()

    def receive(self) -> bytes:
        chunks = []
        while True:
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                continue  # ICMP port unreachable from an earlier send: peer not up yet
            if self.udpin:
                self.peer = addr
            chunks.append(data)
        return b"".join(chunks)

    def write(self, data: bytes) -> None:
        if self.peer is None or self.closed or self.muted:
            return
        try:
            self.sock.sendto(data, self.peer)
        except OSError:
            self.tx_errors += 1

    def close(self) -> None:
        super().close()
        self.sock.close()


class _TcpLink(_Link):
    def __init__(self, sock: socket.socket, name: str, sysid: int, compid: int,
                 intervals: Mapping[str, float]):
        super().__init__(name, sysid, compid, intervals)
        self.sock = sock
        self.sock.setblocking(False)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.pending = bytearray()
        self.dropped = 0

    def fileno(self) -> int:
        return self.sock.fileno()

    def receive(self) -> bytes:
        try:
            data = self.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            data = b""
        if not data:
            self.close()
        return data

    def write(self, data: bytes) -> None:
        if self.closed or self.muted:
            return
        if len(self.pending) + len(data) > self.MAX_PENDING:
            self.dropped += 1  # like ArduPilot with no txspace: drop, never block
            return
        self.pending += data
        self.flush()

    def flush(self) -> None:
        while self.pending and not self.closed:
            try:
                sent = self.sock.send(self.pending)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.close()
                return
            del self.pending[:sent]

    def close(self) -> None:
        if not self.closed:
            super().close()
            self.sock.close()


class _TcpListener:
    def __init__(self, ep: Endpoint, index: int = 0):
        self.index = index  # the endpoint's position: its "serial port" (SRn_ rates)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.sock.bind((ep.host, ep.port))
            self.sock.listen(4)
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.local = self.sock.getsockname()

    def fileno(self) -> int:
        return self.sock.fileno()

    def accept(self) -> Optional[tuple[socket.socket, tuple]]:
        try:
            return self.sock.accept()
        except (BlockingIOError, InterruptedError, OSError):
            return None

    def close(self) -> None:
        self.sock.close()


# --------------------------------------------------------------------------- telemetry

# Sent on every link whatever its SRn_ rates (ArduPilot's GCS_MAVLINK heartbeat): interval, sim s
ALWAYS_INTERVALS_S: Mapping[str, float] = {"HEARTBEAT": 1.0}

# REQUEST_DATA_STREAM / SRn_ groups (ArduCopter's STREAM_* lists, restricted to what we send;
# measured on 4.4 SITL: EXTENDED_SYS_STATE is in none, it comes only when asked for).
DATA_STREAMS: Mapping[int, tuple[str, ...]] = {
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS", "GPS_RAW_INT", "POSITION_TARGET_GLOBAL_INT"),
    mavlink.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    mavlink.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    mavlink.MAV_DATA_STREAM_EXTRA2: ("VFR_HUD",),
    mavlink.MAV_DATA_STREAM_EXTRA3: ("SYSTEM_TIME", "BATTERY_STATUS", "EKF_STATUS_REPORT"),
}
SR_GROUPS = {"EXT_STAT": mavlink.MAV_DATA_STREAM_EXTENDED_STATUS, "POSITION": mavlink.MAV_DATA_STREAM_POSITION,
             "EXTRA1": mavlink.MAV_DATA_STREAM_EXTRA1, "EXTRA2": mavlink.MAV_DATA_STREAM_EXTRA2,
             "EXTRA3": mavlink.MAV_DATA_STREAM_EXTRA3}

SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
    | mavlink.MAV_SYS_STATUS_AHRS | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
    | mavlink.MAV_SYS_STATUS_LOGGING | mavlink.MAV_SYS_STATUS_PREARM_CHECK
)

CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
)  # no FTP: clients then fetch parameters with PARAM_REQUEST_LIST

# type_mask bits (POSITION_TARGET_TYPEMASK_*)
_POS_IGNORE = 0b111
_VEL_IGNORE = 0b111 << 3
_ACC_IGNORE = 0b111 << 6
_FORCE_SET = 1 << 9
_YAW_IGNORE = 1 << 10
_YAW_RATE_IGNORE = 1 << 11

# MAVLink FTP opcodes and error codes used by the FTP refusal
_FTP_TERMINATE_SESSION, _FTP_RESET_SESSIONS = 1, 2
_FTP_OPEN_OPS = {3, 4, 6, 11, 13}  # list dir, open RO, create, open WO, calc CRC
_FTP_ACK, _FTP_NAK = 128, 129
_FTP_ERR_INVALID_SESSION, _FTP_ERR_FILE_NOT_FOUND = 4, 10

# COMMAND_LONGs ArduCopter 4.4 handles as COMMAND_INT (param5/6 as degE7 int32)
LONG_AS_INT = frozenset({mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_DO_SET_HOME,
                         mavlink.MAV_CMD_DO_SET_ROI_LOCATION})

_LOCAL_FRAMES = {
    mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_OFFSET_NED,
    mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED,
}
_BODY_FRAMES = {mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED}
_ABSOLUTE_FRAMES = {mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT}
_RELATIVE_FRAMES = {mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                    mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT}
_TERRAIN_FRAMES = {mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT,
                   mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT}


@dataclass(frozen=True)
class AutopilotState:
    """Snapshot of the mock for tests (SI units, radians, degrees only for lat/lon)."""

    time_boot_ms: int
    mode: int
    mode_name: str
    armed: bool
    landed_state: int
    pos_ned: Vec3  # m, local NED, origin = home
    vel_ned: Vec3
    pos_enu: Vec3  # m, local ENU (the core's mission frame at this origin)
    vel_enu: Vec3
    yaw: float  # rad, heading from north, clockwise
    lat: float  # deg
    lon: float  # deg
    alt_amsl: float  # m
    alt_rel: float  # m above home


@dataclass(frozen=True)
class _Command:
    """COMMAND_LONG / COMMAND_INT in one shape (x, y in degE7 for INT location commands)."""

    command: int
    params: tuple[float, float, float, float]
    x: float
    y: float
    z: float
    frame: Optional[int]  # None for COMMAND_LONG
    sysid: int
    compid: int


# --------------------------------------------------------------------------- the mock

class MockAutopilot:
    """A mock ArduCopter on MAVLink 2, run by a background thread.

    Args:
        home: (lat deg, lon deg, alt m AMSL); also the local NED origin.
        endpoints: "udpout:HOST:PORT" (send to a listening client, like SITL --out),
            "udpin:HOST:PORT" (listen; replies go to the last sender) and
            "tcpin:HOST:PORT" (TCP server; every accepted client is its own link);
            loopback hosts only; port 0 picks a free port (see `endpoints`).
        speedup: autopilot seconds per wall second.
        physics_hz: model step rate on the autopilot clock.
        params: parameter overrides, ArduPilot units (e.g. {"WPNAV_SPEED": 500}); the
            stream rates of endpoint n (its "serial port") are SRn_EXT_STAT, SRn_POSITION,
            SRn_EXTRA1..3 (Hz, 0 by default: only HEARTBEAT is sent unasked, as ArduCopter
            SITL does). Streamable: HEARTBEAT, SYS_STATUS, GPS_RAW_INT, EXTENDED_SYS_STATE,
            GLOBAL_POSITION_INT, LOCAL_POSITION_NED, ATTITUDE, VFR_HUD, SYSTEM_TIME,
            BATTERY_STATUS, EKF_STATUS_REPORT, HOME_POSITION, GPS_GLOBAL_ORIGIN,
            AUTOPILOT_VERSION, POSITION_TARGET_LOCAL_NED, POSITION_TARGET_GLOBAL_INT. Clients
            change them per link with SET_MESSAGE_INTERVAL and REQUEST_DATA_STREAM.
        boot: when the GPS, the EKF origin and arming become ready (``BootTimeline``: ArduCopter
            4.4's by default; ``BootTimeline.scaled(s)`` for a shorter wait).
        seed: seed of the position-noise generator; pos_noise: m/sqrt(s), 0 disables.
        unix_time0: UNIX time (s) at boot for SYSTEM_TIME; default: wall clock at start.
        signing_key: 32-byte MAVLink 2 signing key (onboard/app/signing.py): every link signs
            what it sends and drops unsigned or wrongly signed packets (counted
            ``signing_rejected``), like ArduPilot with a key set.
        max_lag_s: autopilot seconds the model may fall behind the wall clock before the
            clock slips (counted ``clock_slips``) instead of catching up. ArduPilot SITL runs
            slower than --speedup when the machine cannot keep up; set this small (e.g. 0.1)
            to behave the same on a loaded machine.
    """

    def __init__(
        self,
        home: tuple[float, float, float] = (-35.363261, 149.165230, 584.0),
        endpoints: Iterable[str | Endpoint] = ("tcpin:127.0.0.1:5760",),
        speedup: float = 1.0,
        physics_hz: float = 50.0,
        params: Mapping[str, float] = {},
        seed: int = 0,
        pos_noise: float = 0.02,
        unix_time0: Optional[float] = None,
        sysid: int = 1,
        compid: int = mavlink.MAV_COMP_ID_AUTOPILOT1,
        signing_key: Optional[bytes] = None,
        max_lag_s: float = 10.0,
        boot: BootTimeline = BootTimeline(),
    ):
        if not speedup > 0 or not physics_hz > 0:
            raise ValueError("speedup and physics_hz must be positive")
        self.sysid = sysid
        self.compid = compid
        self.speedup = float(speedup)
        self.max_lag_s = float(max_lag_s)
        self.signing_key = signing_key
        self._link_ids = 0
        self.dt = 1.0 / physics_hz
        self._endpoints = [e if isinstance(e, Endpoint) else Endpoint.parse(e) for e in endpoints]
        for ep in self._endpoints:
            _check_loopback(ep.host)
        self.params = Params(overrides=params)
        self.copter = Copter(home, self.params, np.random.default_rng(seed), pos_noise, boot)
        self._origin_sent = False
        self.crashed: str | None = None  # why the mock went silent like the crashed firmware
        self._unix_time0 = unix_time0
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._links: list[_Link] = []
        self._listeners: list[_TcpListener] = []
        self._bound: list[Endpoint] = []
        self._routes: set[tuple[int, int, _Link]] = set()
        self._counters: dict[str, int] = {}
        self._wall0 = 0.0
        self._encoder = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self._replies: list = []  # messages to send after the COMMAND_ACK being built
        self._msg_builders: dict[str, Callable[[_Link], Optional[object]]] = {
            "HEARTBEAT": self._heartbeat,
            "SYS_STATUS": self._sys_status,
            "GPS_RAW_INT": self._gps_raw_int,
            "EXTENDED_SYS_STATE": self._extended_sys_state,
            "GLOBAL_POSITION_INT": self._global_position_int,
            "LOCAL_POSITION_NED": self._local_position_ned,
            "ATTITUDE": self._attitude,
            "VFR_HUD": self._vfr_hud,
            "SYSTEM_TIME": self._system_time,
            "BATTERY_STATUS": self._battery_status,
            "EKF_STATUS_REPORT": self._ekf_status_report,
            "HOME_POSITION": self._home_position,
            "GPS_GLOBAL_ORIGIN": self._gps_global_origin,
            "AUTOPILOT_VERSION": self._autopilot_version,
            "POSITION_TARGET_LOCAL_NED": self._position_target_local_ned,
            "POSITION_TARGET_GLOBAL_INT": self._position_target_global_int,
        }

    # ----- lifecycle
    def start(self) -> "MockAutopilot":
        """Bind every endpoint (raises OSError if a port is taken) and start the thread."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._bound = []
        try:
            self._open_endpoints()
        except Exception:
            self._close_all()
            raise
        self._wall0 = time.monotonic()
        if self._unix_time0 is None:
            self._unix_time0 = time.time()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="mock-autopilot", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close every socket (ports are free when this returns)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._close_all()

    def __enter__(self) -> "MockAutopilot":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def run_forever(self) -> None:
        """Run until stop() is called from another thread or a signal handler."""
        self.start()
        try:
            while not self._stop.wait(0.2):
                pass
        finally:
            self.stop()

    # ----- public observers
    @property
    def endpoints(self) -> list[Endpoint]:
        """The endpoints as bound (port 0 replaced by the port actually chosen)."""
        return list(self._bound)

    def port(self, kind: str, index: int = 0) -> int:
        """Bound port of the index-th endpoint of a kind ('udpout' gives its target port)."""
        return [e for e in self._bound if e.kind == kind][index].port

    @property
    def sim_time(self) -> float:
        """Autopilot time since boot, s."""
        with self._lock:
            return self.copter.t

    def state(self) -> AutopilotState:
        with self._lock:
            c = self.copter
            s = c.state
            lat, lon, alt = c.geodetic_from_ned(s.pos)
            return AutopilotState(
                time_boot_ms=int(c.t * 1000),
                mode=int(c.mode),
                mode_name=c.mode.name,
                armed=c.armed,
                landed_state=c.landed_state(),
                pos_ned=s.pos,
                vel_ned=s.vel,
                pos_enu=(s.pos[1], s.pos[0], -s.pos[2]),
                vel_enu=(s.vel[1], s.vel[0], -s.vel[2]),
                yaw=s.yaw,
                lat=lat,
                lon=lon,
                alt_amsl=alt,
                alt_rel=c.alt_above_home(),
            )

    def counters(self) -> dict[str, int]:
        """Copy of the event counters (rx, tx, bad_data, unknown_msgid, forwarded, ...)."""
        with self._lock:
            return dict(self._counters)

    def routes(self) -> set[tuple[int, int, str]]:
        """Learned routes as (sysid, compid, link name)."""
        with self._lock:
            return {(s, c, link.name) for s, c, link in self._routes}

    def wait_until(self, predicate: Callable[[AutopilotState], bool], timeout: float) -> bool:
        """Poll state() until predicate holds or `timeout` wall seconds pass."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate(self.state()):
                return True
            time.sleep(0.01)
        return predicate(self.state())

    # ----- plumbing
    def _count(self, key: str, n: int = 1) -> None:
        self._counters[key] = self._counters.get(key, 0) + n

    def _default_intervals(self, port: int) -> dict[str, float]:
        """Stream intervals (sim s) of a new link on endpoint ``port``: a HEARTBEAT a second,
        and the groups its SRn_ parameters turn on (ArduPilot's stream rates per serial port)."""
        out = dict(ALWAYS_INTERVALS_S)
        for group, stream in SR_GROUPS.items():
            name = f"SR{port}_{group}"
            hz = self.params[name] if name in self.params else 0.0
            for msg in DATA_STREAMS[stream]:
                if hz > 0:
                    out[msg] = 1.0 / hz
        return out

    def _open_endpoints(self) -> None:
        for index, ep in enumerate(self._endpoints):
            if ep.kind == "tcpin":
                lst = _TcpListener(ep, index)
                self._listeners.append(lst)
                self._bound.append(Endpoint("tcpin", ep.host, lst.local[1]))
            else:
                link = self._secure(_UdpLink(ep, self.sysid, self.compid, self._default_intervals(index)))
                link.port_index = index
                self._links.append(link)
                port = link.local[1] if ep.kind == "udpin" else ep.port
                self._bound.append(Endpoint(ep.kind, ep.host, port))

    def _close_all(self) -> None:
        for link in self._links:
            link.close()
        for lst in self._listeners:
            lst.close()
        self._links = []
        self._listeners = []
        self._routes.clear()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._iterate()
            except Exception:  # never let one bad iteration kill the autopilot
                with self._lock:
                    self._count("loop_errors")
                log.exception("mock autopilot loop error")
                time.sleep(0.01)

    def _iterate(self) -> None:
        sim_now = (time.monotonic() - self._wall0) * self.speedup
        with self._lock:
            steps = 0
            while self.copter.t + self.dt <= sim_now and steps < 500:
                self.copter.tick(self.dt)
                steps += 1
            if steps == 500:  # far behind (debugger, overload): skip instead of spiralling
                self._count("clock_skips")
                self._wall0 = time.monotonic() - self.copter.t / self.speedup
            elif sim_now - self.copter.t > self.max_lag_s:  # SITL-like: run slower, never jump
                self._count("clock_slips")
                self._wall0 = time.monotonic() - self.copter.t / self.speedup
            now_t = self.copter.t
            for link in self._links:
                link.muted = now_t < link.muted_until
            if not self._origin_sent and self.copter.origin_set:
                self._origin_sent = True  # ArduPilot tells every link when its EKF origin is set
                self.copter.text(mavlink.MAV_SEVERITY_INFO, "EKF3 IMU0 origin set")
                for lk in self._links:
                    lk.send(self._gps_global_origin(lk))
                    lk.send(self._home_position(lk))
            self._flush_events()
            self._send_streams()
            for link in self._links:
                link.flush()
        next_step_wall = self._wall0 + (self.copter.t + self.dt) / self.speedup
        timeout = min(max(next_step_wall - time.monotonic(), 0.0), 0.02)
        socks = [*self._links, *self._listeners]
        try:
            readable, _, _ = select.select(socks, [], [], timeout)
        except (OSError, ValueError):
            readable = []  # a socket closed under us; the next iteration drops it
        with self._lock:
            for obj in readable:
                if isinstance(obj, _TcpListener):
                    self._accept(obj)
                else:
                    self._read_link(obj)
            dead = [link for link in self._links if link.closed]
            for link in dead:
                self._links.remove(link)
                self._routes = {r for r in self._routes if r[2] is not link}
                self._count("links_closed")

    def _accept(self, lst: _TcpListener) -> None:
        got = lst.accept()
        if got is None:
            return
        sock, addr = got
        name = f"tcpin:{lst.local[0]}:{lst.local[1]}<-{addr[0]}:{addr[1]}"
        link = self._secure(_TcpLink(sock, name, self.sysid, self.compid,
                                     self._default_intervals(lst.index)))
        link.port_index = lst.index
        self._links.append(link)
        self._count("links_opened")

    def _secure(self, link: _Link) -> _Link:
        if self.signing_key is not None:
            from onboard.app.signing import configure
            self._link_ids += 1
            configure(link.parser, self.signing_key, self._link_ids, sign_outgoing=False)
            configure(link.out, self.signing_key, self._link_ids)
        return link

    def _crash(self, why: str) -> None:
        """A defect the real firmware dies of: counted, logged, and the mock falls silent and
        drops every link (the process of a crashed SITL is gone)."""
        self._count("defects")
        self.crashed = why
        log.error("mock autopilot: defect that crashes ArduCopter 4.4: %s", why)
        for lk in self._links:
            lk.flush()
            lk.close()
        self._stop.set()

    # ----- fault injection (tests)
    def _links_of(self, compid: int) -> list[_Link]:
        return [link for s, c, link in self._routes if c == compid]

    def cut_link(self, compid: int, seconds: float) -> int:
        """The link(s) a component is reached on go dead both ways for ``seconds`` of
        autopilot time (a radio out of range): nothing is read or written, the TCP connection
        stays up. Returns the number of links cut."""
        with self._lock:
            links = self._links_of(compid)
            for link in links:
                link.muted_until = self.copter.t + seconds
                link.muted = True
            return len(links)

    def drop_link(self, compid: int) -> int:
        """Close the link(s) of a component (a TCP client must reconnect)."""
        with self._lock:
            links = self._links_of(compid)
            for link in links:
                link.close()
            return len(links)

    def _read_link(self, link: _Link) -> None:
        data = link.receive()
        if not data or link.muted:
            return
        rejected = link.parser.signing.reject_count
        try:
            msgs = link.parser.parse_buffer(data) or []
        except Exception:  # pymavlink raises on some malformed frames even when robust
            self._count("bad_data")
            return
        finally:
            if link.parser.signing.reject_count != rejected:
                self._count("signing_rejected", link.parser.signing.reject_count - rejected)
        for msg in msgs:
            try:
                self._on_message(link, msg)
            except Exception:
                self._count("handler_errors")
                log.exception("error handling %s", getattr(msg, "get_type", lambda: "?")())

    # ----- routing (ArduPilot's MAVLink_routing::check_and_forward)
    def _on_message(self, link: _Link, msg) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self._count("bad_data")
            return
        if isinstance(msg, mavlink.MAVLink_unknown) or mtype.startswith("UNKNOWN"):
            self._count("unknown_msgid")  # CRC cannot be checked: ArduPilot drops these
            return
        self._count("rx")
        link.active = True
        sysid, compid = msg.get_srcSystem(), msg.get_srcComponent()
        if (sysid, compid) == (self.sysid, self.compid):
            self._count("loopback")  # our own packets echoed back: ignore
            return
        if sysid != 0:
            self._routes.add((sysid, compid, link))
        if mtype in ("RADIO", "RADIO_STATUS"):
            self._handle(link, msg)
            return
        raw = msg.get_msgbuf()
        if mtype == "HEARTBEAT":
            for other in self._links:
                if (other is not link and other.active
                        and (sysid, compid, other) not in self._routes):
                    other.write(raw)
                    self._count("forwarded")
            self._handle(link, msg)
            return
        tsys = getattr(msg, "target_system", -1)
        tcomp = getattr(msg, "target_component", -1)
        bcast_sys = tsys in (0, -1)
        bcast_comp = tcomp in (0, -1)
        match_sys = bcast_sys or tsys == self.sysid
        local = match_sys and (bcast_comp or tcomp == self.compid)
        if local and not bcast_sys and not bcast_comp:
            self._handle(link, msg)
            return
        sent_to: set[int] = set()
        for rsys, rcomp, other in list(self._routes):
            if other is link or id(other) in sent_to:
                continue
            if bcast_sys or (rsys == tsys and (bcast_comp or rcomp == tcomp or not match_sys)):
                other.write(raw)
                sent_to.add(id(other))
                self._count("forwarded")
        if not sent_to and match_sys:
            local = True
        if local:
            self._handle(link, msg)

    # ----- local handling
    def _handle(self, link: _Link, msg) -> None:
        handler = getattr(self, "_on_" + msg.get_type().lower(), None)
        if handler is None:
            self._count("ignored")
            return
        handler(link, msg)

    def _ack(self, link: _Link, msg, command: int, result: int) -> None:
        link.send(self._enc().command_ack_encode(
            command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        self._count(f"ack_{mavlink.enums['MAV_RESULT'][result].name[11:].lower()}")

    def _enc(self) -> mavlink.MAVLink:
        """The message constructor (links do the packing and sequence numbers)."""
        return self._encoder

    def _broadcast(self, msg) -> None:
        for link in self._links:
            link.send(msg)

    def _flush_events(self) -> None:
        for severity, text in self.copter.events:
            self._broadcast(self._enc().statustext_encode(severity, text.encode()[:50]))
        self.copter.events.clear()

    def _on_heartbeat(self, link: _Link, msg) -> None:
        pass  # routes are learned in _on_message; GCS failsafe is not modelled

    def _on_timesync(self, link: _Link, msg) -> None:
        if msg.tc1 == 0:  # a request: answer with our clock (ns since boot)
            link.send(self._enc().timesync_encode(
                int(self.copter.t * 1e9), msg.ts1, msg.get_srcSystem(), msg.get_srcComponent()))

    def _on_autopilot_version_request(self, link: _Link, msg) -> None:
        link.send(self._autopilot_version(link))

    def _on_request_data_stream(self, link: _Link, msg) -> None:
        hz = msg.req_message_rate if msg.start_stop else 0
        ids = list(DATA_STREAMS) if msg.req_stream_id == mavlink.MAV_DATA_STREAM_ALL else [
            msg.req_stream_id]
        for sid in ids:
            for name in DATA_STREAMS.get(sid, ()):
                self._set_interval(link, name, 1.0 / hz if hz > 0 else 0.0)

    def _set_interval(self, link: _Link, name: str, interval_s: float) -> None:
        link.intervals[name] = interval_s
        link.next_due[name] = self.copter.t  # start the new rate now

    def _on_set_mode(self, link: _Link, msg) -> None:
        result = self._set_mode_common(msg.base_mode, msg.custom_mode)
        self._ack(link, msg, mavlink.MAV_CMD_DO_SET_MODE, result)

    def _set_mode_common(self, base_mode: int, custom_mode: int) -> int:
        if int(base_mode) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            ok = self.copter.set_mode(int(custom_mode))
            return mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_FAILED
        return mavlink.MAV_RESULT_DENIED

    # ----- commands
    def _on_command_long(self, link: _Link, msg) -> None:
        self._count("commands")
        cmd = _Command(msg.command, (msg.param1, msg.param2, msg.param3, msg.param4),
                       msg.param5, msg.param6, msg.param7, None,
                       msg.get_srcSystem(), msg.get_srcComponent())
        self._run_command(link, msg, cmd)

    def _on_command_int(self, link: _Link, msg) -> None:
        self._count("commands")
        cmd = _Command(msg.command, (msg.param1, msg.param2, msg.param3, msg.param4),
                       msg.x, msg.y, msg.z, msg.frame,
                       msg.get_srcSystem(), msg.get_srcComponent())
        self._run_command(link, msg, cmd)

    def _run_command(self, link: _Link, msg, cmd: _Command) -> None:
        if cmd.frame is None and cmd.command in LONG_AS_INT and self.copter.armed and not (
                math.isfinite(cmd.x) and math.isfinite(cmd.y)):
            # ArduCopter 4.4, armed, converts these COMMAND_LONGs to COMMAND_INT, param5/6 * 1e7
            # to int32: NaN aborts the firmware before it answers (measured on its SITL; when
            # disarmed it answers FAILED and lives)
            self._crash(f"floating point exception: {mavlink.enums['MAV_CMD'][cmd.command].name} "
                        f"with latitude/longitude {cmd.x}, {cmd.y} from {cmd.sysid}/{cmd.compid}")
            return
        # Like ArduPilot, the ACK goes out first and requested messages after it.
        self._replies = []
        try:
            result = self._command(link, cmd)
        except (ValueError, OverflowError):  # e.g. NaN where an integer is expected
            self._count("command_errors")
            self._replies = []
            result = mavlink.MAV_RESULT_FAILED
        self._ack(link, msg, cmd.command, result)
        for reply in self._replies:
            link.send(reply)
        self._replies = []

    def _command(self, link: _Link, cmd: _Command) -> int:
        """Run a command; returns the MAV_RESULT ArduCopter 4.5 would answer."""
        m = mavlink
        c = self.copter
        p1, p2, p3, p4 = cmd.params
        ok = lambda b: m.MAV_RESULT_ACCEPTED if b else m.MAV_RESULT_FAILED  # noqa: E731
        if cmd.command == m.MAV_CMD_COMPONENT_ARM_DISARM:
            if p1 == 1.0:
                return ok(c.arm(force=p2 == MAGIC_FORCE_ARM))
            if p1 == 0.0:
                return ok(c.disarm(force=p2 == MAGIC_FORCE_DISARM))
            return m.MAV_RESULT_UNSUPPORTED
        if cmd.command == m.MAV_CMD_NAV_TAKEOFF:
            if cmd.frame is not None and cmd.frame != m.MAV_FRAME_GLOBAL_RELATIVE_ALT:
                return m.MAV_RESULT_DENIED
            return ok(c.takeoff(cmd.z))
        if cmd.command == m.MAV_CMD_DO_SET_MODE:
            return self._set_mode_common(int(p1), int(p2))
        if cmd.command == m.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return ok(c.set_mode(Mode.RTL))
        if cmd.command == m.MAV_CMD_NAV_LAND:
            return ok(c.set_mode(Mode.LAND))
        if cmd.command == m.MAV_CMD_NAV_LOITER_UNLIM:
            return ok(c.set_mode(Mode.LOITER))
        if cmd.command == m.MAV_CMD_DO_REPOSITION:
            if cmd.frame is None:
                return m.MAV_RESULT_UNSUPPORTED  # ArduPilot takes it as COMMAND_INT only
            return self._do_reposition(cmd)
        if cmd.command == m.MAV_CMD_REQUEST_MESSAGE:
            return self._request_message(link, int(p1))
        if cmd.command == m.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_message_interval(link, int(p1), p2)
        if cmd.command == m.MAV_CMD_GET_MESSAGE_INTERVAL:
            return self._get_message_interval(link, int(p1))
        if cmd.command == m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            if p1 != 1.0:
                return m.MAV_RESULT_FAILED
            self._replies.append(self._autopilot_version(link))
            return m.MAV_RESULT_ACCEPTED
        if cmd.command == m.MAV_CMD_GET_HOME_POSITION:
            self._replies.append(self._home_position(link))
            self._replies.append(self._gps_global_origin(link))
            return m.MAV_RESULT_ACCEPTED
        if cmd.command == m.MAV_CMD_CONDITION_YAW:
            if 0.0 <= p1 <= 360.0 and p4 in (0.0, 1.0):
                target = math.radians(p1) + (c.state.yaw if p4 == 1.0 else 0.0)
                c.fixed_yaw = vehicle.wrap_pi(target)
                return m.MAV_RESULT_ACCEPTED
            return m.MAV_RESULT_FAILED
        if cmd.command == m.MAV_CMD_DO_CHANGE_SPEED:
            if not p2 > 0.0:
                return m.MAV_RESULT_DENIED
            key = {0: "xy", 1: "xy", 2: "up", 3: "down"}.get(int(p1))
            if key is None:
                return m.MAV_RESULT_DENIED
            c.speed[key] = p2
            return m.MAV_RESULT_ACCEPTED
        if cmd.command == m.MAV_CMD_DO_SET_HOME:
            return self._do_set_home(cmd)
        if cmd.command == m.MAV_CMD_DO_SEND_BANNER:
            self._banner(link)
            return m.MAV_RESULT_ACCEPTED
        if cmd.command == m.MAV_CMD_RUN_PREARM_CHECKS:
            return m.MAV_RESULT_TEMPORARILY_REJECTED if c.armed else m.MAV_RESULT_ACCEPTED
        if cmd.command == m.MAV_CMD_DO_FLIGHTTERMINATION:
            if p1 > 0.5:
                c.disarm(force=True, reason=" (flight termination)")
                return m.MAV_RESULT_ACCEPTED
            return m.MAV_RESULT_FAILED
        if cmd.command == m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN:
            # A mock cannot reboot; refuse the way ArduPilot refuses when armed.
            return m.MAV_RESULT_FAILED if c.armed else m.MAV_RESULT_UNSUPPORTED
        return m.MAV_RESULT_UNSUPPORTED

    def _location_to_ned(self, lat_e7: float, lon_e7: float, alt: float,
                         frame: int) -> Optional[Vec3]:
        """Target location (degE7, m in frame) -> local NED; None for unknown frames."""
        if frame in _ABSOLUTE_FRAMES:
            alt_amsl = alt
        elif frame in _RELATIVE_FRAMES or frame in _TERRAIN_FRAMES:
            alt_amsl = self.copter.home[2] + alt  # flat terrain at home altitude
        else:
            return None
        return self.copter.ned_from_geodetic(lat_e7 * 1e-7, lon_e7 * 1e-7, alt_amsl)

    def _do_reposition(self, cmd: _Command) -> int:
        """GCS_MAVLINK_Copter::handle_command_int_do_reposition."""
        m = mavlink
        c = self.copter
        change_mode = int(cmd.params[1]) & m.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE
        if c.mode != Mode.GUIDED and not change_mode:
            return m.MAV_RESULT_DENIED
        if not _check_latlng(cmd.x, cmd.y):
            return m.MAV_RESULT_DENIED
        if cmd.x == 0 and cmd.y == 0:
            return m.MAV_RESULT_DENIED  # Location::sanitize would change it
        if cmd.z == 0 and cmd.frame in _RELATIVE_FRAMES:
            return m.MAV_RESULT_DENIED
        ned = self._location_to_ned(cmd.x, cmd.y, cmd.z, cmd.frame)
        if ned is None:
            return m.MAV_RESULT_DENIED
        if c.mode != Mode.GUIDED and not c.set_mode(Mode.GUIDED):
            return m.MAV_RESULT_FAILED
        c.set_guided(GuidedTarget("pos", pos=ned))
        return m.MAV_RESULT_ACCEPTED

    def _do_set_home(self, cmd: _Command) -> int:
        m = mavlink
        p1 = cmd.params[0]
        if p1 == 1.0 or (cmd.x == 0 and cmd.y == 0):
            self.copter.set_home(None)
            return m.MAV_RESULT_ACCEPTED
        if p1 != 0.0:
            return m.MAV_RESULT_FAILED
        if cmd.frame is None:  # COMMAND_LONG: degrees, AMSL
            lat, lon, alt = cmd.x, cmd.y, cmd.z
        else:
            lat, lon = cmd.x * 1e-7, cmd.y * 1e-7
            if cmd.frame in _ABSOLUTE_FRAMES:
                alt = cmd.z
            elif cmd.frame in _RELATIVE_FRAMES:
                alt = self.copter.home[2] + cmd.z
            else:
                return m.MAV_RESULT_DENIED
        if not _check_latlng(lat * 1e7, lon * 1e7):
            return m.MAV_RESULT_FAILED
        self.copter.set_home((lat, lon, alt))
        return m.MAV_RESULT_ACCEPTED

    def _msg_name(self, msgid: int) -> Optional[str]:
        cls = mavlink.mavlink_map.get(msgid)
        name = cls.msgname if cls is not None else None
        return name if name in self._msg_builders else None

    def _request_message(self, link: _Link, msgid: int) -> int:
        name = self._msg_name(msgid)
        if name is None:
            if msgid == mavlink.MAVLINK_MSG_ID_PARAM_VALUE:
                return mavlink.MAV_RESULT_ACCEPTED  # ArduPilot: "send the next param"; no-op
            return mavlink.MAV_RESULT_FAILED
        msg = self._msg_builders[name](link)
        if msg is not None:
            self._replies.append(msg)
        return mavlink.MAV_RESULT_ACCEPTED

    def _set_message_interval(self, link: _Link, msgid: int, interval_us: float) -> int:
        name = self._msg_name(msgid)
        if interval_us == 0:  # back to the default rate
            if name is None:
                return mavlink.MAV_RESULT_FAILED
            self._set_interval(link, name, self._default_intervals(link.port_index).get(name, 0.0))
            return mavlink.MAV_RESULT_ACCEPTED
        if name is None:
            self.copter.text(mavlink.MAV_SEVERITY_INFO, f"No ap_message for mavlink id ({msgid})")
            return mavlink.MAV_RESULT_DENIED
        if interval_us < 0:
            self._set_interval(link, name, 0.0)
        else:
            self._set_interval(link, name, max(interval_us, 1000.0) * 1e-6)
        return mavlink.MAV_RESULT_ACCEPTED

    def _get_message_interval(self, link: _Link, msgid: int) -> int:
        name = self._msg_name(msgid)
        if name is None:
            self._replies.append(self._enc().message_interval_encode(msgid, 0))
            return mavlink.MAV_RESULT_FAILED
        iv = link.intervals.get(name, 0.0)
        interval_us = int(iv * 1e6) if iv > 0 else -1
        self._replies.append(self._enc().message_interval_encode(msgid, interval_us))
        return mavlink.MAV_RESULT_ACCEPTED

    # ----- parameters
    def _param_value(self, name: str):
        return self._enc().param_value_encode(
            name.encode(), self.params[name], self.params.ptype(name), len(self.params),
            self.params.index(name))

    def _on_param_request_list(self, link: _Link, msg) -> None:
        self._banner(link)
        for name in self.params.names():
            link.send(self._param_value(name))

    def _on_param_request_read(self, link: _Link, msg) -> None:
        names = self.params.names()
        if msg.param_index >= 0:
            name = names[msg.param_index] if msg.param_index < len(names) else None
        else:
            name = _param_name(msg.param_id)
        if name is None or name not in self.params:
            self._count("param_unknown")
            link.send(self._enc().statustext_encode(
                mavlink.MAV_SEVERITY_WARNING,
                f"Unknown parameter {_param_name(msg.param_id) or msg.param_index}".encode()[:50]))
            return
        link.send(self._param_value(name))

    def _on_param_set(self, link: _Link, msg) -> None:
        name = _param_name(msg.param_id)
        if name not in self.params:
            self._count("param_unknown")
            link.send(self._enc().statustext_encode(
                mavlink.MAV_SEVERITY_WARNING, f"Unknown parameter {name}".encode()[:50]))
            return
        if self.params.set(name, float(msg.param_value)):
            self._count("param_set")
            self.copter.params_changed()
            if name.startswith("SR") and "_" in name:  # a port's stream rates: at once
                for lk in self._links:
                    if name.startswith(f"SR{lk.port_index}_"):
                        for msg_name, iv in self._default_intervals(lk.port_index).items():
                            self._set_interval(lk, msg_name, iv)
        self._broadcast(self._param_value(name))  # ArduPilot tells every link

    # ----- missions: an empty mission, fence and rally
    def _on_mission_request_list(self, link: _Link, msg) -> None:
        link.send(self._enc().mission_count_encode(
            msg.get_srcSystem(), msg.get_srcComponent(), 0, getattr(msg, "mission_type", 0)))

    def _mission_nack(self, link: _Link, msg, result: int) -> None:
        link.send(self._enc().mission_ack_encode(
            msg.get_srcSystem(), msg.get_srcComponent(), result,
            getattr(msg, "mission_type", 0)))

    def _on_mission_request_int(self, link: _Link, msg) -> None:
        self._mission_nack(link, msg, mavlink.MAV_MISSION_INVALID_SEQUENCE)

    _on_mission_request = _on_mission_request_int

    def _on_mission_clear_all(self, link: _Link, msg) -> None:
        self._mission_nack(link, msg, mavlink.MAV_MISSION_ACCEPTED)

    def _on_mission_count(self, link: _Link, msg) -> None:
        # Uploading an empty list is fine; storing missions is not modelled.
        result = mavlink.MAV_MISSION_ACCEPTED if msg.count == 0 else mavlink.MAV_MISSION_UNSUPPORTED
        self._mission_nack(link, msg, result)

    def _on_mission_set_current(self, link: _Link, msg) -> None:
        self._mission_nack(link, msg, mavlink.MAV_MISSION_INVALID_SEQUENCE)

    # ----- MAVLink FTP: a vehicle without files
    def _on_file_transfer_protocol(self, link: _Link, msg) -> None:
        """Answer every FTP request at once so clients (MAVProxy fetches parameters over FTP
        first) fall back to PARAM_REQUEST_LIST instead of waiting for a timeout."""
        payload = bytes(msg.payload)
        if len(payload) < 12:
            return
        seq = int.from_bytes(payload[0:2], "little")
        session, opcode = payload[2], payload[3]
        if opcode in (_FTP_TERMINATE_SESSION, _FTP_RESET_SESSIONS):
            reply_op, size, data = _FTP_ACK, 0, b""
        else:
            code = _FTP_ERR_FILE_NOT_FOUND if opcode in _FTP_OPEN_OPS else _FTP_ERR_INVALID_SESSION
            reply_op, size, data = _FTP_NAK, 1, bytes([code])
        header = (((seq + 1) & 0xFFFF).to_bytes(2, "little")
                  + bytes([session, reply_op, size, opcode, 0, 0]) + payload[8:12])
        body = (header + data).ljust(251, b"\x00")
        link.send(self._enc().file_transfer_protocol_encode(
            0, msg.get_srcSystem(), msg.get_srcComponent(), list(body)))

    # ----- position targets (GCS_MAVLINK_Copter::handle_message_set_position_target_*)
    def _on_set_position_target_local_ned(self, link: _Link, msg) -> None:
        c = self.copter
        if c.mode != Mode.GUIDED:
            self._count("setpoint_ignored")
            return
        mask = msg.type_mask
        if msg.coordinate_frame not in _LOCAL_FRAMES:
            return self._reject_setpoint()
        body = msg.coordinate_frame in _BODY_FRAMES
        offset = msg.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED
        yaw_now = c.state.yaw

        def rotate(v: Vec3) -> Vec3:
            if not body:
                return v
            cy, sy = math.cos(yaw_now), math.sin(yaw_now)
            return (v[0] * cy - v[1] * sy, v[0] * sy + v[1] * cy, v[2])

        pos = vel = acc = None
        if not mask & _POS_IGNORE:
            pos = rotate((msg.x, msg.y, msg.z))
            if offset:
                pos = tuple(a + b for a, b in zip(pos, c.state.pos))
        if not mask & _VEL_IGNORE:
            vel = rotate((msg.vx, msg.vy, msg.vz))
        if not mask & _ACC_IGNORE:
            acc = rotate((msg.afx, msg.afy, msg.afz))
        yaw = None if mask & _YAW_IGNORE else msg.yaw + (yaw_now if body else 0.0)
        yaw_rate = None if mask & _YAW_RATE_IGNORE else msg.yaw_rate
        self._apply_setpoint(mask, pos, vel, acc, yaw, yaw_rate)

    def _on_set_position_target_global_int(self, link: _Link, msg) -> None:
        c = self.copter
        if c.mode != Mode.GUIDED:
            self._count("setpoint_ignored")
            return
        mask = msg.type_mask
        pos = vel = acc = None
        if not mask & _POS_IGNORE:
            if not _check_latlng(msg.lat_int, msg.lon_int):
                return self._reject_setpoint()
            if msg.coordinate_frame in _TERRAIN_FRAMES and not mask & _VEL_IGNORE:
                return self._reject_setpoint()  # posvel does not take terrain altitudes
            pos = self._location_to_ned(msg.lat_int, msg.lon_int, msg.alt, msg.coordinate_frame)
            if pos is None:
                return self._reject_setpoint()
        if not mask & _VEL_IGNORE:
            vel = (msg.vx, msg.vy, msg.vz)
        if not mask & _ACC_IGNORE:
            acc = (msg.afx, msg.afy, msg.afz)
        yaw = None if mask & _YAW_IGNORE else msg.yaw
        yaw_rate = None if mask & _YAW_RATE_IGNORE else msg.yaw_rate
        self._apply_setpoint(mask, pos, vel, acc, yaw, yaw_rate)

    def _apply_setpoint(self, mask: int, pos, vel, acc, yaw, yaw_rate) -> None:
        """Pick the GUIDED sub-mode from the type_mask exactly as ArduCopter does."""
        if mask & _FORCE_SET and acc is not None:
            return self._reject_setpoint()  # force inputs are not supported
        if vel is not None and not _sane_vector(vel):
            return self._reject_setpoint()
        if acc is not None and not all(math.isfinite(a) for a in acc):
            return self._reject_setpoint()
        if pos is not None and not all(math.isfinite(p) for p in pos):
            return self._reject_setpoint()
        if yaw is not None and not math.isfinite(yaw):
            yaw = None
        if yaw_rate is not None and not math.isfinite(yaw_rate):
            yaw_rate = None
        zero = (0.0, 0.0, 0.0)
        if pos is not None and vel is not None:
            target = GuidedTarget("posvel", pos=pos, vel=vel, acc=acc or zero)
        elif pos is None and vel is not None:
            target = GuidedTarget("vel", vel=vel, acc=acc)
        elif pos is None and vel is None and acc is not None:
            target = GuidedTarget("accel", acc=acc)
        elif pos is not None and vel is None and acc is None:
            target = GuidedTarget("pos", pos=pos)
        else:
            return self._reject_setpoint()  # e.g. pos+accel, or nothing at all
        self.copter.set_guided(replace(target, yaw=yaw, yaw_rate=yaw_rate))
        self._count("setpoint_accepted")

    def _reject_setpoint(self) -> None:
        self.copter.guided_hold()
        self._count("setpoint_rejected")

    # ----- outgoing messages
    def _send_streams(self) -> None:
        now = self.copter.t
        for link in self._links:
            for name, interval in link.intervals.items():
                if interval <= 0.0:
                    continue
                due = link.next_due.get(name, 0.0)
                if now + 1e-9 < due:
                    continue
                due += interval
                link.next_due[name] = due if due > now else now + interval
                builder = self._msg_builders.get(name)
                msg = builder(link) if builder is not None else None
                if msg is not None:
                    link.send(msg)
                    self._count("tx")

    def _time_ms(self) -> int:
        return int(self.copter.t * 1000) & 0xFFFFFFFF

    def _base_mode(self) -> int:
        c = self.copter
        base = (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
                | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED)
        if c.mode not in (Mode.STABILIZE, Mode.ALT_HOLD):
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED  # position control active
        if c.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        return base

    def _heartbeat(self, link: _Link):
        c = self.copter
        status = mavlink.MAV_STATE_STANDBY if c.land_complete else mavlink.MAV_STATE_ACTIVE
        return self._enc().heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, self._base_mode(),
            int(c.mode), status)

    def _battery(self) -> tuple[int, int, int]:
        """(voltage mV, current cA, remaining %) of a 3S pack."""
        cap = max(self.params["BATT_CAPACITY"], 1.0)
        remaining = max(0.0, 1.0 - self.copter.battery_used_mah / cap)
        volts = 10.5 + 2.1 * remaining
        current = 15.0 if self.copter.armed and not self.copter.land_complete else 0.3
        return int(volts * 1000), int(current * 100), int(round(remaining * 100))

    def _sys_status(self, link: _Link):
        mv, ca, pct = self._battery()
        # GEOFENCE is reported healthy while not breached even with no fence (as ArduPilot);
        # the pre-arm bit only once arming would pass
        health = SENSORS | mavlink.MAV_SYS_STATUS_GEOFENCE
        if not self.copter.prearm_bit:
            health &= ~mavlink.MAV_SYS_STATUS_PREARM_CHECK
        return self._enc().sys_status_encode(SENSORS, SENSORS, health, 150, mv, ca, pct,
                                             0, 0, 0, 0, 0, 0)

    def _battery_status(self, link: _Link):
        mv, ca, pct = self._battery()
        voltages = [mv] + [65535] * 9
        return self._enc().battery_status_encode(
            0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 32767, voltages,
            ca, int(self.copter.battery_used_mah), -1, pct)

    def _geo(self) -> tuple[float, float, float]:
        return self.copter.geodetic_from_ned(self.copter.state.pos)

    def _gps_raw_int(self, link: _Link):
        lat, lon, alt = self._geo()
        v = self.copter.state.vel
        gs = math.hypot(v[0], v[1])
        cog = int(math.degrees(math.atan2(v[1], v[0])) % 360 * 100) if gs > 0.2 else 65535
        fix = mavlink.GPS_FIX_TYPE_3D_FIX if self.copter.gps_ok else mavlink.GPS_FIX_TYPE_NO_GPS
        if not self.copter.gps_ok:
            lat = lon = 0.0
        return self._enc().gps_raw_int_encode(
            int(self.copter.t * 1e6), fix, int(lat * 1e7), int(lon * 1e7),
            int(alt * 1000), 121, 200, int(gs * 100), cog, 10, int(alt * 1000), 300, 500, 40, 0)

    def _extended_sys_state(self, link: _Link):
        return self._enc().extended_sys_state_encode(
            mavlink.MAV_VTOL_STATE_UNDEFINED, self.copter.landed_state())

    def _global_position_int(self, link: _Link):
        lat, lon, alt = self._geo() if self.copter.gps_ok else (0.0, 0.0, self._geo()[2])
        s = self.copter.state
        hdg = int(math.degrees(s.yaw) % 360 * 100) % 36000
        return self._enc().global_position_int_encode(
            self._time_ms(), int(lat * 1e7), int(lon * 1e7), int(alt * 1000),
            int(self.copter.alt_above_home() * 1000), int(s.vel[0] * 100), int(s.vel[1] * 100),
            int(s.vel[2] * 100), hdg)

    def _local_position_ned(self, link: _Link):
        if not self.copter.position_ok:
            return None  # no position estimate relative to an origin yet
        s = self.copter.state
        return self._enc().local_position_ned_encode(self._time_ms(), *s.pos, *s.vel)

    def _attitude(self, link: _Link):
        roll, pitch, yaw = vehicle.attitude(self.copter.state)
        return self._enc().attitude_encode(self._time_ms(), roll, pitch, yaw, 0.0, 0.0, 0.0)

    def _vfr_hud(self, link: _Link):
        s = self.copter.state
        gs = math.hypot(s.vel[0], s.vel[1])
        throttle = 0 if not self.copter.armed else (15 if self.copter.land_complete else 50)
        return self._enc().vfr_hud_encode(gs, gs, int(math.degrees(s.yaw) % 360), throttle,
                                          self._geo()[2], -s.vel[2])

    def _system_time(self, link: _Link):
        unix_us = int(((self._unix_time0 or 0.0) + self.copter.t) * 1e6)
        return self._enc().system_time_encode(unix_us, self._time_ms())

    def _ekf_status_report(self, link: _Link):
        flags = mavlink.EKF_ATTITUDE | mavlink.EKF_VELOCITY_VERT | mavlink.EKF_POS_VERT_ABS
        if self.copter.position_ok:
            flags |= (mavlink.EKF_VELOCITY_HORIZ | mavlink.EKF_POS_HORIZ_REL | mavlink.EKF_POS_HORIZ_ABS
                      | mavlink.EKF_PRED_POS_HORIZ_REL | mavlink.EKF_PRED_POS_HORIZ_ABS)
        return self._enc().ekf_status_report_encode(flags, 0.02, 0.02, 0.02, 0.01, 0.0)

    def _home_position(self, link: _Link):
        if not self.copter.origin_set:
            return None  # no home yet: a request is accepted and answered by nothing
        lat, lon, alt = self.copter.home
        x, y, z = self.copter.home_ned
        return self._enc().home_position_encode(
            int(lat * 1e7), int(lon * 1e7), int(alt * 1000), x, y, z, [1.0, 0.0, 0.0, 0.0],
            0.0, 0.0, 0.0, int(self.copter.t * 1e6))

    def _gps_global_origin(self, link: _Link):
        if not self.copter.origin_set:
            return None
        lat, lon, alt = self.copter.origin
        return self._enc().gps_global_origin_encode(
            int(lat * 1e7), int(lon * 1e7), int(alt * 1000), int(self.copter.t * 1e6))

    def _autopilot_version(self, link: _Link):
        return self._enc().autopilot_version_encode(
            CAPABILITIES, FW_VERSION, 0, 0, 0, [0x70, 0x6d, 0x6f, 0x6e, 0, 0, 0, 0],
            [0] * 8, [0] * 8, 0, 0, 0)

    def _position_target_local_ned(self, link: _Link):
        g = self.copter.guided
        if self.copter.mode != Mode.GUIDED or g is None or g.pos is None:
            return None
        mask = _VEL_IGNORE | _ACC_IGNORE | _YAW_IGNORE | _YAW_RATE_IGNORE
        return self._enc().position_target_local_ned_encode(
            self._time_ms(), mavlink.MAV_FRAME_LOCAL_NED, mask, *g.pos, 0, 0, 0, 0, 0, 0, 0, 0)

    def _position_target_global_int(self, link: _Link):
        g = self.copter.guided
        if self.copter.mode != Mode.GUIDED or g is None or g.pos is None:
            return None
        lat, lon, alt = self.copter.geodetic_from_ned(g.pos)
        mask = _VEL_IGNORE | _ACC_IGNORE | _YAW_IGNORE | _YAW_RATE_IGNORE
        return self._enc().position_target_global_int_encode(
            self._time_ms(), mavlink.MAV_FRAME_GLOBAL, mask, int(lat * 1e7), int(lon * 1e7), alt,
            0, 0, 0, 0, 0, 0, 0, 0)

    def _banner(self, link: _Link) -> None:
        for text in (FIRMWARE, "Frame: QUAD/X"):
            link.send(self._enc().statustext_encode(mavlink.MAV_SEVERITY_INFO, text.encode()))


def _check_latlng(lat_e7: float, lon_e7: float) -> bool:
    return abs(lat_e7) <= 90e7 and abs(lon_e7) <= 180e7


def _sane_vector(v: Vec3) -> bool:
    return all(math.isfinite(x) and abs(x) <= 1000.0 for x in v)


def _param_name(raw) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0].strip()


# --------------------------------------------------------------------------- CLI

def _parse_home(text: str) -> tuple[float, float, float]:
    try:
        lat, lon, alt = (float(v) for v in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--home wants LAT,LON,ALT, got {text!r}") from exc
    if not (-90 <= lat <= 90 and -180 <= lon <= 180 and math.isfinite(alt)):
        raise argparse.ArgumentTypeError(f"--home out of range: {text!r}")
    return (lat, lon, alt)


def main(argv: Optional[Sequence[str]] = None) -> int:
    from onboard.argcheck import HOST_PORT, HOST_PORT_BIND, SEED, SPEEDUP, OneLineParser, fail, number, param_item

    ap = OneLineParser(prog="python -m sim.autopilot", description=__doc__.split("\n")[0])
    ap.add_argument("--udp", action="append", default=[], metavar="HOST:PORT", type=HOST_PORT,
                    help="send to a UDP listener (like SITL --out); repeatable")
    ap.add_argument("--udpin", action="append", default=[], metavar="HOST:PORT", type=HOST_PORT_BIND,
                    help="listen on UDP; replies go to the last sender; repeatable")
    ap.add_argument("--tcp", action="append", default=[], metavar="HOST:PORT", type=HOST_PORT_BIND,
                    help="TCP server port; repeatable")
    ap.add_argument("--speedup", type=SPEEDUP, default=1.0, help="autopilot s per wall s, (0, 1000]")
    ap.add_argument("--home", type=_parse_home, default=(-35.363261, 149.165230, 584.0),
                    help="LAT,LON,ALT (deg, deg, m AMSL), written --home=LAT,... when LAT < 0; "
                    "default ArduPilot's CMAC")
    ap.add_argument("--seed", type=SEED, default=0)
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", type=param_item,
                    help="parameter override in ArduPilot units; repeatable")
    ap.add_argument("--signing-key", metavar="FILE",
                    help="MAVLink 2 signing key file (64 hex chars, mode 0600): sign everything, "
                    "drop unsigned or wrongly signed packets")
    ap.add_argument("--ready-after", type=number(0.0, 600.0), default=BootTimeline.ready_s, metavar="S",
                    help="autopilot s after boot until it can arm (GPS and EKF origin earlier, in "
                    f"proportion); default {BootTimeline.ready_s:g}, as ArduCopter 4.4 SITL")
    ap.add_argument("--max-lag", type=number(0.0, 3600.0, lo_open=True), default=10.0, metavar="S",
                    help="autopilot s the model may fall behind before the clock slips "
                    "(small: run slower than --speedup on a loaded machine, like SITL)")
    args = ap.parse_args(argv)
    endpoints = ([f"udpout:{h}:{p}" for h, p in args.udp] + [f"udpin:{h}:{p}" for h, p in args.udpin]
                 + [f"tcpin:{h}:{p}" for h, p in args.tcp]) or ["tcpin:127.0.0.1:5760"]
    try:
        overrides = dict(args.param)
        key = None
        if args.signing_key:
            from onboard.app.signing import load_key
            key = load_key(args.signing_key)
        mock = MockAutopilot(home=args.home, endpoints=endpoints, speedup=args.speedup,
                             params=overrides, seed=args.seed, signing_key=key,
                             max_lag_s=args.max_lag, boot=BootTimeline.scaled(args.ready_after))
        mock.start()
    except KeyError as exc:  # Params: unknown parameter 'NAME'
        return fail(ap.prog, str(exc.args[0] if exc.args else exc))
    except (ValueError, OSError) as exc:
        return fail(ap.prog, str(exc))
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print("mock autopilot up: " + " ".join(str(e) for e in mock.endpoints), flush=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        mock.stop()
        print(f"mock autopilot stopped: {mock.counters()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
