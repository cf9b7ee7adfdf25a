"""What the app knows of its autopilot: the ``Vehicle`` record the io thread keeps from the
autopilot's heartbeats and telemetry, and the firmware facts it is read with."""
from __future__ import annotations

import math
from dataclasses import dataclass

from onboard.app.mavlink_connection import mavlink

ARDUCOPTER_GUIDED = 4
PX4_MAIN_MODE_OFFBOARD = 6
# the autopilot's horizontal speed and acceleration limits for guided position setpoints, read at
# connection to check what the planner's moves assume: (name, factor to SI) per autopilot
SPEED_ACCEL_PARAMS = {
    mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: (("WPNAV_SPEED", 0.01), ("WPNAV_ACCEL", 0.01)),  # cm/s, cm/s^2
    mavlink.MAV_AUTOPILOT_PX4: (("MPC_XY_CRUISE", 1.0), ("MPC_ACC_HOR", 1.0)),  # m/s, m/s^2
}


@dataclass
class Vehicle:
    """What the app knows of the autopilot (from its heartbeats and telemetry)."""

    sysid: int | None = None
    compid: int | None = None
    autopilot: int = mavlink.MAV_AUTOPILOT_INVALID
    custom_mode: int | None = None
    armed: bool = False
    landed_state: int | None = None
    relative_alt: float | None = None
    ned_origin: tuple[float, float, float] | None = None  # autopilot local origin (deg, deg, m)
    heartbeat_local: float = -math.inf
    mode_seen_local: float = -math.inf
    speed_limit_mps: float | None = None  # horizontal, from its parameters (SPEED_ACCEL_PARAMS)
    accel_limit_mps2: float | None = None
    lat_lon_deg: tuple[float, float] | None = None  # last valid GLOBAL_POSITION_INT
    amsl_m: float | None = None
    heading_deg: float | None = None
    position_local: float = -math.inf  # local time of the last valid GLOBAL_POSITION_INT
    prearm_ok: bool | None = None  # SYS_STATUS MAV_SYS_STATUS_PREARM_CHECK (None: not reported)
    prearm_text: str | None = None  # its latest "PreArm: ..." / "Arm: ..." STATUSTEXT

    def is_guided(self) -> bool:
        if self.custom_mode is None:
            return False
        if self.autopilot == mavlink.MAV_AUTOPILOT_PX4:
            return (self.custom_mode >> 16) & 0xFF == PX4_MAIN_MODE_OFFBOARD
        return self.custom_mode == ARDUCOPTER_GUIDED

    def airborne(self) -> bool:
        """Off the ground: taking off, flying or landing (``flying`` waits for the take-off to
        be reported done)."""
        if self.landed_state not in (None, mavlink.MAV_LANDED_STATE_UNDEFINED):
            return self.landed_state != mavlink.MAV_LANDED_STATE_ON_GROUND
        return self.relative_alt is not None and self.relative_alt > 2.0

    def flying(self) -> bool:
        if self.landed_state not in (None, mavlink.MAV_LANDED_STATE_UNDEFINED):
            return self.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR
        return self.relative_alt is not None and self.relative_alt > 2.0

