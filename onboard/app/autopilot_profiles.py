"""Commands the app and the ground station send to an autopilot, in a form every firmware version
accepts. Light module (no core import): ``pmon gcs`` uses it too.

MAV_CMD_NAV_TAKEOFF: the MAVLink spec lets latitude/longitude/yaw be NaN ("current"), but
ArduCopter 4.4 converts a COMMAND_LONG's param5/6 to integers and aborts on NaN (floating point
exception in SITL; measured on the 4.4.0-dev binary in ../shared/ardupilot), while PX4 takes
finite ones as the take-off location (0, 0 would be off the coast of Africa). So both get the
vehicle's own position and heading: ArduCopter ignores them, PX4 takes off where it stands.
Altitude (param7): ArduCopter reads it above home (COMMAND_LONG's frame is relative), PX4 as
AMSL.
"""
from __future__ import annotations

import math

from onboard.app.mavlink_connection import mavlink


def takeoff_params(autopilot: int, lat_deg: float, lon_deg: float, heading_deg: float | None,
                   alt_above_home_m: float, home_amsl_m: float) -> tuple[float, ...]:
    """The seven COMMAND_LONG parameters of MAV_CMD_NAV_TAKEOFF to ``alt_above_home_m``, from a
    vehicle at (lat_deg, lon_deg) heading ``heading_deg`` (None: unknown, sent as 0) whose home
    is ``home_amsl_m`` above mean sea level. Raises ValueError on a non-finite input: a
    take-off is never sent with NaN in it."""
    values = (lat_deg, lon_deg, alt_above_home_m, home_amsl_m)
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"take-off needs a finite position and altitude, got {values}")
    yaw = heading_deg if heading_deg is not None and math.isfinite(heading_deg) else 0.0
    alt = alt_above_home_m + home_amsl_m if autopilot == mavlink.MAV_AUTOPILOT_PX4 else alt_above_home_m
    return (0.0, 0.0, 0.0, float(yaw), float(lat_deg), float(lon_deg), float(alt))


def heading_from_global_position_int(hdg_cdeg: int) -> float | None:
    """GLOBAL_POSITION_INT.hdg in degrees, None when the autopilot does not know it (65535)."""
    return None if hdg_cdeg == 65535 else hdg_cdeg / 100.0


def prearm_ok(sys_status) -> bool | None:
    """The autopilot's pre-arm checks from a SYS_STATUS message (None where it does not report
    them: the bit absent from onboard_control_sensors_present, as PX4 leaves it)."""
    bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
    if sys_status is None or not sys_status.onboard_control_sensors_present & bit:
        return None
    return bool(sys_status.onboard_control_sensors_health & bit)
