"""The onboard app's side of the autopilot link: what it asks the autopilot for, and what it
makes of what the autopilot says (heartbeats and modes, telemetry, its origin, its speed
limits, reboots, acknowledgements, commands and parameters for the app). A mixin of
``OnboardApp`` (onboard/app/app.py): io thread, under the app lock."""
from __future__ import annotations

import logging
import math

from onboard.app.autopilot_profiles import heading_from_global_position_int, prearm_ok
from onboard.app.contract import WARN_SPEED, Reason, State
from onboard.app.mavlink_connection import COMP_ID, mavlink
from onboard.app.pose import origin_of, valid_global_position_int
from onboard.app.vehicle_state import SPEED_ACCEL_PARAMS
from onboard.policy import vehicle_motion

log = logging.getLogger("pmon.app")
STALE_TELEMETRY_S = 2.0  # local s without GLOBAL_POSITION_INT while heartbeats come: ask again


class AutopilotIn:
    """Methods of ``OnboardApp``; the attributes they use are set up in ``OnboardApp.__init__``."""

    def _request_telemetry(self) -> None:
        """Ask for the rates the app needs on its own link (any ArduPilot / PX4 honours these)."""
        for msg_id, hz in ((mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10.0),
                           (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 2.0),
                           (mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 2.0),
                           (mavlink.MAVLINK_MSG_ID_SYS_STATUS, 1.0),  # the pre-arm bit (launch)
                           (mavlink.MAVLINK_MSG_ID_HEARTBEAT, 4.0)):
            self._command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
        if self.vehicle.ned_origin is None:
            self._command_long(mavlink.MAV_CMD_REQUEST_MESSAGE,
                               mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)

    def _on_mavlink(self, msg) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self._count("mavlink_bad_data")
            return
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        if mtype == "HEARTBEAT":
            self._on_heartbeat(msg, src_sys, src_comp)
            return
        if self.vehicle.sysid is None:
            return
        from_autopilot = (src_sys, src_comp) == (self.vehicle.sysid, self.vehicle.compid)
        tb = getattr(msg, "time_boot_ms", None)
        if from_autopilot and tb is not None:
            self.clock.observe(tb)
            if getattr(self.clock, "resets", 0) != self._clock_resets:
                self._clock_resets = self.clock.resets
                self._on_autopilot_reboot()
        if from_autopilot:
            if mtype == "GLOBAL_POSITION_INT":
                if valid_global_position_int(msg):
                    v = self.vehicle
                    self.poses.add(self.frame.pose_from_global_position_int(msg))
                    v.relative_alt = msg.relative_alt / 1000.0
                    v.lat_lon_deg = (msg.lat * 1e-7, msg.lon * 1e-7)
                    v.amsl_m = msg.alt * 1e-3
                    v.heading_deg = heading_from_global_position_int(msg.hdg)
                    v.position_local = self.mono()
            elif mtype == "SYS_STATUS":
                self.vehicle.prearm_ok = prearm_ok(msg)
            elif mtype == "STATUSTEXT":
                text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("ascii", "replace")
                if text.startswith(("PreArm:", "Arm:")):  # why the autopilot refuses to arm
                    self.vehicle.prearm_text = text.split("\x00", 1)[0][:50]
            elif mtype == "EXTENDED_SYS_STATE":
                self.vehicle.landed_state = msg.landed_state
            elif mtype == "GPS_GLOBAL_ORIGIN":
                self._on_origin(msg)
            elif mtype == "COMMAND_ACK":
                self._on_autopilot_ack(msg)
            elif mtype == "PARAM_VALUE":
                self._on_autopilot_param(msg)
            return
        # messages for this component (from a ground station, routed or direct)
        tsys = getattr(msg, "target_system", None)
        tcomp = getattr(msg, "target_component", None)
        if tsys is None or tsys not in (0, self.vehicle.sysid) or tcomp not in (0, COMP_ID):
            return
        if mtype in ("COMMAND_LONG", "COMMAND_INT", "PARAM_SET") and tcomp == COMP_ID \
                and src_sys not in self.cfg.gcs_sysids:
            # only configured ground stations command the app; no ACK: nothing to tell a stranger
            self._count("rejected_sysid")
            self.say(f"{mtype} from sysid {src_sys} ignored: not a configured GCS",
                     mavlink.MAV_SEVERITY_WARNING, once=f"sysid{src_sys}")
            return
        if mtype == "COMMAND_LONG" and tcomp == COMP_ID:
            if msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE and int(msg.param1) == \
                    mavlink.MAVLINK_MSG_ID_DEBUG_FLOAT_ARRAY:
                self._ack(msg, mavlink.MAV_RESULT_ACCEPTED)  # PMON_STAT at once (h4 request 3)
                self._publish_stat()
                return
            self._on_command(msg)
        elif mtype == "COMMAND_INT" and tcomp == COMP_ID:
            self._ack(msg, mavlink.MAV_RESULT_UNSUPPORTED, Reason.UNKNOWN_ACTION)
        elif mtype == "PARAM_REQUEST_LIST":
            for i, name in enumerate(self.params.names()):
                self._param_value(name, i)
        elif mtype == "PARAM_REQUEST_READ":
            self._on_param_read(msg)
        elif mtype == "PARAM_SET" and tcomp == COMP_ID:
            self._on_param_set(msg)

    def _on_origin(self, msg) -> None:
        """The NED origin is fixed by the first valid GPS_GLOBAL_ORIGIN and never moved in
        flight (pose.FixedOrigin): a different one is refused, and since the app cannot tell
        which one the vehicle flies by, it stops commanding and says so (resume flies on the
        fixed origin; every setpoint is still checked against the fence as it is sent)."""
        origin = origin_of(msg)
        if origin is None:
            self._count("origin_invalid")
            return
        first = self.origin.value is None
        off = self.origin.offer(origin)
        if off is None:
            if first:
                self.vehicle.ned_origin = self.origin.value
                log.info("autopilot NED origin: %.7f %.7f %.2f m", *origin)
                self.say("NED origin fixed")  # the same words whatever the place (tests/test_conformance.py)
            return
        self._count("origin_changes_refused")
        if self.state == State.MONITORING:
            self._set_state(State.FAULT)
            self.say(f"NED origin moved {off:.0f} m: refused, setpoints stopped", mavlink.MAV_SEVERITY_CRITICAL)
        else:
            self.say(f"NED origin moved {off:.0f} m: refused", mavlink.MAV_SEVERITY_CRITICAL,
                     once="origin_moved")

    def _on_heartbeat(self, msg, src_sys: int, src_comp: int) -> None:
        if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.type in (
                mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER):
            return  # ground stations, companions, gimbals ... are not the autopilot
        v = self.vehicle
        if v.sysid is None:
            if self.cfg.target_system not in (None, src_sys):
                return
            v.sysid, v.compid, v.autopilot = src_sys, src_comp, msg.autopilot
            self.link.set_source_system(src_sys)  # the app is a component of this vehicle
            self.say(f"autopilot {src_sys}/{src_comp} found")
            self._request_telemetry()
            self._request_speed_limits()
            self._msg_interval_local = self.mono()
        elif (src_sys, src_comp) != (v.sysid, v.compid):
            return
        v.heartbeat_local = self.mono()
        if self._link_lost:
            self._link_lost = False
            self._count("link_regained")
            self._request_telemetry()  # a reconnected link starts with the default rates
            # said now: "link lost" could reach no one while the link was down
            lost_s = self.mono() - self._link_lost_local
            self.say(f"link back (lost {lost_s:.0f} s)" + (": send resume" if self.state == State.FAULT else ""),
                     mavlink.MAV_SEVERITY_WARNING)
        v.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        changed = msg.custom_mode != v.custom_mode
        v.custom_mode = msg.custom_mode
        if changed:
            v.mode_seen_local = self.mono()
        self._check_mode()

    def _on_autopilot_reboot(self) -> None:
        """The autopilot's clock went back: it rebooted. DF scans are stamped with that clock,
        so the scan bookkeeping starts over (else every new scan would be 'stale'); the
        filters keep their state (the targets did not reboot) and go on from the next scan."""
        self._count("autopilot_reboots")
        self.scans.pending.clear()
        self.scans.arrival.clear()
        self.scans.consumed_until = -math.inf
        self.scans.last_scan_t = [-math.inf] * self.M
        self._scan_t_used = [-math.inf] * self.M
        self.last_tick_t = None
        self._tick_times = []
        # a new boot sets its EKF origin anew: the fixed one is let go, and the vehicle is not
        # ours to fly until the operator says so (the link was lost meanwhile, as a rule)
        self.origin.clear()
        self.vehicle.ned_origin = None
        if self.state in (State.MONITORING, State.PAUSED):
            self._set_state(State.FAULT)
        self.say("autopilot rebooted: DF scan times start over", mavlink.MAV_SEVERITY_WARNING)

    def _check_mode(self) -> None:
        """Stop commanding the moment the vehicle leaves the mode the app put it in."""
        v = self.vehicle
        if self.state == State.MONITORING:
            if self._guided_deadline is not None:
                if v.is_guided():
                    self._guided_deadline = None
                    self.say("GUIDED: monitoring")
                return
            if not v.is_guided() or not v.armed:
                why = "disarmed" if not v.armed else f"mode {v.custom_mode}"
                self._set_state(State.PILOT_OVERRIDE)
                self.say(f"pilot override ({why}): setpoints stopped", mavlink.MAV_SEVERITY_WARNING)

    def _request_speed_limits(self) -> None:
        v = self.vehicle
        for name, _ in SPEED_ACCEL_PARAMS.get(v.autopilot, ()):
            self.link.send(self.link.mav.param_request_read_encode(v.sysid, v.compid, name.encode(), -1))

    def _on_autopilot_param(self, msg) -> None:
        """The autopilot's speed / acceleration limit, read at connection and again whenever it
        sends one (ArduPilot tells every link when a ground station changes it)."""
        names = SPEED_ACCEL_PARAMS.get(self.vehicle.autopilot)
        if not names:
            return
        (speed_name, speed_k), (accel_name, accel_k) = names
        name, value = self._param_name(msg.param_id), float(msg.param_value)
        if not math.isfinite(value) or value <= 0.0 or name not in (speed_name, accel_name):
            return
        if name == speed_name:
            self.vehicle.speed_limit_mps = value * speed_k
        else:
            self.vehicle.accel_limit_mps2 = value * accel_k
        self._check_speed_limits()

    def _check_speed_limits(self) -> None:
        """The planner's speed and acceleration against the autopilot's limits (docs/MAVLINK.md).

        Vehicle motion (the flight policy): the planner flies at the autopilot's limits, capped
        by the scenario's ``planning.speed_max_mps`` / ``accel_max_mps2`` (what the airframe can
        fly): a change of either rebuilds the core setup (``_limits``), and no plan is faster
        than the autopilot flies. The jump model (the paper's policy) asks for its grid's rings
        each tick whatever the autopilot's limit: below it the vehicle lags its setpoints, a
        warning that holds until the limits or PMON_REACH change: PMON_STAT carries it every
        second (``pmon gcs status`` shows it), and it is said when it first holds and again
        whenever monitoring starts."""
        names = SPEED_ACCEL_PARAMS.get(self.vehicle.autopilot)
        if not names:
            return
        (speed_name, _), (accel_name, _) = names
        sc = self.base_scenario
        pl = sc.planning
        v = self.vehicle
        if pl.motion == "vehicle":
            m = vehicle_motion(pl, v.speed_limit_mps or math.inf, v.accel_limit_mps2 or math.inf)
            speed, accel = m.speed_max_mps, m.accel_max_mps2
            if (speed, accel) != self._limits:
                self._limits = (speed, accel)
                self._plan_limits = (speed, accel)
                self.say(f"planning at {speed:g} m/s, {accel:g} m/s^2")
            self._warnings, self.speed_warning = 0, None
            return
        # the paper's jump: the largest ring asked for, per tick (no acceleration assumed)
        reach = min(sc.uav.n_radial * sc.uav.step_m, self.params["PMON_REACH"])
        speed_need, speed_why = reach / sc.dynamics.dt_s, "the planner's steps (PMON_REACH)"
        checks = [(WARN_SPEED, speed_name, v.speed_limit_mps, speed_need, speed_why, "m/s")]
        self._plan_limits = (speed_need, math.nan)
        bits, texts, details = 0, [], []
        for bit, name, have, need, why, unit in checks:
            if have is None or have >= need - 1e-6:  # not read yet (the other may be), or enough
                continue
            bits |= bit
            texts.append(f"{name} {have:g} {unit} < {need:g} planned")
            details.append(f"autopilot {name} = {have:g} {unit} is below {why} = {need:g} {unit}")
        text = "; ".join(texts) or None
        changed = text != self.speed_warning
        self._warnings, self.speed_warning = bits, text
        if changed and text is not None:
            log.warning("%s: the vehicle will lag the setpoints", "; ".join(details))
            self.say(text, mavlink.MAV_SEVERITY_WARNING)

    def _on_autopilot_ack(self, msg) -> None:
        if msg.result not in (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_IN_PROGRESS):
            self._count(f"autopilot_refused_{msg.command}")
