"""What differs between autopilot firmwares, in one place: the seam where an autopilot plugs in.

The app (and the ground station) talk MAVLink to whatever autopilot the first HEARTBEAT says it
is (``HEARTBEAT.autopilot``); ``profile_for`` picks its profile, and every firmware-specific
fact the app uses comes from that profile, never from a special case elsewhere:

- mode names and numbers, both ways (``mode_number``, ``mode_name``, ``in_mode``; names a
  firmware lacks get a line that says what to use instead, ``no_mode``) and the
  MAV_CMD_DO_SET_MODE that asks for one (``set_mode_params``);
- the mode the app flies the mission in (``mission_mode``: ArduCopter's GUIDED, PX4's OFFBOARD),
  how it is entered (``mode_lead_s``: autopilot s of setpoints streamed before asking: PX4's
  OFFBOARD needs the stream already running) and where the app leaves the vehicle when it stops
  commanding in it (``release_mode``: PX4 leaves OFFBOARD ~1 s after the last setpoint, into
  its failsafe);
- the launch: the mode it arms in (``launch_mode``) and the modes the autopilot takes by itself
  on the way (``launch_own_modes``: PX4's take-off, which ends in Hold); a pilot's stop
  (``hold_mode``: ArduCopter's BRAKE, PX4's Hold);
- the take-off altitude's frame (``takeoff_params``);
- the parameters that hold the vehicle's speed and acceleration limits (``limit_params``) and
  the jerk its guided setpoints are shaped with (``jerk_params``, ``jerk_limit``), which values
  of them are no limit (``limit_refusal``), others checked at connection (``checked_params``,
  ``param_warning``), and how PARAM_VALUE carries an integer (``param_value``);
- the pre-arm state (``prearm_ok``) and the texts that say why arming was refused
  (``arming_refusal``);
- whether it signs MAVLink 2 (``can_sign``).

A mode change is never taken from its COMMAND_ACK (PX4 ACKs OFFBOARD with no stream, and POSCTL
with no RC, ACCEPTED and stays where it was): the app, on every firmware, waits for HEARTBEAT to
show it (onboard/app/state_machine.py).

``ArduPilot`` is flown against its real SITL firmware (tests/firmware/test_ardupilot.py), ``Px4`` against
PX4 v1.16's (tests/firmware/test_px4.py; ../shared/px4/README.md has what was measured there). Light
module (no core import): ``pmon gcs`` uses it.

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
import struct
from collections.abc import Mapping

from onboard.app.mavlink2 import mavutil
from onboard.app.mavlink_connection import mavlink


class AutopilotProfile:
    """One firmware's MAVLink dialect as the app uses it. Subclasses set the class attributes
    and override what differs; the defaults are ArduCopter's (the firmware the app was built
    against), with no limit parameters."""

    name = "unknown autopilot"
    mission_mode = "GUIDED"  # the mode the app flies the mission in (it asks for it, then streams)
    mode_lead_s = 0.0  # autopilot s of setpoints streamed before the mission mode is asked for
    # the mode the app asks for when it stops commanding while the vehicle is in the mission mode
    # (pause, stop, a refused origin); None: the mission mode holds the vehicle by itself
    release_mode: str | None = None
    launch_mode = "GUIDED"  # the launch arms in it (ArduCopter takes off by command only in GUIDED)
    launch_own_modes: tuple[str, ...] = ()  # modes the autopilot takes by itself during a launch
    hold_mode = "BRAKE"  # stop and hold position (pmon gcs hold)
    takeoff_altitude_amsl = False  # MAV_CMD_NAV_TAKEOFF param7: above home (False) or AMSL (True)
    # ((speed parameter, factor to m/s), (acceleration parameter, factor to m/s^2)): the vehicle's
    # horizontal limits for guided position setpoints, read at connection; () where unknown
    limit_params: tuple[tuple[str, float], ...] = ()
    # the parameters ``jerk_limit`` makes the horizontal jerk of guided setpoints from, read with
    # ``limit_params``; () where the autopilot shapes none (the planner keeps the scenario's)
    jerk_params: tuple[str, ...] = ()
    checked_params: tuple[str, ...] = ()  # read at connection; ``param_warning`` judges them
    params_bytewise = False  # PARAM_VALUE carries an integer's bytes in its float (PX4)
    can_sign = True  # MAVLink 2 signing
    # said as the reason of a refused arm when the autopilot gives its reasons where the app
    # cannot read them (PX4: EVENTs, without the build's event metadata); None: it says them
    refusal_elsewhere: str | None = None
    # the parameter (s) after which a vehicle armed on the ground disarms by itself without a
    # take-off (0 or less: never); None where unknown
    auto_disarm_param: str | None = None
    _modes: dict[int, str] = mavutil.mode_mapping_acm  # custom_mode -> name
    _advice: dict[str, str] = {}  # a mode name this firmware lacks -> what to use instead

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

    def no_mode(self, name: str) -> str:
        """One line for a mode name this firmware does not have."""
        key = name.strip().upper()
        advice = self._advice.get(key)
        return f"{self.name} has no mode {key}" + (f": {advice}" if advice else
                                                  f" (its modes: {', '.join(self.mode_names())})")

    def in_mode(self, custom_mode: int | None, name: str) -> bool:
        """HEARTBEAT.custom_mode is the mode ``name``."""
        return custom_mode is not None and custom_mode == self.mode_number(name)

    def in_mission_mode(self, custom_mode: int | None) -> bool:
        return self.in_mode(custom_mode, self.mission_mode)

    def in_launch_mode(self, custom_mode: int | None, own: bool = False) -> bool:
        """In the launch's mode (``own``: or in one the autopilot takes by itself on the way)."""
        names = (self.launch_mode, *self.launch_own_modes) if own else (self.launch_mode,)
        return any(self.in_mode(custom_mode, n) for n in names)

    def set_mode_params(self, name: str) -> tuple[float, ...]:
        """MAV_CMD_DO_SET_MODE's parameters for the mode ``name`` (ValueError if unknown)."""
        number = self.mode_number(name)
        if number is None:
            raise ValueError(self.no_mode(name))
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
        them: the bit absent from onboard_control_sensors_present)."""
        bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
        if sys_status is None or not sys_status.onboard_control_sensors_present & bit:
            return None
        return bool(sys_status.onboard_control_sensors_health & bit)

    def arming_refusal(self, text: str) -> bool:
        """A STATUSTEXT that says why the autopilot refuses to arm."""
        return text.startswith(("PreArm:", "Arm:"))

    # ----- parameters
    def param_value(self, msg) -> float:
        """PARAM_VALUE's value as a number: a float as sent, or an integer parameter as the
        firmware encodes it (``params_bytewise``: the integer's bytes in the float's)."""
        value = float(msg.param_value)
        if self.params_bytewise and msg.param_type in _INT_TYPES:
            fmt = _INT_TYPES[msg.param_type]
            raw = struct.pack("<f", value)[:struct.calcsize(fmt)]
            return float(struct.unpack(fmt, raw)[0])
        return value

    def param_warning(self, name: str, value: float) -> str | None:
        """What is unsafe about a ``checked_params`` value for the app's flight (None: fine)."""
        return None

    def limit_refusal(self, name: str, value: float) -> str | None:
        """Why a ``limit_params`` / ``jerk_params`` value read cannot be planned with (None: it
        can): NaN, infinite, zero or negative is no limit."""
        if not math.isfinite(value) or value <= 0.0:
            return "not a positive number"
        return None

    def jerk_limit(self, values: Mapping[str, float]) -> float | None:
        """The horizontal jerk (m/s^3) the autopilot shapes guided position + velocity +
        acceleration setpoints with, from the ``limit_params`` and ``jerk_params`` values read so
        far (by name, in the autopilot's units); None: none known, or none applies."""
        return None


GRAVITY_MSS = 9.80665  # ArduPilot's GRAVITY_MSS
# PSC_JERK_XY values planned with, m/s^3: ArduPilot documents 1-20 (AC_PosControl.cpp @Range);
# outside a tenth of its lowest and 50 times its highest it is a mis-set parameter, not a tuning
PSC_JERK_XY_RANGE = (0.1, 1000.0)


def arducopter_jerk_xy(jerk_mps3: float, accel_mps2: float, lean_accel_radss: float) -> float:
    """The horizontal jerk (m/s^3) ArduCopter 4.4 shapes guided targets with (AC_PosControl::
    set_max_speed_accel_xy, called by ModeGuided::pva_control_start with WPNAV_SPEED and
    WPNAV_ACCEL): PSC_JERK_XY (``jerk_mps3``) capped by the largest average jerk the attitude
    loop can give, 0.5 sqrt(accel * g * angular acceleration), the angular acceleration the
    smaller of ATC_ACCEL_R_MAX and ATC_ACCEL_P_MAX (``lean_accel_radss``; 0: no cap, as the
    firmware's is_positive). The firmware's other cap, ATC_RATE_R_MAX / ATC_RATE_P_MAX times g,
    is off at their default 0 and not modelled; both caps apply only with ATC_RATE_FF_ENAB (on by
    default). sim/mock/multicopter.py's vehicle flies with this one."""
    if lean_accel_radss > 0.0:
        return min(jerk_mps3, 0.5 * math.sqrt(accel_mps2 * GRAVITY_MSS * lean_accel_radss))
    return jerk_mps3


class ArduPilot(AutopilotProfile):
    """ArduCopter (flown against its 4.4 SITL firmware)."""

    name = "ArduPilot"
    auto_disarm_param = "DISARM_DELAY"  # ArduCopter's auto_disarm_check, 10 s by default
    limit_params = (("WPNAV_SPEED", 0.01), ("WPNAV_ACCEL", 0.01))  # cm/s, cm/s^2
    # GUIDED's position + velocity + acceleration targets (ModeGuided::posvelaccel_control_run ->
    # AC_PosControl::input_pos_vel_accel_xy -> shape_pos_vel_accel_xy) change their acceleration
    # at most at the jerk ``arducopter_jerk_xy`` gives: PSC_JERK_XY (m/s^3), ATC_ACCEL_R_MAX and
    # ATC_ACCEL_P_MAX (cdeg/s^2)
    jerk_params = ("PSC_JERK_XY", "ATC_ACCEL_R_MAX", "ATC_ACCEL_P_MAX")

    def limit_refusal(self, name: str, value: float) -> str | None:
        lo, hi = PSC_JERK_XY_RANGE
        if name == "PSC_JERK_XY" and math.isfinite(value) and value > 0.0 and not lo <= value <= hi:
            return f"outside {lo:g}-{hi:g} m/s^3"
        if name in ("ATC_ACCEL_R_MAX", "ATC_ACCEL_P_MAX") and value == 0.0:
            return None  # the firmware's angular acceleration limit off: no cap on the jerk (a setting)
        return super().limit_refusal(name, value)

    def jerk_limit(self, values: Mapping[str, float]) -> float | None:
        """PSC_JERK_XY, capped (``arducopter_jerk_xy``) once WPNAV_ACCEL and both ATC_ACCEL_*_MAX
        are known; None until PSC_JERK_XY is."""
        jerk = values.get("PSC_JERK_XY")
        if jerk is None:
            return None
        accel, roll, pitch = (values.get(n) for n in ("WPNAV_ACCEL", "ATC_ACCEL_R_MAX", "ATC_ACCEL_P_MAX"))
        if accel is None or roll is None or pitch is None:
            return jerk
        return arducopter_jerk_xy(jerk, accel * 0.01, math.radians(min(roll, pitch) * 0.01))


# PX4's modes by name (px4_custom_mode.h: custom_mode = main << 16 | sub << 24), in the names its
# own console and MAVSDK use; pymavlink's and the operator's everyday names as aliases
_PX4_MODES = {"MANUAL": (1, 0), "ALTCTL": (2, 0), "POSCTL": (3, 0), "AUTO.TAKEOFF": (4, 2),
              "AUTO.LOITER": (4, 3), "AUTO.MISSION": (4, 4), "AUTO.RTL": (4, 5), "AUTO.LAND": (4, 6),
              "AUTO.FOLLOW_TARGET": (4, 8), "AUTO.PRECLAND": (4, 9), "ACRO": (5, 0), "OFFBOARD": (6, 0),
              "STABILIZED": (7, 0)}
_PX4_ALIASES = {"HOLD": "AUTO.LOITER", "LOITER": "AUTO.LOITER", "TAKEOFF": "AUTO.TAKEOFF",
                "MISSION": "AUTO.MISSION", "RTL": "AUTO.RTL", "LAND": "AUTO.LAND", "POSITION": "POSCTL",
                "ALTITUDE": "ALTCTL", "FOLLOWME": "AUTO.FOLLOW_TARGET", "STABILIZE": "STABILIZED"}
# COM_OBL_RC_ACT (commander: what PX4 does when the offboard stream stops), by value
_OBL_RC_ACT = {0: "Position mode", 1: "Altitude mode", 2: "Manual", 3: "Return", 4: "Land", 5: "Hold",
               6: "Terminate", 7: "Disarm"}
_INT_TYPES = {mavlink.MAV_PARAM_TYPE_UINT8: "<B", mavlink.MAV_PARAM_TYPE_INT8: "<b",
              mavlink.MAV_PARAM_TYPE_UINT16: "<H", mavlink.MAV_PARAM_TYPE_INT16: "<h",
              mavlink.MAV_PARAM_TYPE_UINT32: "<I", mavlink.MAV_PARAM_TYPE_INT32: "<i"}


class Px4(AutopilotProfile):
    """PX4 (flown against its v1.16 SITL firmware, SIH quad): ``custom_mode = (main << 16) |
    (sub << 24)``; OFFBOARD needs setpoints streaming before it is asked for and leaves ~1 s
    after they stop (COM_OF_LOSS_T) into COM_OBL_RC_ACT; arming in Hold, the take-off AMSL and
    ended in Hold by PX4; MPC_* limits; integers bytewise in PARAM_VALUE; no MAVLink signing."""

    name = "PX4"
    auto_disarm_param = "COM_DISARM_PRFLT"  # commander's pre-flight auto-disarm, 10 s by default
    mission_mode = "OFFBOARD"
    # ~1 s of stream before the switch worked (../shared/px4/README.md); 1.2: a margin on PX4's clock
    mode_lead_s = 1.2
    release_mode = "AUTO.LOITER"  # Hold: stops and holds where it is, needs no stream
    launch_mode = "AUTO.LOITER"  # PX4 boots in Hold, arms there and takes off by command
    launch_own_modes = ("AUTO.TAKEOFF",)
    hold_mode = "AUTO.LOITER"
    takeoff_altitude_amsl = True
    limit_params = (("MPC_XY_VEL_MAX", 1.0), ("MPC_ACC_HOR", 1.0))  # m/s, m/s^2
    # no jerk_params: OFFBOARD's setpoints reach the position controller unshaped (v1.16:
    # mavlink_receiver.cpp handle_message_set_position_target_local_ned publishes them as the
    # trajectory_setpoint; FlightModeManager::start_flight_task runs no flight task in OFFBOARD;
    # PositionControl clamps the velocity to MPC_XY_VEL_MAX and the tilt, no jerk). MPC_JERK_AUTO /
    # MPC_JERK_MAX shape PX4's own auto and manual modes only: the scenario's jerk is planned with
    checked_params = ("COM_OBL_RC_ACT",)
    params_bytewise = True
    can_sign = False  # v1.16: no SETUP_SIGNING, signatures not checked, nothing signed
    refusal_elsewhere = "refused by PX4 (see its console / events)"
    _advice = {"GUIDED": "the app flies OFFBOARD (pmon gcs start / resume)",
               "BRAKE": "use AUTO.LOITER (Hold; pmon gcs hold)",
               "POSHOLD": "use POSCTL", "ALT_HOLD": "use ALTCTL", "SMART_RTL": "use AUTO.RTL"}

    def mode_names(self) -> list[str]:
        return sorted(_PX4_MODES)

    def _canonical(self, name: str) -> str | None:
        key = name.strip().upper()
        key = _PX4_ALIASES.get(key, key)
        return key if key in _PX4_MODES else None

    def mode_number(self, name: str) -> int | None:
        key = self._canonical(name)
        if key is None:
            return None
        main, sub = _PX4_MODES[key]
        return (main << 16) | (sub << 24)

    def mode_name(self, custom_mode: int | None) -> str:
        if custom_mode is None:
            return "?"
        for name in _PX4_MODES:
            if self.in_mode(custom_mode, name):
                return name
        return f"PX4 mode {(custom_mode >> 16) & 0xFF}.{(custom_mode >> 24) & 0xFF}"

    def in_mode(self, custom_mode: int | None, name: str) -> bool:
        """By main mode, and by sub mode where the mode has one (OFFBOARD, POSCTL have none)."""
        key = self._canonical(name)
        if custom_mode is None or key is None:
            return False
        main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
        want_main, want_sub = _PX4_MODES[key]
        return main == want_main and (want_sub == 0 or sub == want_sub)

    def set_mode_params(self, name: str) -> tuple[float, ...]:
        key = self._canonical(name)
        if key is None:
            raise ValueError(self.no_mode(name))
        main, sub = _PX4_MODES[key]
        return (float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(main), float(sub))

    def prearm_ok(self, sys_status) -> bool | None:
        """PX4 sets SYS_STATUS's pre-arm *health* bit when it can arm but never the *present*
        bit (measured on v1.16: the bit came with the first accepted arm, ~5 s after boot)."""
        if sys_status is None:
            return None
        return bool(sys_status.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK)

    def arming_refusal(self, text: str) -> bool:
        return text.startswith(("Arming denied", "Preflight Fail", "Preflight check failed"))

    def param_warning(self, name: str, value: float) -> str | None:
        if name == "COM_OBL_RC_ACT" and value in (0, 1, 2):
            return (f"COM_OBL_RC_ACT = {value:g} ({_OBL_RC_ACT[int(value)]}): if the app's setpoints stop, PX4 "
                    "flies it, which without RC sinks and drifts; set 5 (Hold)")
        return None


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
