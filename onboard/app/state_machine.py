"""The app's state as commanded (docs/MAVLINK.md): idle, monitoring, paused, pilot override,
fault, advisory; the commands that move it (start, pause, resume, stop, launch, advise, each
acknowledged with a reason when refused); what the autopilot's news does to it (a mode someone else set, a link
loss, a reboot, a moved origin); and the launch sequence's actions (onboard/app/autopilot/launch.py).

Only ``monitoring`` sends setpoints, and only while the autopilot is in the mode the app put it
in (the profile's mission mode: GUIDED, OFFBOARD); any other mode set by someone else -> pilot
override, at once. ``advisory`` (``pmon run --advise``, the advise action) tracks and plans
from where the vehicle is while a pilot or a mission flies it, publishes the plan's next point,
and commands nothing: no setpoint, no mode, no arming; a mode change is not its business. It
hands over to ``monitoring`` by start (or resume), through the same checks and mode entry as
any start. Leaving ``monitoring`` drops the setpoint and bumps ``generation``: results of
ticks already running are not sent; where the mission mode needs the stream to hold the vehicle
(the profile's ``release_mode``: PX4's OFFBOARD), the app hands it to that mode (Hold) instead.

Entering the mission mode (``ModeEntry``), the same way for every firmware: a hold setpoint at
the vehicle's position streams first for the profile's ``mode_lead_s`` (PX4 takes OFFBOARD only
with setpoints already coming; 0 for ArduCopter, whose GUIDED holds by itself), then the mode is
asked for every ``MODE_RETRY_S`` until HEARTBEAT shows it (an ACK is not proof: PX4 ACKs OFFBOARD
ACCEPTED and stays in Hold) or ``MODE_WAIT_S`` passes (paused, saying what the autopilot answered
and which mode it is in); the hold streams on until the first tick's setpoint replaces it, so
the stream never lapses. A mode other than the one it started from, meanwhile, is a pilot's.
io thread, under the app lock.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from onboard.app.autopilot import launch
from onboard.app.autopilot.profiles import AutopilotProfile
from onboard.app.context import AppContext
from onboard.app.contract import MAV_CMD_PMON, REASON_TEXT, Action, Reason, State
from onboard.app.gcs.dispatch import ack
from onboard.app.mavlink_connection import mavlink
from onboard.app.part import Job, Part

log = logging.getLogger("pmon.app")
MODE_WAIT_S = 3.0  # autopilot s the vehicle has to reach the mission mode after it is first asked for
MODE_RETRY_S = 1.0  # autopilot s between requests of the mission mode while it is not shown
RELEASE_S = 3.0  # autopilot s the app asks for the release mode (every MODE_RETRY_S) until it is shown
SENSOR_FRESH_S = 3.0  # start needs a DF scan this recent (autopilot s)
SEVERITY = {"info": mavlink.MAV_SEVERITY_INFO, "warning": mavlink.MAV_SEVERITY_WARNING,
            "error": mavlink.MAV_SEVERITY_ERROR}


@dataclass
class ModeEntry:
    """The way into the mission mode (see the module): autopilot s."""

    ask_t: float  # first request (after the lead)
    deadline: float
    from_mode: int | None  # the mode the vehicle was in: another one meanwhile is a pilot's
    asked_t: float = -math.inf


class StateMachine(Part):
    """``autopilot``: the autopilot side; ``publisher``: says and heartbeats; ``stream``: the
    setpoint stream; ``limits``: the plan limits (their warning is said again at start);
    ``scans``: the scan buffer (start needs fresh DF data); ``ctx``: the app's link, clock,
    parameters (PMON_ALT for a launch) and config (``auto_launch``)."""

    def __init__(self, ctx: AppContext, autopilot, publisher, stream, limits, scans):
        self.link = ctx.link
        self.clock = ctx.clock
        self.autopilot = autopilot
        self.publisher = publisher
        self.say = publisher.say
        self.stream = stream
        self.limits = limits
        self.scans = scans
        self.params = ctx.params
        self.auto_launch = ctx.cfg.auto_launch
        self.state = State.ADVISORY if ctx.cfg.advise else State.IDLE
        self.generation = 0  # bumped when setpoints must stop; results of older ticks are dropped
        self.entry: ModeEntry | None = None  # entering the mission mode after start/resume
        self.release_until = -math.inf  # autopilot s: asking for the release mode until then
        self.release_asked_t = -math.inf
        self.launch: launch.Launch | None = None

    @property
    def profile(self) -> AutopilotProfile:
        """The served autopilot's profile (onboard/app/autopilot/profiles.py): its modes and what
        they need. Read each time: the first HEARTBEAT picks it."""
        return self.autopilot.vehicle.profile

    # ----- what the state allows
    def commanding(self) -> bool:
        """Monitoring, with the vehicle in the mission mode: the tick's point is to be sent."""
        return self.state == State.MONITORING and self.entry is None

    def may_stream(self) -> bool:
        """The setpoint may be re-sent now: monitoring in the mission mode, or entering it."""
        return self.state == State.MONITORING and not self.autopilot.link_lost and (
            self.entry is not None or self.autopilot.vehicle.in_mission_mode())

    def set_state(self, new: State) -> None:
        if new != State.MONITORING:
            self.stream.clear()
            self.generation += 1  # results of ticks already running are not sent
            self.entry = None
            self._release()
        self.state = new
        self.publisher.heartbeat()

    def _release(self) -> None:
        """The setpoints stop: where the mission mode needs them to hold the vehicle, hand it to
        the profile's release mode (PX4: Hold) instead of letting the autopilot's failsafe act."""
        v = self.autopilot.vehicle
        if self.profile.release_mode is not None and v.in_mission_mode() and not self.autopilot.link_lost:
            now = self.clock.now() or 0.0
            self.release_until, self.release_asked_t = now + RELEASE_S, now
            self.autopilot.set_mode(self.profile.release_mode)

    # ----- commands (MAV_CMD_PMON, param1 = action)
    def on_command(self, msg) -> None:
        if msg.command != MAV_CMD_PMON:
            ack(self.link, msg, mavlink.MAV_RESULT_UNSUPPORTED, Reason.UNKNOWN_ACTION)
            return
        p1 = msg.param1
        action = int(p1) if math.isfinite(p1) and p1 == int(p1) else -1
        handler = {Action.START: self.start, Action.PAUSE: self.pause, Action.RESUME: self.resume,
                   Action.STOP: self.stop, Action.LAUNCH: self.begin_launch,
                   Action.ADVISE: self.advise}.get(action)
        if handler is None:
            self._refuse(msg, mavlink.MAV_RESULT_DENIED, Reason.UNKNOWN_ACTION, f"action {p1:g}")
            return
        result, reason = handler()
        if result == mavlink.MAV_RESULT_ACCEPTED:
            ack(self.link, msg, result, reason)
        else:
            self._refuse(msg, result, reason, Action(action).name.lower())

    def _refuse(self, msg, result: int, reason: Reason, what: str) -> None:
        ack(self.link, msg, result, reason)
        self.say(f"{what} refused: {REASON_TEXT.get(reason, reason.name)}", mavlink.MAV_SEVERITY_WARNING)

    def preconditions(self) -> tuple[int, Reason]:
        ap, v = self.autopilot, self.autopilot.vehicle
        now = self.clock.now()
        if not ap.heard_recently():
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.NO_AUTOPILOT
        if not ap.has_position() or now is None:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.NO_POSITION
        if not v.armed:
            return mavlink.MAV_RESULT_DENIED, Reason.NOT_ARMED
        if not v.flying():
            return mavlink.MAV_RESULT_DENIED, Reason.NOT_FLYING
        if not now - max(self.scans.last_scan_t) <= SENSOR_FRESH_S:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.NO_SENSOR_DATA
        return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE

    def _enter_monitoring(self) -> None:
        v = self.autopilot.vehicle
        self.set_state(State.MONITORING)
        self.stream.restart()
        self.release_until = -math.inf
        if self.limits.warning:  # said again where an operator starting the mission hears it
            self.say(self.limits.warning, mavlink.MAV_SEVERITY_WARNING)
        mode = self.profile.mission_mode
        if v.in_mission_mode():
            self.entry = None
            self.say("monitoring started")
            return
        # take the vehicle into the mission mode; not an override until it is there (or refuses)
        now = self.clock.now() or 0.0
        lead = self.profile.mode_lead_s
        self.entry = ModeEntry(now + lead, now + lead + MODE_WAIT_S, v.custom_mode)
        if lead > 0.0 and not self._hold_here(now):
            return
        self.say(f"monitoring: switching to {mode}" + (f" (setpoints streaming {lead:g} s first)" if lead else ""))
        self.periodic_mode(now)

    def _hold_here(self, now: float) -> bool:
        """Stream a hold setpoint where the vehicle is, at the mission altitude h as every
        setpoint (fenced as every setpoint)."""
        pose = self.autopilot.poses.latest()
        setup = self.stream.setup()
        if pose is not None:
            here = (float(pose.pos[0]), float(pose.pos[1]), float(setup.grid.altitude_m))
            sent, refused = self.stream.adopt(here, None, now, pose.pos, setup)
            if self.stream.setpoint is not None:
                return True
        else:
            refused = "no position"
        self.set_state(State.PAUSED)
        self.say(f"cannot hold here to enter {self.profile.mission_mode} ({refused}): paused",
                 mavlink.MAV_SEVERITY_WARNING)
        return False

    def start(self) -> tuple[int, Reason]:
        if self.state == State.MONITORING:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE  # already: do nothing twice
        if self.launch is not None:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.BUSY
        result, reason = self.preconditions()
        if result == mavlink.MAV_RESULT_ACCEPTED:
            self._enter_monitoring()
        return result, reason

    def resume(self) -> tuple[int, Reason]:
        if self.state == State.MONITORING:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE
        if self.state == State.IDLE:
            return mavlink.MAV_RESULT_DENIED, Reason.WRONG_STATE
        return self.start()

    def pause(self) -> tuple[int, Reason]:
        if self.state == State.PAUSED:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE
        if self.state != State.MONITORING:
            return mavlink.MAV_RESULT_DENIED, Reason.WRONG_STATE
        self.set_state(State.PAUSED)
        self.say("paused: setpoints stopped, vehicle holds")
        return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE

    def stop(self) -> tuple[int, Reason]:
        if self.launch is not None:
            self.launch = None
            self.say("launch cancelled")
        if self.state == State.IDLE:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE
        self.set_state(State.IDLE)
        self.say("stopped")
        return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE

    def advise(self) -> tuple[int, Reason]:
        """To advisory from any state: nothing is commanded from now on (from monitoring the
        setpoints stop as on pause: PX4's OFFBOARD is handed to Hold, the stream's release).
        Refused while a launch runs: that flies the vehicle, stop it first."""
        if self.state == State.ADVISORY:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE
        if self.launch is not None:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.BUSY
        was = self.state
        self.set_state(State.ADVISORY)
        self.say("advisory: tracking and planning, the vehicle is not commanded"
                 + (" (setpoints stopped)" if was == State.MONITORING else ""))
        return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE

    def begin_launch(self) -> tuple[int, Reason]:
        if self.launch is not None or self.state == State.MONITORING:
            return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE
        if self.state == State.ADVISORY:  # someone else flies it: stop first, then launch
            return mavlink.MAV_RESULT_DENIED, Reason.WRONG_STATE
        v = self.autopilot.vehicle
        if v.sysid is None or self.autopilot.link_lost:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, Reason.NO_AUTOPILOT
        if v.armed and v.flying():
            return mavlink.MAV_RESULT_DENIED, Reason.ALREADY_FLYING
        # accepted from the autopilot's boot on: the sequence waits for its position and pre-arm
        # checks itself (onboard/app/autopilot/launch.py), so the operator never has to try again
        p = self.profile
        self.launch = launch.Launch(altitude_m=self.params.settings.uav.altitude_m, launch_mode=p.launch_mode)
        then = "" if p.mission_mode == p.launch_mode else f", {p.mission_mode}"
        self.say(f"launch: {p.launch_mode}, arm, take off{then}")
        return mavlink.MAV_RESULT_ACCEPTED, Reason.NONE

    # ----- the autopilot's news (AutopilotEvents, through the app)
    def check_mode(self) -> None:
        """Stop commanding the moment the vehicle leaves the mode the app put it in."""
        v = self.autopilot.vehicle
        if self.state != State.MONITORING:
            return
        if self.entry is not None:
            if v.in_mission_mode():
                self.entry = None
                self.say(f"{self.profile.mission_mode}: monitoring")
                return
            # the mode it started from, or the autopilot's own launch modes (PX4 ending its
            # take-off in Hold), are not a pilot's
            if v.armed and (v.custom_mode == self.entry.from_mode or self.profile.in_launch_mode(v.custom_mode, own=True)):
                return
        if not v.in_mission_mode() or not v.armed:
            why = "disarmed" if not v.armed else f"mode {self.profile.mode_name(v.custom_mode)}"
            self.set_state(State.PILOT_OVERRIDE)
            self.say(f"pilot override ({why}): setpoints stopped", mavlink.MAV_SEVERITY_WARNING)

    def on_link_lost(self) -> None:
        """Stop commanding at once, keep estimating; fly again only when told."""
        # what stopped is said only where something was flowing: not in advisory, idle or paused
        stopped = ["setpoints stopped"] if self.state == State.MONITORING else []
        if self.launch is not None:
            stopped.append("launch aborted")
        if self.state in (State.MONITORING, State.PAUSED):
            self.set_state(State.FAULT)
        self.launch = None
        said = ": " + ", ".join(stopped) if stopped else ""
        self.say(f"autopilot link lost{said}, estimating", mavlink.MAV_SEVERITY_CRITICAL)

    def on_link_back(self, lost_s: float) -> None:
        # said now: "link lost" could reach no one while the link was down
        self.say(f"link back (lost {lost_s:.0f} s)" + (": send resume" if self.state == State.FAULT else ""),
                 mavlink.MAV_SEVERITY_WARNING)

    def on_reboot(self) -> None:
        """The vehicle is not ours to fly until the operator says so (the link was lost
        meanwhile, as a rule; a PX4 back within the link timeout is seen first as a disarm: a
        pilot override that no pilot made)."""
        if self.state in (State.MONITORING, State.PAUSED, State.PILOT_OVERRIDE):
            self.set_state(State.FAULT)

    def on_origin_moved(self, off_m: float) -> None:
        if self.state == State.MONITORING:
            self.set_state(State.FAULT)
            self.say(f"NED origin moved {off_m:.0f} m: refused, setpoints stopped", mavlink.MAV_SEVERITY_CRITICAL)
        else:
            self.say(f"NED origin moved {off_m:.0f} m: refused", mavlink.MAV_SEVERITY_CRITICAL, once="origin_moved")

    # ----- periodic jobs (io thread, under the lock)
    def jobs(self) -> tuple[Job, ...]:
        return (Job("periodic mode", lambda local, now: self.periodic_mode(now), clocked=True),
                Job("periodic launch", lambda local, now: self.periodic_launch(now), clocked=True))

    def periodic_mode(self, now: float) -> None:
        """Ask for the mission mode while entering it (until HEARTBEAT shows it or the deadline),
        and for the release mode while it is not shown."""
        v, e = self.autopilot.vehicle, self.entry
        if self.state == State.MONITORING and e is not None and not self.autopilot.link_lost:
            if now > e.deadline:
                answer = mavlink.enums["MAV_RESULT"].get(v.mode_ack)
                said = answer.name.removeprefix("MAV_RESULT_") if answer is not None else "nothing"
                self.set_state(State.PAUSED)
                self.say(f"{self.profile.mission_mode} not entered in {now - e.ask_t:.0f} s (the autopilot answered "
                         f"{said}, it is in {self.profile.mode_name(v.custom_mode)}): paused", mavlink.MAV_SEVERITY_WARNING)
            elif now >= e.ask_t and now - e.asked_t >= MODE_RETRY_S:
                e.asked_t = now
                self.autopilot.set_mission_mode()
        elif now < self.release_until and v.in_mission_mode() and self.state != State.MONITORING \
                and not self.autopilot.link_lost and now - self.release_asked_t >= MODE_RETRY_S:
            self.release_asked_t = now
            self.autopilot.set_mode(self.profile.release_mode)

    def periodic_launch(self, now: float) -> None:
        if self.auto_launch and self.state == State.IDLE and self.launch is None \
                and not self.publisher.said("auto_launch"):
            if self.begin_launch()[0] == mavlink.MAV_RESULT_ACCEPTED and self.launch is not None:
                self.publisher.mark_said("auto_launch")
        self._launch_step(now)

    def _launch_view(self) -> launch.VehicleView:
        ap, v = self.autopilot, self.autopilot.vehicle
        pose = ap.poses.latest()
        result, reason = self.preconditions()
        blocker = None if result == mavlink.MAV_RESULT_ACCEPTED or reason == Reason.NOT_FLYING \
            else REASON_TEXT[reason]  # NOT_FLYING: the take-off is not reported done yet
        return launch.VehicleView(
            position=pose is not None and v.ned_origin is not None and v.lat_lon_deg is not None,
            in_launch_mode=self.profile.in_launch_mode(v.custom_mode),
            in_own_mode=self.profile.in_launch_mode(v.custom_mode, own=True),
            mode_name=self.profile.mode_name(v.custom_mode), armed=v.armed,
            up_m=None if pose is None else float(pose.pos[2]),
            home_up_m=ap.home_up_m(), climbing=v.landed_state in (mavlink.MAV_LANDED_STATE_TAKEOFF,
                                                                mavlink.MAV_LANDED_STATE_IN_AIR),
            prearm_ok=v.prearm_ok, prearm_text=v.prearm_text,
            can_start=result == mavlink.MAV_RESULT_ACCEPTED, start_blocker=blocker)

    def _launch_step(self, now: float) -> None:
        """Advance the launch sequence (onboard/app/autopilot/launch.py) and carry out its actions."""
        if self.launch is None:
            return
        self.launch, actions = launch.step(self.launch, self._launch_view(), now)
        for a in actions:
            if isinstance(a, launch.Say):
                self.say(a.text, SEVERITY[a.level], once=None if a.once is None else f"launch:{a.once}")
            elif a[0] == "mode":
                self.autopilot.set_mode(self.profile.launch_mode)
            elif a[0] == "arm":
                self.autopilot.arm()
            elif a[0] == "takeoff":
                self.autopilot.takeoff(a[1])
            elif a[0] == "start":
                self._enter_monitoring()
        if self.launch is None:
            self.publisher.forget("launch:")
