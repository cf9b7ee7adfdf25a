"""The app's state machine as commanded (start, pause, resume, stop, launch), its parameters,
and the launch sequence's actions. A mixin of ``OnboardApp`` (onboard/app/app.py): io thread,
under the app lock."""
from __future__ import annotations

import logging
import math

from onboard.app import launch
from onboard.app.autopilot_profiles import takeoff_params
from onboard.app.contract import MAV_CMD_PMON, REASON_TEXT, Action, Reason, State
from onboard.app.mavlink_connection import mavlink
from onboard.app.vehicle_state import ARDUCOPTER_GUIDED, PX4_MAIN_MODE_OFFBOARD

log = logging.getLogger("pmon.app")


class Commands:
    """Methods of ``OnboardApp``; the attributes they use are set up in ``OnboardApp.__init__``."""

    def _set_state(self, new: State) -> None:
        if new != State.MONITORING:
            self.setpoint = None
            self.segment = None
            self.generation += 1  # results of ticks already running are not sent
            self._guided_deadline = None
        self.state = new
        self._heartbeat()

    def _on_command(self, msg) -> None:
        if msg.command != MAV_CMD_PMON:
            self._ack(msg, mavlink.MAV_RESULT_UNSUPPORTED, Reason.UNKNOWN_ACTION)
            return
        p1 = msg.param1
        action = int(p1) if math.isfinite(p1) and p1 == int(p1) else -1
        handler = {Action.START: self._cmd_start, Action.PAUSE: self._cmd_pause,
                   Action.RESUME: self._cmd_resume, Action.STOP: self._cmd_stop,
                   Action.LAUNCH: self._cmd_launch}.get(action)
        if handler is None:
            self._refuse(msg, mavlink.MAV_RESULT_DENIED, Reason.UNKNOWN_ACTION, f"action {p1:g}")
            return
        result, reason = handler()
        if result == mavlink.MAV_RESULT_ACCEPTED:
            self._ack(msg, result, reason)
        else:
            self._refuse(msg, result, reason, Action(action).name.lower())

    def _ack(self, msg, result: int, reason: Reason = Reason.NONE) -> None:
        self.link.send(self.link.mav.command_ack_encode(
            msg.command, result, 0, int(reason), msg.get_srcSystem(), msg.get_srcComponent()))

    def _refuse(self, msg, result: int, reason: Reason, what: str) -> None:
        self._ack(msg, result, reason)
        self.say(f"{what} refused: {REASON_TEXT.get(reason, reason.name)}", mavlink.MAV_SEVERITY_WARNING)

    def _preconditions(self) -> tuple[int, Reason]:
        v = self.vehicle
        now = self.clock.now()
        if v.sysid is None or self.mono() - v.heartbeat_local > self.cfg.link_timeout_s:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.NO_AUTOPILOT
        if self.poses.latest() is None or v.ned_origin is None or now is None:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.NO_POSITION
        if not v.armed:
            return mavlink.MAV_RESULT_DENIED, Reason.NOT_ARMED
        if not v.flying():
            return mavlink.MAV_RESULT_DENIED, Reason.NOT_FLYING
        last = max(self.scans.last_scan_t)
        if not now - last <= 3.0:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.NO_SENSOR_DATA
        return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE

    def _enter_monitoring(self) -> None:
        self._set_state(State.MONITORING)
        self._next_sp_t = -math.inf
        if self.speed_warning:  # said again where an operator starting the mission hears it
            self.say(self.speed_warning, mavlink.MAV_SEVERITY_WARNING)
        if self.vehicle.is_guided():
            self._guided_deadline = None
            self.say("monitoring started")
        else:  # take the vehicle into GUIDED; not an override until it is there (or refuses)
            self._guided_deadline = (self.clock.now() or 0.0) + 3.0
            self._set_guided()
            self.say("monitoring: switching to GUIDED")

    def _set_guided(self) -> None:
        if self.vehicle.autopilot == mavlink.MAV_AUTOPILOT_PX4:
            self._command_long(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                               PX4_MAIN_MODE_OFFBOARD)
        else:
            self._command_long(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                               ARDUCOPTER_GUIDED)

    def _cmd_start(self) -> tuple[int, Reason]:
        if self.state == State.MONITORING:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE  # already: do nothing twice
        if self._launch is not None:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.BUSY
        result, reason = self._preconditions()
        if result == mavlink.MAV_RESULT_ACCEPTED:
            self._enter_monitoring()
        return result, reason

    def _cmd_resume(self) -> tuple[int, Reason]:
        if self.state == State.MONITORING:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE
        if self.state == State.IDLE:
            return mavlink.MAV_RESULT_DENIED, Reason.WRONG_STATE
        return self._cmd_start()

    def _cmd_pause(self) -> tuple[int, Reason]:
        if self.state == State.PAUSED:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE
        if self.state != State.MONITORING:
            return mavlink.MAV_RESULT_DENIED, Reason.WRONG_STATE
        self._set_state(State.PAUSED)
        self.say("paused: setpoints stopped, vehicle holds")
        return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE

    def _cmd_stop(self) -> tuple[int, Reason]:
        if self._launch is not None:
            self._launch = None
            self.say("launch cancelled")
        if self.state == State.IDLE:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE
        self._set_state(State.IDLE)
        self.say("stopped")
        return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE

    def _cmd_launch(self) -> tuple[int, Reason]:
        if self._launch is not None or self.state == State.MONITORING:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE
        v = self.vehicle
        if v.sysid is None or self._link_lost:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.NO_AUTOPILOT
        if v.armed and v.flying():
            return mavlink.MAV_RESULT_DENIED, Reason.ALREADY_FLYING
        # accepted from the autopilot's boot on: the sequence waits for its position and pre-arm
        # checks itself (onboard/app/launch.py), so the operator never has to try again
        self._launch = launch.Launch(target_up_m=self.params["PMON_ALT"])
        self.say("launch: GUIDED, arm, take off")
        return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE

    def _param_value(self, name: str, index: int | None = None) -> None:
        self.link.send(self.link.mav.param_value_encode(
            name.encode(), self.params[name], mavlink.MAV_PARAM_TYPE_REAL32, len(self.params),
            self.params.index(name) if index is None else index))

    @staticmethod
    def _param_name(raw) -> str:
        if isinstance(raw, bytes):
            raw = raw.decode("ascii", "replace")
        return str(raw).split("\x00", 1)[0]

    def _on_param_read(self, msg) -> None:
        name = self._param_name(msg.param_id)
        if msg.param_index >= 0:
            if msg.param_index < len(self.params):
                self._param_value(self.params.names()[msg.param_index], msg.param_index)
            else:
                self.say(f"no parameter index {msg.param_index}", mavlink.MAV_SEVERITY_WARNING)
            return
        if name in self.params:
            self._param_value(name)
        else:
            self.say(f"unknown parameter {name[:16]}", mavlink.MAV_SEVERITY_WARNING)

    def _on_param_set(self, msg) -> None:
        name = self._param_name(msg.param_id)
        if name not in self.params:
            self.say(f"unknown parameter {name[:16]}", mavlink.MAV_SEVERITY_WARNING)
            return  # nothing to answer with: no such value exists
        refused = self.params.set(name, float(msg.param_value))
        if refused:
            self.say(refused, mavlink.MAV_SEVERITY_WARNING)
        self._param_value(name)
        if name == "PMON_REACH" and not refused:
            self._check_speed_limits()  # longer steps may now be faster than the autopilot flies

    def _launch_step(self, now: float) -> None:
        """Advance the launch sequence (onboard/app/launch.py) and carry out its actions."""
        if self._launch is None:
            return
        v = self.vehicle
        pose = self.poses.latest()
        home_up = pose.pos[2] - v.relative_alt if pose is not None and v.relative_alt is not None else None
        result, reason = self._preconditions()
        blocker = None if result == mavlink.MAV_RESULT_ACCEPTED or reason == Reason.NOT_FLYING \
            else REASON_TEXT[reason]  # NOT_FLYING: the take-off is not reported done yet
        view = launch.VehicleView(
            position=pose is not None and v.ned_origin is not None and v.lat_lon_deg is not None,
            guided=v.is_guided(), armed=v.armed, up_m=None if pose is None else float(pose.pos[2]),
            home_up_m=home_up, climbing=v.landed_state in (mavlink.MAV_LANDED_STATE_TAKEOFF,
                                                         mavlink.MAV_LANDED_STATE_IN_AIR),
            prearm_ok=v.prearm_ok, prearm_text=v.prearm_text,
            can_start=result == mavlink.MAV_RESULT_ACCEPTED, start_blocker=blocker)
        self._launch, actions = launch.step(self._launch, view, now)
        severity = {"info": mavlink.MAV_SEVERITY_INFO, "warning": mavlink.MAV_SEVERITY_WARNING,
                    "error": mavlink.MAV_SEVERITY_ERROR}
        for a in actions:
            if isinstance(a, launch.Say):
                self.say(a.text, severity[a.level], once=None if a.once is None else f"launch:{a.once}")
            elif a[0] == "guided":
                self._set_guided()
            elif a[0] == "arm":
                v.prearm_text = None  # a refusal now says why afresh
                self._command_long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            elif a[0] == "takeoff":
                self._command_long(mavlink.MAV_CMD_NAV_TAKEOFF, *takeoff_params(
                    v.autopilot, *v.lat_lon_deg, v.heading_deg, a[1], v.amsl_m - v.relative_alt))
            elif a[0] == "start":
                self._enter_monitoring()
        if self._launch is None:
            self._said = {k for k in self._said if not k.startswith("launch:")}
