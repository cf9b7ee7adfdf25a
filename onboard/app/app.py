"""The onboard app: the imperative shell around ``onboard.core.monitor.tick``.

Threads (all daemon; ``stop()`` joins them):
  io      MAVLink in (heartbeats, telemetry, commands, parameters), DF datagrams in (parsed),
          and every periodic job on the autopilot clock: heartbeat, setpoint re-send, tick
          scheduling, launch sequence, link watchdog, PMON_STAT. Each message, datagram and job
          is its own contained handler (onboard/app/contain.py): an error is counted under its
          kind and the loop goes on, so nothing a peer sends can skip the schedule; reads are
          bounded per iteration (``IO_MAVLINK_MAX``, ``IO_DF_MAX``).
  df      reads the DF port at line rate, drops foreign and rate-limited senders unparsed, and
          queues the rest for the io thread (onboard/app/df_input.py).
  worker  one core tick at a time. A scan that becomes due while the worker is busy waits;
          when it frees, only the newest due scan is ticked and older ones are counted as
          skipped: an overrun is skipped, never queued.

State (HEARTBEAT.custom_mode and PMON_STAT[0]): 0 idle, 1 monitoring, 2 paused, 3 pilot
override, 4 fault. Only ``monitoring`` sends setpoints, and only while the autopilot is in the
mode the app put it in (GUIDED); any other mode set by someone else -> pilot override, at once.

Tracking runs whenever scans arrive (every state): the filters stay in step with the targets
while the vehicle takes off or a pilot flies; planning and setpoints only in ``monitoring``.
"""
from __future__ import annotations

import logging
import math
import select
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from onboard.app import datagram as dg
from onboard.app import launch
from onboard.app.autopilot_in import STALE_TELEMETRY_S, AutopilotIn
from onboard.app.clock import AutopilotClock
from onboard.app.state_machine import Commands
from onboard.app.contain import Contained
from onboard.app.contract import STAT_FIELDS, STATUS, TGT_FIELDS, Action, Reason, State
from onboard.app.df_input import DEFAULT_RATE_HZ, DfInput, Source
from onboard.app.fence import Fence, outgoing_violation
from onboard.app.mavlink_connection import Link, mavlink
from onboard.app.params import SPECS, ParamTable, defaults_from_scenario
from onboard.app.pose import FixedOrigin, Frame, PoseHistory
from onboard.app.schedule import COAST_AFTER_S, TickRecord
from onboard.app.setpoint_stream import PlannedSegment, enu_to_ned_vector
from onboard.app.setpoint_stream import message as setpoint_message
from onboard.app.vehicle_state import Vehicle
from onboard.app.watchdog import Watchdog
from onboard.app.worker import TickWorker, _malloc_trim
from onboard.core.guidance import GuidanceWorkspace
from onboard.core.monitor import MonitorSetup, initial_state
from onboard.core.planning import CandidateGrid
from onboard.core.tracking import ParticleSet

log = logging.getLogger("pmon.app")

IO_MAVLINK_MAX = 500  # MAVLink messages handled per io iteration, then the periodic jobs
IO_DF_MAX = 200  # DF datagrams parsed per io iteration (the reader's rate limit bounds the rest)


@dataclass(frozen=True)
class AppConfig:
    mavlink_url: str
    sensor_host: str = "127.0.0.1"
    sensor_port: int = 14600  # 0: pick a free port (see OnboardApp.sensor_port)
    baud: int = 57600
    target_system: int | None = None  # None: the first autopilot heard
    auto_launch: bool = False  # the demo's "by itself": GUIDED, arm, take off, start
    seed: int = 0
    runlog_path: str | None = None
    tlog_path: str | None = None
    link_timeout_s: float = 3.0  # local seconds without autopilot heartbeats -> link lost
    # system ids whose commands and parameter writes are obeyed (reads are answered to anyone)
    gcs_sysids: tuple[int, ...] = (255,)
    signing_key_path: str | None = None  # MAVLink 2 signing key file (onboard/app/signing.py)
    history: int = 600  # tick records kept in memory (app.ticks, ~3 kB each); the run log keeps all
    watchdog_s: float = 3.0  # autopilot s a tick may run (or the io loop stall) before a report
    # autopilot s between returns of freed heap memory to the OS (glibc malloc_trim, by the idle
    # worker); 0: never. A tick's planning allocates tens of MB for a moment; without this the
    # allocator keeps the largest such peak resident for good (see docs/SAFETY.md, long flights)
    trim_memory_s: float = 60.0
    # DF senders accepted (onboard/app/df_input.py); empty: the first peer whose datagram is valid
    df_sources: tuple[Source, ...] = ()
    df_rate_hz: float = DEFAULT_RATE_HZ  # datagrams/s per accepted DF sender; the excess is dropped


class OnboardApp(AutopilotIn, Commands, TickWorker, Watchdog):
    """The app: its state and threads; each role's methods are in the module its mixin names."""

    def __init__(self, cfg: AppConfig, scenario, clock=None, link: Link | None = None,
                 monotonic: Callable[[], float] = time.monotonic):
        self.cfg = cfg
        self.base_scenario = scenario
        self.frame = Frame(scenario.origin.lat_deg, scenario.origin.lon_deg, scenario.origin.alt_m)
        self.mono = monotonic
        self.clock = clock if clock is not None else AutopilotClock(monotonic)
        key = None
        if cfg.signing_key_path is not None:
            from onboard.app.signing import load_key
            key = load_key(cfg.signing_key_path)  # KeyFileError: refuse to start
        # an autopilot still booting (TCP refused) is waited for, as after a reboot
        self.link = link or Link(cfg.mavlink_url, cfg.baud, cfg.tlog_path,
                                 source_system=cfg.target_system or 1, signing_key=key,
                                 wait_for_peer=True)
        self.params = ParamTable(defaults_from_scenario(scenario))
        self.M = len(scenario.targets)
        self.scans = dg.ScanBuffer(self.M)
        self.poses = PoseHistory()
        self.vehicle = Vehicle()
        self.state = State.IDLE
        self.lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        try:
            self.df = DfInput(cfg.sensor_host, cfg.sensor_port, cfg.df_sources, cfg.df_rate_hz)
        except BaseException:
            self.link.close()
            raise
        self.sensor_port = self.df.port
        self._runlog = open(cfg.runlog_path, "w", buffering=1) if cfg.runlog_path else None
        self.rng = np.random.default_rng(cfg.seed)
        # core state, touched by the worker only (and by stop() after the join)
        # vehicle motion: (speed m/s, accel m/s^2) the planner flies at, the autopilot's limits
        # capped by the scenario's (None until the autopilot's are read)
        self._limits: tuple[float, float] | None = None
        self._setup_version: tuple | int = -1
        self.setup: MonitorSetup | None = None
        self.core_state = None
        self.workspace = GuidanceWorkspace()
        self._build_setup()
        # tick bookkeeping
        self._job: TickRecord | None = None
        self._job_event = threading.Event()
        self._worker_busy = False
        self.last_tick_t: float | None = None
        self.generation = 0  # bumped when setpoints must stop; results of older ticks are dropped
        self.setpoint: np.ndarray | None = None  # ENU, m, checked safe: the planned next point
        self.segment: PlannedSegment | None = None  # vehicle motion: the plan to it (setpoint_stream.py)
        self._next_sp_t = -math.inf
        self._guided_deadline: float | None = None  # waiting for GUIDED after start/resume
        self.counters: dict[str, int] = {}
        # bounded: a long flight must not grow the app's memory (bench/soak.py checks RSS); every
        # buffer below has a limit, and whatever must be kept for good goes to the run log
        self.ticks: deque[dict] = deque(maxlen=cfg.history)  # per-tick summaries
        self.latest: dict | None = None
        # called with each tick's record (worker thread, after it is complete); a listener keeps
        # what it needs (bench/latency.py counts every tick this way, whatever ``history`` is);
        # it must be quick, and an exception in it is counted (listener_errors), never raised
        self.tick_listeners: list[Callable[[dict], None]] = []
        self.sent_setpoints: deque[tuple[float, float, np.ndarray]] = deque(maxlen=600)  # (ap t, local t, enu)
        self._hb_local = -math.inf
        self._stat_local = -math.inf
        self._msg_interval_local = -math.inf
        self._launch: launch.Launch | None = None
        self._clock_resets = 0
        self._link_lost_local = -math.inf
        self.speed_warning: str | None = None  # the limit below plan, while it holds
        self._warnings = 0  # WARN_* bits
        self._plan_limits = (math.nan, math.nan)  # (speed m/s, accel m/s^2) the planner assumes
        self._said: set[str] = set()
        self.events: deque[tuple[float | None, str]] = deque(maxlen=500)
        self._tick_times: list[float] = []
        # failsafes
        self._link_lost = False
        self._silent = False  # DF silence episode (coasting) in progress
        self._fallback = [0] * self.M  # consecutive ticks target j's guidance was on a fallback
        self._scan_t_used = [-math.inf] * self.M
        self._last_good: list[tuple[np.ndarray, np.ndarray] | None] = [None] * self.M
        self._io_beat = self.mono()
        self._sched_beat = self.mono()  # the tick schedule job last ran to its end (local s)
        self._submitted_t: float | None = None  # autopilot time the last tick was handed over
        self.errors = Contained(log, on_first=self._say_error)  # io-thread handler errors by kind
        self.origin = FixedOrigin()  # the autopilot's NED origin, fixed once (pose.py)
        self._clock_seen = (0, 0)  # clock.jumps, clock.jumps_ignored already reported
        self._df_seen: set = set()  # foreign DF senders reported
        self._df_limited_seen = 0
        self._running: TickRecord | None = None
        self._alarmed: set[str] = set()
        self.watchdog: dict[str, int] = {}  # written by the watchdog thread only
        self._malloc_trim = _malloc_trim() if cfg.trim_memory_s > 0 else None
        self._trimmed_t = -math.inf

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "OnboardApp":
        self.df.start()
        for name, fn in (("pmon-io", self._io_loop), ("pmon-worker", self._worker_loop),
                         ("pmon-watchdog", self._watchdog_loop)):
            th = threading.Thread(target=fn, name=name, daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def stop(self) -> None:
        self._stop.set()
        self._job_event.set()
        for th in self._threads:
            th.join(timeout=10.0)
        self._threads = []
        self.df.stop()
        self.link.close()
        if self._runlog is not None:
            self._runlog.close()
            self._runlog = None

    def __enter__(self) -> "OnboardApp":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def signing_counts(self) -> dict[str, int]:
        """MAVLink signing counters of the autopilot link (all zero when signing is off)."""
        from onboard.app.signing import counts
        return counts(self.link.mav)

    def _count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    # ------------------------------------------------------------------ core setup
    def _build_setup(self) -> None:
        """(Re)build the core setup from the parameters and the autopilot's speed limits (vehicle
        motion: ``_limits``, autopilot_in.py); called by the worker before a tick."""
        version = (self.params.version, self._limits)
        if self._setup_version == version:
            return
        sc = self.params.apply(self.base_scenario)
        if sc.planning.motion == "vehicle" and self._limits is not None:
            speed, accel = self._limits
            sc = replace(sc, planning=replace(sc.planning, speed_max_mps=speed, accel_max_mps2=accel))
        old = self.setup
        self.setup = MonitorSetup.from_scenario(sc)
        self.scenario = sc
        if self.core_state is None:
            self.core_state = initial_state(self.setup, self.rng)
        else:
            n = self.setup.n_particles
            beliefs = []
            for b in self.core_state.beliefs:
                if len(b) != n:  # resample the current belief to the new particle count
                    idx = self.rng.choice(len(b), size=n, p=b.weights / b.weights.sum())
                    b = ParticleSet(b.particles[idx], np.full(n, -np.log(n)))
                beliefs.append(b)
            plans = self.core_state.plans
            if old is not None and old.guidance != self.setup.guidance:
                plans = (None,) * self.M  # warm starts of another horizon do not fit
                self.workspace = GuidanceWorkspace()
            self.core_state = type(self.core_state)(tuple(beliefs), plans, self.core_state.step)
        self._setup_version = version

    def _grid_within_reach(self) -> CandidateGrid:
        """The candidate grid without the rings the vehicle cannot fly in one tick."""
        g = self.setup.grid
        reach = self.params["PMON_REACH"]
        n_r = min(g.n_radial, int(math.floor(reach / g.step_m + 1e-9)))
        return CandidateGrid(g.step_m, n_r, g.n_heading, g.altitude_m)

    # ------------------------------------------------------------------ messages out
    def say(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO, once: str | None = None) -> None:
        """STATUSTEXT 'PMON: ...' (and the event list/log). ``once``: a key said only once."""
        if once is not None:
            if once in self._said:
                return
            self._said.add(once)
        full = f"PMON: {text}"
        self.events.append((self.clock.now(), full))
        log.info(full)
        if self.vehicle.sysid is not None:
            self.link.send(self.link.mav.statustext_encode(severity, full.encode()[:50]))

    def _heartbeat(self) -> None:
        self.link.send(self.link.mav.heartbeat_encode(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(self.state), STATUS[self.state]))

    def _debug_array(self, name: str, array_id: int, values, t: float | None) -> None:
        data = [float(v) if np.isfinite(v) else float("nan") for v in values][:58]
        data += [0.0] * (58 - len(data))
        usec = int((t or 0.0) * 1e6)
        self.link.send(self.link.mav.debug_float_array_encode(usec, name.encode(), array_id, data))

    def _publish_stat(self) -> None:
        tk = self.latest or {}
        nxt = self.setpoint if self.setpoint is not None else (math.nan,) * 3
        pose = self.poses.latest()
        uav = pose.pos if pose is not None else (math.nan,) * 3
        rate = 0.0
        if len(self._tick_times) >= 2:
            span = self._tick_times[-1] - self._tick_times[0]
            rate = (len(self._tick_times) - 1) / span if span > 0 else 0.0
        values = [
            int(self.state), rate, tk.get("t", math.nan), tk.get("tick_ms", math.nan), *nxt,
            self.scans.accepted, self.scans.rejected_total + self.df.dropped_total,
            self.counters.get("ticks", 0),
            self.counters.get("ticks_skipped", 0), tk.get("latency_ms") if tk.get("latency_ms") is not None else math.nan,
            self.vehicle.custom_mode if self.vehicle.custom_mode is not None else -1,
            float(self.vehicle.armed), *uav, tk.get("sum_trace") if tk.get("sum_trace") is not None else math.nan,
            self.counters.get("ticks_late", 0), self.counters.get("setpoints_refused", 0),
            self._warnings, _nan(self.vehicle.speed_limit_mps), self._plan_limits[0],
            _nan(self.vehicle.accel_limit_mps2), self._plan_limits[1],
            -1 if self._launch is None else launch.PHASES.index(self._launch.phase),
        ]
        self._debug_array("PMON_STAT", 0, values, self.clock.now())

    def _command_long(self, command: int, *params: float, target_comp: int | None = None) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        self.link.send(self.link.mav.command_long_encode(
            self.vehicle.sysid, self.vehicle.compid if target_comp is None else target_comp,
            command, 0, *p))

    # ------------------------------------------------------------------ io thread
    def _io_loop(self) -> None:
        while not self._stop.is_set():
            self._io_beat = self.mono()
            try:
                self._io_once()
            except Exception as exc:  # the glue itself: every handler below is contained already
                self._count("io_errors")
                self.errors.caught("io loop", exc)
                time.sleep(0.002)

    def _io_once(self) -> None:
        """One iteration: wait up to 2 ms for MAVLink, handle what came (bounded), parse queued
        DF datagrams (bounded), run the periodic jobs. Each handler is contained: its error is
        counted and the rest of the iteration runs."""
        fd = self.link.fileno()
        if fd is not None:
            try:
                select.select([fd], [], [], 0.002)
            except (OSError, ValueError):
                time.sleep(0.002)
        else:
            time.sleep(0.002)
        if not self.errors.run("MAVLink read", self._read_mavlink):  # the link itself failing
            with self.lock:
                self._count("io_errors")
        for data, addr in self.df.pop(IO_DF_MAX):
            with self.lock:
                self._handle("DF datagram", self._on_datagram, data, addr)
        with self.lock:
            self._periodic()

    def _read_mavlink(self) -> None:
        for _ in range(IO_MAVLINK_MAX):  # pymavlink buffers several messages per read
            msg = self.link.recv()
            if msg is None:
                break
            with self.lock:
                self._handle(f"MAVLink {_msg_type(msg)}", self._on_mavlink, msg)

    def _handle(self, where: str, fn, *args) -> bool:
        """Run one handler contained (io thread, under the lock): an error is counted
        (``io_errors``, ``errors.counts`` by kind), the first of a kind logged and said."""
        ok = self.errors.run(where, fn, *args)
        if not ok:
            self._count("io_errors")
        return ok

    def _say_error(self, kind: str, exc: BaseException) -> None:
        with self.lock:  # the MAVLink read's handler runs without it
            self.say(f"error in {kind}"[:44], mavlink.MAV_SEVERITY_ERROR)

    def _on_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        if not self.df.accepts(addr):  # queued before the lock to another sender
            self._count("df_foreign_queued")
            return
        try:
            self.scans.offer(data, self.clock.now())
        except dg.DatagramError as err:
            if self.scans.rejected[err.reason] == 1:  # the first of each kind
                self.say(f"bad DF datagram: {err}"[:44], mavlink.MAV_SEVERITY_WARNING)
            return
        if self.df.lock(addr):
            self.say(f"DF source {addr[0]}:{addr[1]}; others ignored")

    # ----- periodic jobs (io thread, under the lock)
    def _periodic(self) -> None:
        """Every job on its own: one that raises is counted and the others still run (the
        tick schedule and the setpoint stream above all)."""
        local = self.mono()
        now = self.clock.now()
        self._handle("periodic heartbeat", self._periodic_heartbeat, local)
        self._handle("periodic link", self._periodic_link, local)
        self._handle("periodic clock", self._periodic_clock, now)
        self._handle("periodic DF input", self._periodic_df_input)
        if now is None:
            self._sched_beat = self.mono()  # nothing to schedule before the first clock sample
            return
        self._handle("periodic mode", self._periodic_mode, now)
        self._handle("periodic launch", self._periodic_launch, now)
        if self._handle("tick schedule", self._schedule_tick, now):
            self._sched_beat = self.mono()
        self._handle("setpoint stream", self._stream_setpoint, now)

    def _periodic_heartbeat(self, local: float) -> None:
        v = self.vehicle
        if v.sysid is not None and local - self._hb_local >= 1.0:
            self._hb_local = local
            self._heartbeat()
            if local - self._stat_local >= 1.0:
                self._publish_stat()
                self._stat_local = local
        # ask for the telemetry again while the origin is unknown or positions stop coming with
        # heartbeats still there: an autopilot that rebooted (or a link reopened to it) starts
        # from its default rates, which on ArduPilot send no position at all
        stale = local - v.heartbeat_local < 1.5 and local - v.position_local > STALE_TELEMETRY_S
        if v.sysid is not None and (v.ned_origin is None or stale) and local - self._msg_interval_local > 2.0:
            self._msg_interval_local = local
            self._request_telemetry()

    def _periodic_link(self, local: float) -> None:
        v = self.vehicle
        # link loss (local time: no heartbeat for link_timeout_s): stop commanding at once, keep
        # estimating (the clock free-runs, scans are still ticked); fly again only when told
        # (a stream link that dropped is lost at once: nothing can be sent on it)
        if v.sysid is not None and not self._link_lost and (
                local - v.heartbeat_local > self.cfg.link_timeout_s or not self.link.up):
            self._link_lost = True
            self._link_lost_local = local
            self._count("link_losses")
            if self.state in (State.MONITORING, State.PAUSED):
                self._set_state(State.FAULT)
            aborted = ", launch aborted" if self._launch is not None else ""
            self._launch = None
            self.say(f"autopilot link lost: setpoints stopped{aborted}, estimating",
                     mavlink.MAV_SEVERITY_CRITICAL)

    def _periodic_mode(self, now: float) -> None:
        if self.state == State.MONITORING and self._guided_deadline is not None \
                and now > self._guided_deadline:
            self._set_state(State.PAUSED)
            self.say("GUIDED refused by the autopilot: paused", mavlink.MAV_SEVERITY_WARNING)

    def _periodic_launch(self, now: float) -> None:
        if self.cfg.auto_launch and self.state == State.IDLE and self._launch is None \
                and not self._said_launch():
            if self._cmd_launch()[0] == mavlink.MAV_RESULT_ACCEPTED and self._launch is not None:
                self._said.add("auto_launch")
        self._launch_step(now)

    def _periodic_clock(self, now: float | None) -> None:
        """Report the clock's jumps (clock.py): a candidate it refused, or a jump it followed. A
        followed jump ahead restarts the tick schedule on the new timeline (no burst of coast
        ticks, no scan of the old timeline ticked on the new one); one back is a reboot, which
        ``_on_autopilot_reboot`` handled when the clock followed it."""
        c = self.clock
        seen = (getattr(c, "jumps", 0), getattr(c, "jumps_ignored", 0))
        if seen == self._clock_seen:
            return
        (j0, i0), self._clock_seen = self._clock_seen, seen
        if seen[1] > i0:
            self._count("clock_jumps_ignored", seen[1] - i0)
            self.say("autopilot time jump not confirmed: ignored", mavlink.MAV_SEVERITY_WARNING,
                     once="clock_ignored")
        if seen[0] > j0:
            self._count("clock_jumps", seen[0] - j0)
            self._submitted_t = now  # the watchdog's tick gap starts again on the new timeline
            jump = getattr(c, "last_jump_s", 0.0)
            if jump > 0 and now is not None:  # the coast grid goes on from now, not from the old time
                self.say(f"autopilot clock jumped {jump:+.0f} s: ticks restart", mavlink.MAV_SEVERITY_CRITICAL)
                self.scans.pending.clear()  # stamped on the old timeline
                self.scans.arrival.clear()
                self._tick_times = []
                start = math.floor(now) - 1.0
                self.scans.consumed_until = max(self.scans.consumed_until, start)
                if self.last_tick_t is not None:
                    self.last_tick_t = max(self.last_tick_t, start)

    def _periodic_df_input(self) -> None:
        """Say once per foreign DF sender, and once per episode of rate limiting."""
        for addr in list(self.df.foreign):
            if addr not in self._df_seen:
                self._df_seen.add(addr)
                self._count("df_foreign_sources")
                self.say(f"DF from {addr[0]}:{addr[1]} ignored", mavlink.MAV_SEVERITY_WARNING)
        limited = self.df.dropped["rate_limited"]
        if limited > self._df_limited_seen:
            self._df_limited_seen = limited
            self.say(f"DF sender over {self.df.rate_hz:g}/s: excess dropped", mavlink.MAV_SEVERITY_WARNING,
                     once="df_rate")

    def _said_launch(self) -> bool:
        return "auto_launch" in self._said

    def _stream_setpoint(self, now: float) -> None:
        if self.state != State.MONITORING or self._guided_deadline is not None or self.setpoint is None \
                or self._link_lost:
            return
        if not self.vehicle.is_guided():
            return
        if now >= self._next_sp_t:
            self._send_setpoint(self.setpoint, now)

    def _send_setpoint(self, enu: np.ndarray, now: float, centre=None) -> bool:
        """Send the setpoint in LOCAL_NED at the fixed origin: with a planned segment (vehicle
        motion) the plan's position, velocity and acceleration at ``now``, else the point
        ``enu`` alone (onboard/app/setpoint_stream.py); both checked when planned. The message itself
        is checked against the fence before it goes (fence.outgoing_violation: its position
        read back to ENU). A message that fails is not sent: counted, said, and the setpoint
        dropped (the stream stops; the vehicle holds its last good one). ``centre``: where the
        vehicle was when the tick planned it (path rule, first send only)."""
        v = self.vehicle
        if v.ned_origin is None:
            return False
        if self.segment is not None:
            pos, vel, acc = self.segment.at(now)
            msg = setpoint_message(self.link.mav, now, v.sysid, v.compid, self.frame.ned_from_enu(pos, v.ned_origin),
                                   enu_to_ned_vector(vel), enu_to_ned_vector(acc))
        else:
            pos = np.asarray(enu, float)
            msg = setpoint_message(self.link.mav, now, v.sysid, v.compid, self.frame.ned_from_enu(pos, v.ned_origin))
        self._next_sp_t = now + 1.0 / self.params["PMON_SP_HZ"]
        refused = outgoing_violation(msg, self.frame, self.origin.value, Fence.of(self.setup, self.params, at_h=False),
                                     centre)
        if refused is not None:
            self._count("setpoints_refused")
            self._count("setpoints_refused_at_send")
            self.setpoint = self.segment = None
            self.say(f"setpoint refused as sent: {refused}", mavlink.MAV_SEVERITY_ERROR)
            return False
        ok = self.link.send(msg)
        if ok:
            self.sent_setpoints.append((now, self.mono(), np.array(pos, float)))
        return ok

    # ----- tick scheduling
    def _schedule_tick(self, now: float) -> None:
        if self._worker_busy:
            return
        wait = self.params["PMON_SCAN_WAIT"]
        due = [k for k in self.scans.pending if self.scans.complete(k) or now >= k + wait]
        if not due:
            # no DF data: coast the filters on the 1 s grid so they stay in step with time
            # (late enough that a DF delivering a few seconds late is not overtaken: a coast tick
            # takes that scan time, and a scan arriving after it is rejected as stale_time)
            if self.last_tick_t is not None and now >= self.last_tick_t + 1.0 + wait + COAST_AFTER_S:
                if not self._silent:  # once per silence episode
                    self._silent = True
                    self._count("df_silences")
                    self.say("no DF data: predicting only", mavlink.MAV_SEVERITY_WARNING)
                self._count("ticks_coasted")
                key = self.last_tick_t + 1.0
                self.scans.consumed_until = max(self.scans.consumed_until, key)
                self._submit(TickRecord(key, {}, 0))
            return
        # scans still within their budget are ticked in order; past it, only the newest is
        # ticked and the older ones are skipped (an overrun is skipped, never queued)
        live = [k for k in due if now <= k + self.params["PMON_BUDGET"]]
        key = min(live) if live else max(due)
        taken = self.scans.take_until(key)
        if self._silent:
            self._silent = False
            self.say("DF data back: updating again")
        skipped = len(taken) - 1
        if skipped:
            self._count("ticks_skipped", skipped)
        if self.last_tick_t is not None and key > self.last_tick_t + 1.5:
            missed = int(round(key - self.last_tick_t)) - 1 - skipped
            if missed > 0:
                self._count("ticks_coasted_missing", missed)
        self._submit(TickRecord(key, taken[-1][1], skipped, arrived_t=self.scans.last_arrival))

    def _submit(self, rec: TickRecord) -> None:
        rec.started_local = self.mono()
        rec.due_t = self.clock.now()
        self._submitted_t = rec.due_t
        self.last_tick_t = rec.t
        self._worker_busy = True
        self._job = rec
        self._job_event.set()


def _msg_type(msg) -> str:
    try:
        return str(msg.get_type())
    except Exception:
        return "?"


def _nan(x: float | None) -> float:
    return math.nan if x is None else float(x)


__all__ = ["AppConfig", "OnboardApp", "State", "Action", "Reason", "TGT_FIELDS", "STAT_FIELDS",
           "SPECS"]
