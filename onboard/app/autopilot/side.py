"""The app's side of the autopilot link: which autopilot it serves (the first HEARTBEAT, and its
profile, onboard/app/autopilot/profiles.py), what it knows of it (the ``Vehicle`` record, its
pose history, its clock, its local origin in the mission frame, whether the link is up), what it
asks of it (telemetry rates, limit parameters, modes, arming, take-off) and what it makes of
what it says. What the rest of the app must react to goes to an ``AutopilotEvents`` listener
(the app). io thread, under the app lock."""
from __future__ import annotations

import logging
import math
from typing import Protocol

from onboard.app.autopilot.profiles import profile_for
from onboard.app.autopilot.clock import UtcMap
from onboard.app.context import AppContext
from onboard.app.mavlink_connection import mavlink, param_name
from onboard.app.part import Handler, Job, Part
from onboard.app.autopilot.pose import (
    FixedOrigin,
    Frame,
    PoseHistory,
    heading_from_global_position_int,
    origin_of,
    valid_global_position_int,
)
from onboard.app.autopilot.px4_events import ARMING_GROUPS, EventMetadata, decode_event
from onboard.app.autopilot.vehicle import Vehicle

log = logging.getLogger("pmon.app")
CHECK_WORDS = " check: "  # "PX4 check: ...": a reason from the autopilot's health and arming report (on_event)
UNHEARD_S = 5.0  # local s without an autopilot, packets refused, before the app says why
STALE_TELEMETRY_S = 2.0  # local s without GLOBAL_POSITION_INT while heartbeats come: ask again
# (message id, Hz) the app asks for on its own link (any ArduPilot / PX4 honours these)
TELEMETRY_HZ = ((mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10.0),
                (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 2.0),
                (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2.0),
                (mavlink.MAVLINK_MSG_ID_SYS_STATUS, 1.0),  # the pre-arm bit (launch)
                (mavlink.MAVLINK_MSG_ID_HEARTBEAT, 4.0))


class AutopilotEvents(Protocol):
    """What the autopilot side tells the rest of the app (the app implements it)."""

    def on_heartbeat(self) -> None: ...  # mode / armed may have changed
    def on_link_lost(self) -> None: ...
    def on_link_back(self, lost_s: float) -> None: ...
    def on_reboot(self) -> None: ...  # its clock went back
    def on_origin_moved(self, off_m: float) -> None: ...  # a different origin was refused
    def on_clock_jump(self, jump_s: float, now: float | None) -> None: ...  # a jump followed
    def on_limits(self) -> None: ...  # a speed / acceleration / jerk limit was read


class AutopilotSide(Part):
    """``ctx``: the app's shared parts (its link, clocks, counters, voice; the config's
    ``target_system`` and ``link_timeout_s``); ``frame``: the mission's ENU frame; ``events``:
    who hears what the autopilot did."""

    def __init__(self, ctx: AppContext, frame: Frame, vehicle: Vehicle, events: AutopilotEvents,
                 events_meta: EventMetadata | None = None):
        self.link = ctx.link
        self.clock = ctx.clock
        self.mono = ctx.mono
        self.frame = frame  # the mission's ENU frame
        self.vehicle = vehicle
        self.poses = PoseHistory()
        self.origin = FixedOrigin()  # the autopilot's NED origin, fixed once (pose.py)
        self.utc = UtcMap()  # its UTC (SYSTEM_TIME): a DF's Unix stamps on its clock (KrakenSDR)
        self.events = events
        self.say = ctx.say
        self.counters = ctx.counters
        self.target_system = ctx.cfg.target_system  # None: the first autopilot heard
        self.link_timeout_s = ctx.cfg.link_timeout_s  # local s without a heartbeat -> link lost
        self.events_meta = events_meta  # PX4's event metadata (its EVENTs in words), if given
        self.link_lost = False
        self._link_lost_local = -math.inf
        self._msg_interval_local = -math.inf
        self._started_local = ctx.mono()
        self._clock_resets = 0
        self._clock_seen = (0, 0)  # clock.jumps, clock.jumps_ignored already reported

    # ----- what the app asks of the autopilot
    def command_long(self, command: int, *params: float) -> None:
        v = self.vehicle
        p = list(params) + [0.0] * (7 - len(params))
        self.link.send(self.link.mav.command_long_encode(v.sysid, v.compid, command, 0, *p))

    def request_telemetry(self) -> None:
        for msg_id, hz in TELEMETRY_HZ:
            self.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
        if self.vehicle.ned_origin is None:
            self.command_long(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)

    def request_limits(self) -> None:
        """The limit parameters and the ones the profile checks (``checked_params``)."""
        v = self.vehicle
        for name in [n for n, _ in v.profile.limit_params] + [*v.profile.jerk_params, *v.profile.checked_params]:
            self.link.send(self.link.mav.param_request_read_encode(v.sysid, v.compid, name.encode(), -1))

    def set_mode(self, name: str) -> None:
        """Ask for a mode by the profile's name for it (only HEARTBEAT says whether it was taken)."""
        self.command_long(mavlink.MAV_CMD_DO_SET_MODE, *self.vehicle.profile.set_mode_params(name))

    def set_mission_mode(self) -> None:
        """Ask for the mode the app flies in (the profile's: GUIDED, OFFBOARD)."""
        self.set_mode(self.vehicle.profile.mission_mode)

    def arm(self) -> None:
        self.vehicle.prearm_text = None  # a refusal now says why afresh
        self.command_long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)

    def takeoff(self, alt_above_home_m: float) -> None:
        v = self.vehicle
        self.command_long(mavlink.MAV_CMD_NAV_TAKEOFF, *v.profile.takeoff_params(
            *v.lat_lon_deg, v.heading_deg, alt_above_home_m, v.amsl_m - v.relative_alt))

    # ----- what the app knows
    def heard_recently(self) -> bool:
        v = self.vehicle
        return v.sysid is not None and self.mono() - v.heartbeat_local <= self.link_timeout_s

    def has_position(self) -> bool:
        """A pose and the local origin setpoints are made relative to."""
        return self.poses.latest() is not None and self.vehicle.ned_origin is not None

    def home_up_m(self) -> float | None:
        """Home's height in the mission frame (the vehicle's height minus its relative altitude)."""
        pose, rel = self.poses.latest(), self.vehicle.relative_alt
        return None if pose is None or rel is None else float(pose.pos[2] - rel)

    # ----- MAVLink in (the router, onboard/app/gcs/dispatch.py, calls these by message type)
    def handlers(self) -> dict[str, Handler]:
        return {
            "HEARTBEAT": self.on_heartbeat,  # from anyone: the autopilot is picked here
            "GLOBAL_POSITION_INT": self.on_global_position_int,
            "SYSTEM_TIME": self.on_system_time,
            "SYS_STATUS": self.on_sys_status,
            "STATUSTEXT": self.on_statustext,
            "EXTENDED_SYS_STATE": self.on_extended_sys_state,
            "GPS_GLOBAL_ORIGIN": self.on_gps_global_origin,
            "COMMAND_ACK": self.on_command_ack,
            "PARAM_VALUE": self.on_param_value,
            "UNKNOWN_410": self.on_event,  # PX4's EVENT, not in pymavlink 2.4.50's dialects
        }

    def on_heartbeat(self, msg) -> None:
        if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.type in (
                mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER):
            return  # ground stations, companions, gimbals ... are not the autopilot
        v = self.vehicle
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if v.sysid is None:
            if self.target_system not in (None, src[0]):
                return
            self._adopt(msg, *src)
        elif src != (v.sysid, v.compid):
            return
        v.heartbeat_local = self.mono()
        if self.link_lost:
            self._link_back()
        v.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        if msg.custom_mode != v.custom_mode:
            v.mode_seen_local = self.mono()
        v.custom_mode = msg.custom_mode
        self.events.on_heartbeat()

    def _adopt(self, msg, sysid: int, compid: int) -> None:
        """The first autopilot heard is the one the app serves; its type picks the profile."""
        v = self.vehicle
        v.sysid, v.compid, v.autopilot = sysid, compid, msg.autopilot
        v.profile = profile_for(msg.autopilot)
        self.link.set_source_system(sysid)  # the app is a component of this vehicle
        self.say(f"autopilot {sysid}/{compid} found")
        if not v.profile.can_sign:
            self._say_unsigned()
        self.request_telemetry()
        self.request_limits()
        self._msg_interval_local = self.mono()

    def _say_unsigned(self) -> None:
        """An autopilot that cannot sign: said plainly, at connection (docs/SAFETY.md)."""
        name = self.vehicle.profile.name
        if self.link.signing:
            self.say(f"{name} cannot sign MAVLink: the autopilot link is UNSIGNED (its packets taken unsigned; "
                     "ground-station commands still need the key; docs/SAFETY.md)", mavlink.MAV_SEVERITY_WARNING)
        else:
            self.say(f"{name} cannot sign MAVLink: the autopilot link cannot be signed (docs/SAFETY.md)",
                     mavlink.MAV_SEVERITY_WARNING)

    def _link_back(self) -> None:
        self.link_lost = False
        self.counters.add("link_regained")
        self.request_telemetry()  # a reconnected link starts with the default rates
        self.events.on_link_back(self.mono() - self._link_lost_local)

    def observe_time(self, msg) -> None:
        """Every autopilot message stamped with ``time_boot_ms`` is a clock sample; a clock that
        went back means the autopilot rebooted."""
        tb = getattr(msg, "time_boot_ms", None)
        if tb is None:
            return
        self.clock.observe(tb)
        if getattr(self.clock, "resets", 0) != self._clock_resets:
            self._clock_resets = self.clock.resets
            self._on_reboot()

    def on_system_time(self, msg) -> None:
        """Its UTC against its boot time (its clock sample was taken by ``observe_time``)."""
        self.utc.observe(msg.time_unix_usec, msg.time_boot_ms)

    def on_global_position_int(self, msg) -> None:
        if not valid_global_position_int(msg):
            return
        v = self.vehicle
        self.poses.add(self.frame.pose_from_global_position_int(msg))
        v.relative_alt = msg.relative_alt / 1000.0
        v.lat_lon_deg = (msg.lat * 1e-7, msg.lon * 1e-7)
        v.amsl_m = msg.alt * 1e-3
        v.heading_deg = heading_from_global_position_int(msg.hdg)
        v.position_local = self.mono()

    def on_sys_status(self, msg) -> None:
        self.vehicle.prearm_ok = self.vehicle.profile.prearm_ok(msg)

    def on_statustext(self, msg) -> None:
        text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("ascii", "replace")
        text = text.split("\x00", 1)[0]
        if self.vehicle.profile.arming_refusal(text):  # why the autopilot refuses to arm
            self.vehicle.prearm_text = text[:50]

    def on_event(self, msg) -> None:
        """PX4's EVENT (id 410, which pymavlink 2.4.50 does not decode; onboard/app/autopilot/px4_events.py)
        in words where the build's event metadata was given (``events_meta``). Its health and
        arming report (a summary, then every check that fails, each with the modes it blocks):
        the first check at warning or worse that blocks the mode the vehicle is in is kept as
        why arming fails (the launch says it), and a report clears what the last one said; an
        "Arming denied" is kept where no check said more; anything else at warning or worse is
        said once."""
        ev = decode_event(msg)
        if ev is None:
            self.counters.add("events_malformed")
            return
        d = self.events_meta.describe(ev) if self.events_meta is not None else None
        if d is None:
            return
        v = self.vehicle
        checked = v.prearm_text is not None and CHECK_WORDS in v.prearm_text
        if d.group in ARMING_GROUPS:
            if d.summary:
                if checked:
                    v.prearm_text = None
            elif ev.severity <= mavlink.MAV_SEVERITY_WARNING and not checked \
                    and self.events_meta.blocks(d, v.custom_mode):
                v.prearm_text = f"{v.profile.name}{CHECK_WORDS}{d.text}"[:80]
        elif v.profile.arming_refusal(d.text):
            if not checked:
                v.prearm_text = d.text[:80]
        elif ev.severity <= mavlink.MAV_SEVERITY_WARNING:
            self.say(f"{v.profile.name}: {d.text}", ev.severity, once=f"event:{d.text}")

    def on_extended_sys_state(self, msg) -> None:
        self.vehicle.landed_state = msg.landed_state

    def on_command_ack(self, msg) -> None:
        refused = msg.result not in (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_IN_PROGRESS)
        v = self.vehicle
        if refused:
            self.counters.add(f"autopilot_refused_{msg.command}")
        if refused and msg.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM and v.prearm_text is None \
                and self.events_meta is None and v.profile.refusal_elsewhere:
            v.prearm_text = v.profile.refusal_elsewhere  # its reasons go where the app cannot read them
        if msg.command == mavlink.MAV_CMD_DO_SET_MODE:  # not proof of the mode: said when one is not taken
            self.vehicle.mode_ack = msg.result

    def on_param_value(self, msg) -> None:
        """The autopilot's speed / acceleration / jerk limits, read at connection and again
        whenever it sends one (ArduPilot tells every link when a ground station changes it); a
        value that is no limit (the profile's ``limit_refusal``: NaN, zero, negative, absurd) is
        said once and not used (the last good one, or none, stays); a parameter the profile
        checks is judged and a bad value said (again whenever it changes)."""
        profile = self.vehicle.profile
        name, value = param_name(msg.param_id), profile.param_value(msg)
        if name in profile.checked_params:
            warning = profile.param_warning(name, value)
            if warning is not None:
                self.say(warning, mavlink.MAV_SEVERITY_WARNING, once=f"param:{name}={value:g}")
            return
        factors = dict(profile.limit_params)
        if name not in factors and name not in profile.jerk_params:
            return
        refusal = profile.limit_refusal(name, value)
        if refusal is not None:
            self.counters.add("limit_params_refused")
            self.say(f"autopilot {name} = {value:g} is no limit ({refusal}): not planned with",
                     mavlink.MAV_SEVERITY_WARNING, once=f"limit:{name}={value:g}")
            return
        v = self.vehicle
        v.limit_values[name] = value
        (speed_name, speed_k), (accel_name, accel_k) = profile.limit_params
        if name == speed_name:
            v.speed_limit_mps = value * speed_k
        elif name == accel_name:
            v.accel_limit_mps2 = value * accel_k
        v.jerk_limit_mps3 = profile.jerk_limit(v.limit_values)
        self.events.on_limits()

    def on_gps_global_origin(self, msg) -> None:
        """The NED origin is fixed by the first valid GPS_GLOBAL_ORIGIN and never moved in
        flight (pose.FixedOrigin): a different one is refused, and since the app cannot tell
        which one the vehicle flies by, the listener stops commanding (resume flies on the
        fixed origin; every setpoint is still checked against the fence as it is sent)."""
        origin = origin_of(msg)
        if origin is None:
            self.counters.add("origin_invalid")
            return
        if getattr(self.clock, "reboot_pending", False):
            # a rebooted autopilot's new origin can come before its clock confirms the reboot
            # (PX4 sends it unasked): not compared with the old boot's; asked again after
            self.counters.add("origin_during_reboot")
            return
        first = self.origin.value is None
        off = self.origin.offer(origin)
        if off is None:
            if first:
                self.vehicle.ned_origin = self.origin.value
                log.info("autopilot NED origin: %.7f %.7f %.2f m", *origin)
                self.say("NED origin fixed")  # the same words whatever the place (tests/firmware/test_conformance.py)
            return
        self.counters.add("origin_changes_refused")
        self.events.on_origin_moved(off)

    def _on_reboot(self) -> None:
        """A new boot sets its EKF origin anew: the fixed one is let go (the listener starts its
        scan bookkeeping over and stops commanding)."""
        self.counters.add("autopilot_reboots")
        self.origin.clear()
        self.vehicle.ned_origin = None
        self.events.on_reboot()
        self.say("autopilot rebooted: DF scan times start over", mavlink.MAV_SEVERITY_WARNING)

    # ----- periodic jobs (io thread, under the lock)
    def jobs(self) -> tuple[Job, ...]:
        return (Job("periodic telemetry", lambda local, now: self.periodic_requests(local)),
                Job("periodic signing", lambda local, now: self.periodic_signing(local)),
                Job("periodic link", lambda local, now: self.periodic_link(local)),
                Job("periodic clock", lambda local, now: self.periodic_clock(now)))

    def periodic_signing(self, local: float) -> None:
        """What signing keeps out, said once each: no autopilot yet while unsigned packets are
        refused (one that cannot sign is heard only with --autopilot-unsigned), and a sender
        whose signatures fail (a wrong key; or forwarded by an autopilot that rewrites them)."""
        if not self.link.signing:
            return
        from onboard.app.signing import bad_signatures
        mav, v = self.link.mav, self.vehicle
        refused = getattr(getattr(mav, "signing", None), "reject_count", 0)
        if v.sysid is None and refused and local - self._started_local > UNHEARD_S:
            self.say(f"no autopilot heard: {refused} unsigned packets refused (an autopilot that cannot sign, "
                     "PX4, needs --autopilot-unsigned; docs/SAFETY.md)", mavlink.MAV_SEVERITY_WARNING,
                     once="unsigned_refused")
        for (sysid, compid), n in bad_signatures(mav).items():
            why = (f"{v.profile.name} rewrites the signature of every message it forwards: sign on a path that "
                   "does not pass through it" if v.sysid is not None and not v.profile.can_sign
                   else "a wrong key, or a forgery")
            self.say(f"packets from {sysid}/{compid} fail their signature ({why}; docs/SAFETY.md)",
                     mavlink.MAV_SEVERITY_WARNING, once=f"badsig:{sysid}/{compid}")

    def periodic_requests(self, local: float) -> None:
        """Ask for the telemetry again while the origin is unknown or positions stop coming with
        heartbeats still there: an autopilot that rebooted (or a link reopened to it) starts
        from its default rates, which on ArduPilot send no position at all."""
        v = self.vehicle
        stale = local - v.heartbeat_local < 1.5 and local - v.position_local > STALE_TELEMETRY_S
        if v.sysid is not None and (v.ned_origin is None or stale) and local - self._msg_interval_local > 2.0:
            self._msg_interval_local = local
            self.request_telemetry()

    def periodic_link(self, local: float) -> None:
        """Link loss (local time: no heartbeat for link_timeout_s, or a stream link that dropped:
        nothing can be sent on it): the listener stops commanding at once."""
        v = self.vehicle
        if v.sysid is not None and not self.link_lost and (
                local - v.heartbeat_local > self.link_timeout_s or not self.link.up):
            self.link_lost = True
            self._link_lost_local = local
            self.counters.add("link_losses")
            self.events.on_link_lost()

    def periodic_clock(self, now: float | None) -> None:
        """Report the clock's jumps (clock.py): a candidate it refused, or a jump it followed
        (the listener restarts the tick schedule on the new timeline; a jump back is a reboot,
        handled when the clock followed it)."""
        c = self.clock
        seen = (getattr(c, "jumps", 0), getattr(c, "jumps_ignored", 0))
        if seen == self._clock_seen:
            return
        (j0, i0), self._clock_seen = self._clock_seen, seen
        if seen[1] > i0:
            self.counters.add("clock_jumps_ignored", seen[1] - i0)
            self.say("autopilot time jump not confirmed: ignored", mavlink.MAV_SEVERITY_WARNING,
                     once="clock_ignored")
        if seen[0] > j0:
            self.counters.add("clock_jumps", seen[0] - j0)
            jump = getattr(c, "last_jump_s", 0.0)
            if jump > 0 and now is not None:
                self.say(f"autopilot clock jumped {jump:+.0f} s: ticks restart", mavlink.MAV_SEVERITY_CRITICAL)
            self.events.on_clock_jump(jump, now)
