"""What the app knows of its autopilot: the ``Vehicle`` record the autopilot side
(onboard/app/autopilot/side.py) keeps from the autopilot's heartbeats and telemetry."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from onboard.app.autopilot.profiles import UNKNOWN, AutopilotProfile
from onboard.app.mavlink_connection import mavlink


@dataclass
class Vehicle:
    """What the app knows of the autopilot (from its heartbeats and telemetry)."""

    sysid: int | None = None
    compid: int | None = None
    autopilot: int = mavlink.MAV_AUTOPILOT_INVALID  # HEARTBEAT.autopilot
    profile: AutopilotProfile = field(default=UNKNOWN)  # chosen by ``autopilot`` (profiles.py)
    custom_mode: int | None = None
    armed: bool = False
    landed_state: int | None = None
    relative_alt: float | None = None
    ned_origin: tuple[float, float, float] | None = None  # autopilot local origin (deg, deg, m)
    heartbeat_local: float = -math.inf
    mode_seen_local: float = -math.inf
    speed_limit_mps: float | None = None  # horizontal, from its parameters (profile.limit_params)
    accel_limit_mps2: float | None = None
    jerk_limit_mps3: float | None = None  # of its guided setpoints' shaping (profile.jerk_limit)
    # the limit_params / jerk_params values read and usable (profile.limit_refusal), by name, in
    # the autopilot's units
    limit_values: dict[str, float] = field(default_factory=dict)
    lat_lon_deg: tuple[float, float] | None = None  # last valid GLOBAL_POSITION_INT
    amsl_m: float | None = None
    heading_deg: float | None = None
    position_local: float = -math.inf  # local time of the last valid GLOBAL_POSITION_INT
    prearm_ok: bool | None = None  # the profile's reading of SYS_STATUS (None: not reported)
    prearm_text: str | None = None  # why it refuses to arm: its latest STATUSTEXT or event saying so
    mode_ack: int | None = None  # MAV_RESULT of its latest answer to a DO_SET_MODE (not proof of the mode)

    def in_mission_mode(self) -> bool:
        """In the mode the app flies the mission in (ArduCopter's GUIDED, PX4's OFFBOARD)."""
        return self.profile.in_mission_mode(self.custom_mode)

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
