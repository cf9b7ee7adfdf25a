"""What differs between autopilot firmwares, in one place: the seam where an autopilot plugs in.

The app (and the ground station) talk MAVLink to whatever autopilot the first HEARTBEAT says it
is (``HEARTBEAT.autopilot``); ``profile_for`` picks its profile, and every firmware-specific
fact the app uses comes from that profile, never from a special case elsewhere:

- mode names and numbers (``mode_number``, ``mode_name``, ``in_mode``) and the
  MAV_CMD_DO_SET_MODE that asks for one (``set_mode_params``);
- the mode the app flies the mission in (``mission_mode``: ArduCopter's GUIDED, PX4's OFFBOARD);
- the take-off altitude's frame (``takeoff_params``);
- the parameters that hold the vehicle's speed and acceleration limits (``limit_params``);
- the pre-arm state (``prearm_ok``).

``ArduPilot`` is flown against its real SITL firmware (tests/test_ardupilot.py). ``Px4`` holds
what the app knew of PX4 before it was flown (OFFBOARD's main mode, MPC_* limits, take-off AMSL;
issue 30 adds what PX4 needs beyond that: a setpoint stream before OFFBOARD, mode changes
confirmed by HEARTBEAT only, no signing). Light module (no core import): ``pmon gcs`` uses it.

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

from pymavlink import mavutil

from onboard.app.mavlink_connection import mavlink


class AutopilotProfile:
    """One firmware's MAVLink dialect as the app uses it. Subclasses set the class attributes
    and override what differs; the defaults are ArduCopter's (the firmware the app was built
    against), with no limit parameters."""

    name = "unknown autopilot"
    mission_mode = "GUIDED"  # the mode the app flies the mission in (it asks for it, then streams)
    takeoff_altitude_amsl = False  # MAV_CMD_NAV_TAKEOFF param7: above home (False) or AMSL (True)
    # ((speed parameter, factor to m/s), (acceleration parameter, factor to m/s^2)): the vehicle's
    # horizontal limits for guided position setpoints, read at connection; () where unknown
    limit_params: tuple[tuple[str, float], ...] = ()
    _modes: dict[int, str] = mavutil.mode_mapping_acm  # custom_mode -> name

    # ----- modes
    def mode_names(self) -> list[str]:
        return sorted(self._modes.values())

    def mode_number(self, name: str) -> int | None:
        """custom_mode of a mode name (any case), None if this firmware has no such mode."""
        return {v: k for k, v in self._modes.items()}.get(name.strip().upper())

    def mode_name(self, custom_mode: int | None) -> str:
        if custom_mode is None:
            return "?"
        return self._modes.get(custom_mode, str(custom_mode))

    def in_mode(self, custom_mode: int | None, name: str) -> bool:
        """HEARTBEAT.custom_mode is the mode ``name``."""
        return custom_mode is not None and custom_mode == self.mode_number(name)

    def in_mission_mode(self, custom_mode: int | None) -> bool:
        return self.in_mode(custom_mode, self.mission_mode)

    def set_mode_params(self, name: str) -> tuple[float, ...]:
        """MAV_CMD_DO_SET_MODE's parameters for the mode ``name`` (ValueError if unknown)."""
        number = self.mode_number(name)
        if number is None:
            raise ValueError(f"{self.name} has no mode {name!r}")
        return (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(number))

    # ----- take-off and pre-arm
    def takeoff_params(self, lat_deg: float, lon_deg: float, heading_deg: float | None,
                       alt_above_home_m: float, home_amsl_m: float) -> tuple[float, ...]:
        """The seven COMMAND_LONG parameters of MAV_CMD_NAV_TAKEOFF to ``alt_above_home_m``, from
        a vehicle at (lat_deg, lon_deg) heading ``heading_deg`` (None: unknown, sent as 0) whose
        home is ``home_amsl_m`` above mean sea level. Raises ValueError on a non-finite input: a
        take-off is never sent with NaN in it."""
        values = (lat_deg, lon_deg, alt_above_home_m, home_amsl_m)
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"take-off needs a finite position and altitude, got {values}")
        yaw = heading_deg if heading_deg is not None and math.isfinite(heading_deg) else 0.0
        alt = alt_above_home_m + home_amsl_m if self.takeoff_altitude_amsl else alt_above_home_m
        return (0.0, 0.0, 0.0, float(yaw), float(lat_deg), float(lon_deg), float(alt))

    def prearm_ok(self, sys_status) -> bool | None:
        """The pre-arm checks from a SYS_STATUS message (None where the firmware does not report
        them: the bit absent from onboard_control_sensors_present, as PX4 leaves it)."""
        bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
        if sys_status is None or not sys_status.onboard_control_sensors_present & bit:
            return None
        return bool(sys_status.onboard_control_sensors_health & bit)


class ArduPilot(AutopilotProfile):
    """ArduCopter (flown against its 4.4 SITL firmware)."""

    name = "ArduPilot"
    limit_params = (("WPNAV_SPEED", 0.01), ("WPNAV_ACCEL", 0.01))  # cm/s, cm/s^2


class Px4(AutopilotProfile):
    """PX4: ``custom_mode = (main << 16) | (sub << 24)``, modes as pymavlink names them."""

    name = "PX4"
    mission_mode = "OFFBOARD"
    takeoff_altitude_amsl = True
    limit_params = (("MPC_XY_CRUISE", 1.0), ("MPC_ACC_HOR", 1.0))  # m/s, m/s^2

    def mode_names(self) -> list[str]:
        return sorted(mavutil.px4_map)

    def mode_number(self, name: str) -> int | None:
        entry = mavutil.px4_map.get(name.strip().upper())
        return None if entry is None else (entry[1] << 16) | (entry[2] << 24)

    def mode_name(self, custom_mode: int | None) -> str:
        if custom_mode is None:
            return "?"
        for name in mavutil.px4_map:
            if self.in_mode(custom_mode, name):
                return name
        return str(custom_mode)

    def in_mode(self, custom_mode: int | None, name: str) -> bool:
        """By main mode, and by sub mode where the mode has one (OFFBOARD has none)."""
        entry = mavutil.px4_map.get(name.strip().upper())
        if custom_mode is None or entry is None:
            return False
        main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
        return main == entry[1] and (entry[2] == 0 or sub == entry[2])

    def set_mode_params(self, name: str) -> tuple[float, ...]:
        entry = mavutil.px4_map.get(name.strip().upper())
        if entry is None:
            raise ValueError(f"{self.name} has no mode {name!r}")
        return (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(entry[1]), float(entry[2]))


ARDUPILOT = ArduPilot()
PX4 = Px4()
UNKNOWN = AutopilotProfile()
PROFILES: dict[int, AutopilotProfile] = {
    mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: ARDUPILOT,
    mavlink.MAV_AUTOPILOT_PX4: PX4,
}


def profile_for(autopilot: int) -> AutopilotProfile:
    """The profile of a HEARTBEAT.autopilot value (``UNKNOWN``: ArduCopter's modes, no limits)."""
    return PROFILES.get(autopilot, UNKNOWN)


def takeoff_params(autopilot: int, lat_deg: float, lon_deg: float, heading_deg: float | None,
                   alt_above_home_m: float, home_amsl_m: float) -> tuple[float, ...]:
    """``profile_for(autopilot).takeoff_params(...)``, for a caller holding a HEARTBEAT only."""
    return profile_for(autopilot).takeoff_params(lat_deg, lon_deg, heading_deg, alt_above_home_m, home_amsl_m)


def prearm_ok(sys_status) -> bool | None:
    """The pre-arm bit of a SYS_STATUS as every profile here reads it (``prearm_ok`` above)."""
    return UNKNOWN.prearm_ok(sys_status)
