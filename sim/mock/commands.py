"""The mock autopilot's commands (COMMAND_LONG / COMMAND_INT and SET_MODE, with ArduCopter's
results) and position targets (SET_POSITION_TARGET_*, with its type_mask rules). A part of
``MockAutopilot`` (sim/mock/context.py)."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Mapping, Optional


from onboard.app.mavlink2 import mavlink
from sim.mock import multicopter
from sim.mock.multicopter import Vec3

from sim.mock.context import Handler, MockContext, Part
from sim.mock.copter import MAGIC_FORCE_ARM, MAGIC_FORCE_DISARM, GuidedTarget, Mode
from sim.mock.links import _Link
from sim.mock.messages import (_ACC_IGNORE, _FORCE_SET, _POS_IGNORE, _VEL_IGNORE, _YAW_IGNORE,
                               _YAW_RATE_IGNORE, Telemetry)

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


class Commands(Part):
    """``telemetry``: the messages a command asks for and the stream rates it sets."""

    def __init__(self, ctx: MockContext, telemetry: Telemetry):
        super().__init__(ctx)
        self.telemetry = telemetry
        self._replies: list = []  # messages to send after the COMMAND_ACK being built

    def handlers(self) -> Mapping[str, Handler]:
        return {"COMMAND_LONG": self._on_command_long,
                "COMMAND_INT": self._on_command_int,
                "SET_MODE": self._on_set_mode,
                "SET_POSITION_TARGET_LOCAL_NED": self._on_set_position_target_local_ned,
                "SET_POSITION_TARGET_GLOBAL_INT": self._on_set_position_target_global_int}

    # ----- commands
    def _ack(self, link: _Link, msg, command: int, result: int) -> None:
        link.send(self.ctx.enc.command_ack_encode(
            command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        self.ctx.count(f"ack_{mavlink.enums['MAV_RESULT'][result].name[11:].lower()}")

    def _on_set_mode(self, link: _Link, msg) -> None:
        result = self._set_mode_common(msg.base_mode, msg.custom_mode)
        self._ack(link, msg, mavlink.MAV_CMD_DO_SET_MODE, result)

    def _set_mode_common(self, base_mode: int, custom_mode: int) -> int:
        if int(base_mode) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            ok = self.ctx.copter.set_mode(int(custom_mode))
            return mavlink.MAV_RESULT_ACCEPTED if ok else mavlink.MAV_RESULT_FAILED
        return mavlink.MAV_RESULT_DENIED

    def _on_command_long(self, link: _Link, msg) -> None:
        self.ctx.count("commands")
        cmd = _Command(msg.command, (msg.param1, msg.param2, msg.param3, msg.param4),
                       msg.param5, msg.param6, msg.param7, None,
                       msg.get_srcSystem(), msg.get_srcComponent())
        self._run_command(link, msg, cmd)

    def _on_command_int(self, link: _Link, msg) -> None:
        self.ctx.count("commands")
        cmd = _Command(msg.command, (msg.param1, msg.param2, msg.param3, msg.param4),
                       msg.x, msg.y, msg.z, msg.frame,
                       msg.get_srcSystem(), msg.get_srcComponent())
        self._run_command(link, msg, cmd)

    def _run_command(self, link: _Link, msg, cmd: _Command) -> None:
        if cmd.frame is None and cmd.command in LONG_AS_INT and self.ctx.copter.armed and not (
                math.isfinite(cmd.x) and math.isfinite(cmd.y)):
            # ArduCopter 4.4, armed, converts these COMMAND_LONGs to COMMAND_INT, param5/6 * 1e7
            # to int32: NaN aborts the firmware before it answers (measured on its SITL; when
            # disarmed it answers FAILED and lives)
            self.ctx.crash(f"floating point exception: {mavlink.enums['MAV_CMD'][cmd.command].name} "
                        f"with latitude/longitude {cmd.x}, {cmd.y} from {cmd.sysid}/{cmd.compid}")
            return
        # Like ArduPilot, the ACK goes out first and requested messages after it.
        self._replies = []
        try:
            result = self._command(link, cmd)
        except (ValueError, OverflowError):  # e.g. NaN where an integer is expected
            self.ctx.count("command_errors")
            self._replies = []
            result = mavlink.MAV_RESULT_FAILED
        self._ack(link, msg, cmd.command, result)
        for reply in self._replies:
            link.send(reply)
        self._replies = []

    def _command(self, link: _Link, cmd: _Command) -> int:
        """Run a command; returns the MAV_RESULT ArduCopter 4.5 would answer."""
        for run in (self._flight_command, self._message_command, self._setting_command):
            result = run(link, cmd)
            if result is not None:
                return result
        return mavlink.MAV_RESULT_UNSUPPORTED

    def _flight_command(self, link: _Link, cmd: _Command) -> int | None:
        """Arming, take-off, modes, reposition, termination, reboot; None: not one of these."""
        m = mavlink
        c = self.ctx.copter
        p1, p2, _, _ = cmd.params
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
        return None

    def _message_command(self, link: _Link, cmd: _Command) -> int | None:
        """What asks for messages (streams, one-offs, version, home, banner) or sets home; None:
        not one of these."""
        m = mavlink
        p1, p2, _, _ = cmd.params
        if cmd.command == m.MAV_CMD_REQUEST_MESSAGE:
            return self._request_message(link, int(p1))
        if cmd.command == m.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_message_interval(link, int(p1), p2)
        if cmd.command == m.MAV_CMD_GET_MESSAGE_INTERVAL:
            return self._get_message_interval(link, int(p1))
        if cmd.command == m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            if p1 != 1.0:
                return m.MAV_RESULT_FAILED
            self._replies.append(self.telemetry.autopilot_version(link))
            return m.MAV_RESULT_ACCEPTED
        if cmd.command == m.MAV_CMD_GET_HOME_POSITION:
            self._replies.append(self.telemetry.home_position(link))
            self._replies.append(self.telemetry.gps_global_origin(link))
            return m.MAV_RESULT_ACCEPTED
        if cmd.command == m.MAV_CMD_DO_SET_HOME:
            return self._do_set_home(cmd)
        if cmd.command == m.MAV_CMD_DO_SEND_BANNER:
            self.telemetry.banner(link)
            return m.MAV_RESULT_ACCEPTED
        return None

    def _setting_command(self, link: _Link, cmd: _Command) -> int | None:
        """Yaw and speed; None: not one of these."""
        m = mavlink
        c = self.ctx.copter
        p1, p2, _, p4 = cmd.params
        if cmd.command == m.MAV_CMD_CONDITION_YAW:
            if 0.0 <= p1 <= 360.0 and p4 in (0.0, 1.0):
                target = math.radians(p1) + (c.state.yaw if p4 == 1.0 else 0.0)
                c.fixed_yaw = multicopter.wrap_pi(target)
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
        return None

    def _location_to_ned(self, lat_e7: float, lon_e7: float, alt: float,
                         frame: int) -> Optional[Vec3]:
        """Target location (degE7, m in frame) -> local NED; None for unknown frames."""
        if frame in _ABSOLUTE_FRAMES:
            alt_amsl = alt
        elif frame in _RELATIVE_FRAMES or frame in _TERRAIN_FRAMES:
            alt_amsl = self.ctx.copter.home[2] + alt  # flat terrain at home altitude
        else:
            return None
        return self.ctx.copter.ned_from_geodetic(lat_e7 * 1e-7, lon_e7 * 1e-7, alt_amsl)

    def _do_reposition(self, cmd: _Command) -> int:
        """GCS_MAVLINK_Copter::handle_command_int_do_reposition."""
        m = mavlink
        c = self.ctx.copter
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
            self.ctx.copter.set_home(None)
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
                alt = self.ctx.copter.home[2] + cmd.z
            else:
                return m.MAV_RESULT_DENIED
        if not _check_latlng(lat * 1e7, lon * 1e7):
            return m.MAV_RESULT_FAILED
        self.ctx.copter.set_home((lat, lon, alt))
        return m.MAV_RESULT_ACCEPTED

    def _msg_name(self, msgid: int) -> Optional[str]:
        cls = mavlink.mavlink_map.get(msgid)
        name = cls.msgname if cls is not None else None
        return name if name in self.telemetry.builders else None

    def _request_message(self, link: _Link, msgid: int) -> int:
        name = self._msg_name(msgid)
        if name is None:
            if msgid == mavlink.MAVLINK_MSG_ID_PARAM_VALUE:
                return mavlink.MAV_RESULT_ACCEPTED  # ArduPilot: "send the next param"; no-op
            return mavlink.MAV_RESULT_FAILED
        msg = self.telemetry.builders[name](link)
        if msg is not None:
            self._replies.append(msg)
        return mavlink.MAV_RESULT_ACCEPTED

    def _set_message_interval(self, link: _Link, msgid: int, interval_us: float) -> int:
        name = self._msg_name(msgid)
        if interval_us == 0:  # back to the default rate
            if name is None:
                return mavlink.MAV_RESULT_FAILED
            tm = self.telemetry
            tm.set_interval(link, name, tm.default_intervals(link.port_index).get(name, 0.0))
            return mavlink.MAV_RESULT_ACCEPTED
        if name is None:
            self.ctx.copter.text(mavlink.MAV_SEVERITY_INFO, f"No ap_message for mavlink id ({msgid})")
            return mavlink.MAV_RESULT_DENIED
        if interval_us < 0:
            self.telemetry.set_interval(link, name, 0.0)
        else:
            self.telemetry.set_interval(link, name, max(interval_us, 1000.0) * 1e-6)
        return mavlink.MAV_RESULT_ACCEPTED

    def _get_message_interval(self, link: _Link, msgid: int) -> int:
        name = self._msg_name(msgid)
        if name is None:
            self._replies.append(self.ctx.enc.message_interval_encode(msgid, 0))
            return mavlink.MAV_RESULT_FAILED
        iv = link.intervals.get(name, 0.0)
        interval_us = int(iv * 1e6) if iv > 0 else -1
        self._replies.append(self.ctx.enc.message_interval_encode(msgid, interval_us))
        return mavlink.MAV_RESULT_ACCEPTED

    # ----- position targets (GCS_MAVLINK_Copter::handle_message_set_position_target_*)
    def _on_set_position_target_local_ned(self, link: _Link, msg) -> None:
        c = self.ctx.copter
        if c.mode != Mode.GUIDED:
            self.ctx.count("setpoint_ignored")
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
        c = self.ctx.copter
        if c.mode != Mode.GUIDED:
            self.ctx.count("setpoint_ignored")
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
        self.ctx.copter.set_guided(replace(target, yaw=yaw, yaw_rate=yaw_rate))
        self.ctx.count("setpoint_accepted")

    def _reject_setpoint(self) -> None:
        self.ctx.copter.guided_hold()
        self.ctx.count("setpoint_rejected")


def _check_latlng(lat_e7: float, lon_e7: float) -> bool:
    return abs(lat_e7) <= 90e7 and abs(lon_e7) <= 180e7


def _sane_vector(v: Vec3) -> bool:
    return all(math.isfinite(x) and abs(x) <= 1000.0 for x in v)
