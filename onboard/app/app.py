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

import ctypes
import json
import logging
import math
import select
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from enum import IntEnum
from typing import Callable

import numpy as np

from onboard.app import datagram as dg
from onboard.app import launch
from onboard.app.autopilot_commands import heading_from_global_position_int, takeoff_params
from onboard.app.clock import AutopilotClock
from onboard.app.contain import Contained
from onboard.app.df_input import DEFAULT_RATE_HZ, DfInput, Source
from onboard.app.fence import Fence, outgoing_violation, violation
from onboard.app.link import COMP_ID, Link, mavlink
from onboard.app.params import SPECS, ParamTable, defaults_from_scenario
from onboard.app.pose import FixedOrigin, Frame, PoseHistory, origin_of, valid_global_position_int
from onboard.core import tracking
from onboard.core.guidance import GuidanceWorkspace
from onboard.core.monitor import MonitorSetup, Scan, initial_state, tick
from onboard.core.planning import CandidateGrid
from onboard.core.tracking import ParticleSet

log = logging.getLogger("pmon.app")

# MAVLink command sent to component 191; param1 = action
MAV_CMD_PMON = mavlink.MAV_CMD_USER_1  # 31010
COAST_AFTER_S = 2.0  # autopilot s past a scan's wait without any DF datagram -> coast tick
PLAN_RESERVE_S = 0.25  # autopilot s of a tick's budget kept for tracking, planning and sending
IO_MAVLINK_MAX = 500  # MAVLink messages handled per io iteration, then the periodic jobs
IO_DF_MAX = 200  # DF datagrams parsed per io iteration (the reader's rate limit bounds the rest)
POSITION_ONLY = 3576  # type_mask: ignore velocity, acceleration, yaw, yaw rate
ARDUCOPTER_GUIDED = 4
PX4_MAIN_MODE_OFFBOARD = 6
# the autopilot's horizontal speed and acceleration limits for guided position setpoints, read at
# connection to check what the planner's moves assume: (name, factor to SI) per autopilot
SPEED_ACCEL_PARAMS = {
    mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: (("WPNAV_SPEED", 0.01), ("WPNAV_ACCEL", 0.01)),  # cm/s, cm/s^2
    mavlink.MAV_AUTOPILOT_PX4: (("MPC_XY_CRUISE", 1.0), ("MPC_ACC_HOR", 1.0)),  # m/s, m/s^2
}


class State(IntEnum):
    IDLE = 0
    MONITORING = 1
    PAUSED = 2
    PILOT_OVERRIDE = 3
    FAULT = 4


class Action(IntEnum):
    START = 1
    PAUSE = 2
    RESUME = 3
    STOP = 4
    LAUNCH = 5  # GUIDED, arm, take off to h, then START


class Reason(IntEnum):
    """COMMAND_ACK.result_param2 when a command is refused (docs/MAVLINK.md)."""

    NONE = 0
    NOT_ARMED = 1
    NOT_FLYING = 2
    NO_SENSOR_DATA = 3
    NO_POSITION = 4
    NO_AUTOPILOT = 5
    UNKNOWN_ACTION = 6
    WRONG_STATE = 7
    ALREADY_FLYING = 8
    BUSY = 9


REASON_TEXT = {
    Reason.NOT_ARMED: "vehicle not armed",
    Reason.NOT_FLYING: "vehicle not flying",
    Reason.NO_SENSOR_DATA: "no DF data in the last 3 s",
    Reason.NO_POSITION: "no valid position or local origin yet",
    Reason.NO_AUTOPILOT: "no autopilot heartbeat",
    Reason.UNKNOWN_ACTION: "unknown action",
    Reason.WRONG_STATE: "not possible in this state",
    Reason.ALREADY_FLYING: "already flying: use start",
    Reason.BUSY: "launch in progress",
}

STATUS = {  # HEARTBEAT.system_status per app state
    State.IDLE: mavlink.MAV_STATE_STANDBY,
    State.MONITORING: mavlink.MAV_STATE_ACTIVE,
    State.PAUSED: mavlink.MAV_STATE_STANDBY,
    State.PILOT_OVERRIDE: mavlink.MAV_STATE_STANDBY,
    State.FAULT: mavlink.MAV_STATE_CRITICAL,
}

TGT_FIELDS = ("x_east_m", "y_north_m", "z_up_m", "vx_mps", "vy_mps", "vz_mps", "sigma_x_m",
              "sigma_y_m", "since_scan_s", "cov_xy_m2", "sigma_vx_mps", "sigma_vy_mps",
              "degenerate", "tick_time_s")
STAT_FIELDS = ("state", "tick_rate_hz", "last_tick_time_s", "tick_ms", "next_e_m", "next_n_m",
               "next_u_m", "dgram_accepted", "dgram_rejected", "ticks", "ticks_skipped",
               "latency_ms", "autopilot_mode", "armed", "uav_e_m", "uav_n_m", "uav_u_m",
               "sum_trace", "ticks_late", "setpoints_refused", "warnings", "speed_limit_mps",
               "speed_plan_mps", "accel_limit_mps2", "accel_plan_mps2", "launch_phase")
# PMON_STAT "warnings" bits: conditions that hold now (docs/MAVLINK.md)
WARN_SPEED = 1  # the autopilot's horizontal speed limit is below what the planner's moves assume
WARN_ACCEL = 2  # ... its acceleration limit
STALE_TELEMETRY_S = 2.0  # local s without GLOBAL_POSITION_INT while heartbeats come: ask again
FALLBACK_SAY_TICKS = 3  # a target's guidance on a fallback this many ticks in a row is said


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


@dataclass
class TickRecord:
    """What the io thread hands the worker."""

    t: float  # scan time (autopilot s)
    scans: dict  # ch -> Datagram
    skipped: int
    started_local: float = 0.0
    run_local: float | None = None  # when the worker began it (the watchdog reads this)
    due_t: float | None = None  # autopilot time when it was handed to the worker
    arrived_t: float | None = None  # autopilot time its newest datagram arrived


@dataclass
class Vehicle:
    """What the app knows of the autopilot (from its heartbeats and telemetry)."""

    sysid: int | None = None
    compid: int | None = None
    autopilot: int = mavlink.MAV_AUTOPILOT_INVALID
    custom_mode: int | None = None
    armed: bool = False
    landed_state: int | None = None
    relative_alt: float | None = None
    ned_origin: tuple[float, float, float] | None = None  # autopilot local origin (deg, deg, m)
    heartbeat_local: float = -math.inf
    mode_seen_local: float = -math.inf
    speed_limit_mps: float | None = None  # horizontal, from its parameters (SPEED_ACCEL_PARAMS)
    accel_limit_mps2: float | None = None
    lat_lon_deg: tuple[float, float] | None = None  # last valid GLOBAL_POSITION_INT
    amsl_m: float | None = None
    heading_deg: float | None = None
    position_local: float = -math.inf  # local time of the last valid GLOBAL_POSITION_INT
    prearm_ok: bool | None = None  # SYS_STATUS MAV_SYS_STATUS_PREARM_CHECK (None: not reported)
    prearm_text: str | None = None  # its latest "PreArm: ..." / "Arm: ..." STATUSTEXT

    def is_guided(self) -> bool:
        if self.custom_mode is None:
            return False
        if self.autopilot == mavlink.MAV_AUTOPILOT_PX4:
            return (self.custom_mode >> 16) & 0xFF == PX4_MAIN_MODE_OFFBOARD
        return self.custom_mode == ARDUCOPTER_GUIDED

    def flying(self) -> bool:
        if self.landed_state not in (None, mavlink.MAV_LANDED_STATE_UNDEFINED):
            return self.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR
        return self.relative_alt is not None and self.relative_alt > 2.0


class OnboardApp:
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
        self._setup_version = -1
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
        self.setpoint: np.ndarray | None = None  # ENU, m, checked safe
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
        """(Re)build the core setup from the parameters; called by the worker before a tick."""
        if self._setup_version == self.params.version:
            return
        sc = self.params.apply(self.base_scenario)
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
        self._setup_version = self.params.version

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

    # ----- MAVLink in
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
                bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
                self.vehicle.prearm_ok = bool(msg.onboard_control_sensors_health & bit) \
                    if msg.onboard_control_sensors_present & bit else None
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
        """Compare the autopilot's limits with what the planner's moves assume (below them the
        vehicle lags its setpoints; docs/MAVLINK.md). The result holds until the limits or
        PMON_REACH change: PMON_STAT carries it every second (``pmon gcs status`` shows it),
        and it is said when it first holds and again whenever monitoring starts."""
        names = SPEED_ACCEL_PARAMS.get(self.vehicle.autopilot)
        if not names:
            return
        (speed_name, _), (accel_name, _) = names
        sc = self.base_scenario
        pl = sc.planning
        if pl.motion == "vehicle":
            speed_need, speed_why = pl.speed_max_mps, "planning.speed_max_mps"
        else:  # the paper's jump: the largest ring asked for, per tick
            reach = min(sc.uav.n_radial * sc.uav.step_m, self.params["PMON_REACH"])
            speed_need, speed_why = reach / sc.dynamics.dt_s, "the planner's steps (PMON_REACH)"
        checks = [(WARN_SPEED, speed_name, self.vehicle.speed_limit_mps, speed_need, speed_why, "m/s")]
        accel_need = math.nan
        if pl.motion == "vehicle":  # the jump model assumes no acceleration limit: nothing to compare
            accel_need = pl.accel_max_mps2
            checks.append((WARN_ACCEL, accel_name, self.vehicle.accel_limit_mps2, accel_need,
                           "planning.accel_max_mps2", "m/s^2"))
        self._plan_limits = (speed_need, accel_need)
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

    # ----- state
    def _set_state(self, new: State) -> None:
        if new != State.MONITORING:
            self.setpoint = None
            self.generation += 1  # results of ticks already running are not sent
            self._guided_deadline = None
        self.state = new
        self._heartbeat()

    # ----- commands
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

    # ----- parameters
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
        """Send the setpoint ``enu`` (checked when planned) in LOCAL_NED at the fixed origin,
        after checking the message itself against the fence (fence.outgoing_violation: its
        position read back to ENU). A message that fails is not sent: counted, said, and the
        setpoint dropped (the stream stops; the vehicle holds its last good one). ``centre``:
        where the vehicle was when the tick planned it (path rule, first send only)."""
        v = self.vehicle
        if v.ned_origin is None:
            return False
        ned = self.frame.ned_from_enu(enu, v.ned_origin)
        msg = self.link.mav.set_position_target_local_ned_encode(
            int(now * 1000) & 0xFFFFFFFF, v.sysid, v.compid, mavlink.MAV_FRAME_LOCAL_NED,
            POSITION_ONLY, float(ned[0]), float(ned[1]), float(ned[2]), 0, 0, 0, 0, 0, 0, 0, 0)
        self._next_sp_t = now + 1.0 / self.params["PMON_SP_HZ"]
        refused = outgoing_violation(msg, self.frame, self.origin.value, Fence.of(self.setup, self.params, at_h=False),
                                     centre)
        if refused is not None:
            self._count("setpoints_refused")
            self._count("setpoints_refused_at_send")
            self.setpoint = None
            self.say(f"setpoint refused as sent: {refused}", mavlink.MAV_SEVERITY_ERROR)
            return False
        ok = self.link.send(msg)
        if ok:
            self.sent_setpoints.append((now, self.mono(), np.array(enu, float)))
        return ok

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

    # ------------------------------------------------------------------ watchdog thread
    def _alarm(self, key: str, text: str) -> None:
        """Report from the watchdog: no app lock (the stuck thread may hold it)."""
        self.watchdog[key] = self.watchdog.get(key, 0) + 1
        full = f"PMON: {text}"
        self.events.append((None, full))
        log.error(full)
        if self.vehicle.sysid is not None:
            self.link.send(self.link.mav.statustext_encode(mavlink.MAV_SEVERITY_CRITICAL, full.encode()[:50]))

    def _watchdog_loop(self) -> None:
        """Reports, once per episode: an io loop not iterating; a tick schedule that does not
        run to its end (its handler failing every time); no tick handed to the worker for
        ``watchdog_s`` past the longest gap the schedule allows (the coast grid), while the
        worker is idle, i.e. a loop that stopped ticking; a tick running past ``watchdog_s`` of
        autopilot time. The io thread keeps re-sending the last (checked) setpoint while a tick
        is stuck, so the vehicle holds a safe point; an overrun's scans are skipped."""
        while not self._stop.wait(0.1):
            local = self.mono()
            rate = getattr(self.clock, "rate", 1.0) or 1.0
            limit = self.cfg.watchdog_s / rate
            self._episode("io", local - self._io_beat > max(limit, 0.5),
                          lambda: f"watchdog: io loop stuck {local - self._io_beat:.1f} s")
            self._episode("schedule", local - self._sched_beat > max(limit, 0.5),
                          lambda: f"watchdog: tick schedule failing {local - self._sched_beat:.1f} s")
            now, sub = self.clock.now(), self._submitted_t
            gap = self.cfg.watchdog_s + 1.0 + self.params["PMON_SCAN_WAIT"] + COAST_AFTER_S
            self._episode("ticks", now is not None and sub is not None and self.last_tick_t is not None
                          and self._running is None and now - sub > gap,
                          lambda: f"watchdog: no tick for {now - sub:.1f} s")
            job = self._running
            started = job.run_local if job is not None else None
            self._episode("tick", started is not None and local - started > limit,
                          lambda: f"watchdog: tick t={job.t:.0f} running {(local - started) * rate:.1f} s")

    def _episode(self, key: str, bad: bool, text: Callable[[], str]) -> None:
        if bad and key not in self._alarmed:
            self._alarmed.add(key)
            self._alarm(f"{key}_stuck", text())
        elif not bad:
            self._alarmed.discard(key)

    # ------------------------------------------------------------------ worker thread
    def _worker_loop(self) -> None:
        while not self._stop.is_set():
            self._job_event.wait(0.1)
            self._job_event.clear()
            job, self._job = self._job, None
            if job is None:
                self._trim_memory()
                continue
            job.run_local = self.mono()
            self._running = job
            try:
                self._run_tick(job)
            except Exception:
                with self.lock:
                    self._count("tick_errors")
                log.exception("tick error")
            finally:
                self._running = None
                with self.lock:
                    self._worker_busy = False

    def _trim_memory(self) -> None:
        """Give freed heap pages back to the OS, once per ``trim_memory_s`` of autopilot time,
        from the worker while it is idle (between ticks). Python frees a tick's temporary arrays
        at once, but glibc keeps the pages (its mmap threshold rises to the largest array ever
        freed; arenas are trimmed only at the top), so the resident size would follow the
        largest tick so far, not what is in use. A few ms per call; worker thread."""
        now = self.clock.now()
        if self._malloc_trim is None or now is None or now < self._trimmed_t + self.cfg.trim_memory_s:
            return
        self._trimmed_t = now
        try:
            self._malloc_trim(0)
        except Exception:  # ctypes failure: never again, never fatal
            self._malloc_trim = None
            return
        with self.lock:
            self._count("memory_trims")

    def _run_tick(self, job: TickRecord) -> None:
        t_start = self.mono()
        with self.lock:
            self._build_setup()
            setup = self.setup
            grid = self._grid_within_reach()
            generation = self.generation
            planning = self.state == State.MONITORING and self._guided_deadline is None
            now = self.clock.now() or job.t
            # pair the scan with where the DF was at the scan's time (telemetry, not setpoint)
            sensor_pos = self.poses.at(job.t)
            centre = self.poses.at(now) if planning else None  # where the vehicle is now
        bearings = tuple(job.scans[ch].bearings if ch in job.scans else np.empty(0)
                         for ch in range(self.M))
        for ch in job.scans:  # newest scan time <= this tick per channel (PMON_TGT[8])
            self._scan_t_used[ch] = max(self._scan_t_used[ch], job.t)
        scans = []
        if sensor_pos is not None and job.scans:
            scans = [Scan(sensor_pos, bearings)]
        elif job.scans:
            with self.lock:
                self._count("scans_without_pose")
                self.say("DF scan without a vehicle position: dropped",
                         mavlink.MAV_SEVERITY_WARNING, once="nopose")
        if grid.n_radial != setup.grid.n_radial:
            setup = _with_grid(setup, grid)
        # guidance time, in autopilot s: PMON_GUID_S, and never more than what is left of the
        # tick's budget after a reserve for planning and sending (converted to local seconds
        # at the clock's rate: at a SITL speedup of 4, 0.3 s of autopilot time is 75 ms)
        guid_s = self.params["PMON_GUID_S"]
        rate = getattr(self.clock, "rate", 1.0) or 1.0
        left = job.t + self.params["PMON_BUDGET"] - PLAN_RESERVE_S - (self.clock.now() or job.t)
        per_target_s = max(min(guid_s, left), 0.0) / rate / max(setup.n_targets, 1)
        setup = replace(setup, guidance=replace(setup.guidance, max_solve_time_s=per_target_s))
        self.core_state, res = tick(setup, self.core_state, scans, self.rng,
                                    plan_from=centre, workspace=self.workspace)
        reseeded = self._check_beliefs(setup, res)
        nxt = res.next_position
        with self.lock:
            self._report_guidance(res)
            for j in reseeded:
                self._count("reseeds")
                self.say(f"T{j + 1}: particle collapse: re-seeded from its last estimate",
                         mavlink.MAV_SEVERITY_ERROR)
            sent = False
            refused = None
            if nxt is not None and planning:
                if self.generation != generation or self.state != State.MONITORING:
                    refused = "state changed during the tick"
                else:
                    refused = violation(Fence.of(setup, self.params), nxt, centre)
                    if refused is None:
                        previous, self.setpoint = self.setpoint, np.array(nxt, float)
                        sent = self._send_setpoint(self.setpoint, self.clock.now() or job.t, centre)
                        if self.setpoint is None:  # refused as sent: the previous one stays
                            refused, self.setpoint = "refused as sent", previous
                    else:
                        self._count("setpoints_refused")
                        self.say(f"setpoint refused: {refused}", mavlink.MAV_SEVERITY_ERROR)
            t_sent = self.mono()
            ap_sent = self.clock.now()
            self._count("ticks")
            late = ap_sent is not None and ap_sent > job.t + self.params["PMON_BUDGET"]
            if late and planning and job.scans:  # a coast tick has no scan to be late for
                self._count("ticks_late")
            rec = self._record(job, res, sensor_pos, centre, nxt, sent, refused,
                               t_start, t_sent, ap_sent)
            rec["planned"] = planning
            rec["plans"] = [p.status for p in res.plans]
            rec["qp_solves"] = [p.qp_solves for p in res.plans]
            rec["guidance_timeouts"] = [p.status == "timeout" for p in res.plans]
            rec["reseeded"] = reseeded
            if self._runlog is not None:
                self._runlog.write(json.dumps(rec, allow_nan=False, default=_json_default) + "\n")
            self._publish_tick(rec, res)
            self._tick_times = (self._tick_times + [job.t])[-10:]
        for fn in list(self.tick_listeners):
            try:
                fn(rec)
            except Exception:
                with self.lock:
                    self._count("listener_errors")
                log.exception("tick listener error")

    def _check_beliefs(self, setup: MonitorSetup, res) -> list[int]:
        """Particle collapse: a target whose update left no finite weight (``degenerate``) or
        whose belief holds a NaN/inf is re-seeded from its last good estimate, covariance
        inflated (x4 plus the initial covariance: it was lost, so be generous). Only that
        target's belief is replaced; the others are untouched. Worker thread."""
        out = []
        beliefs = list(self.core_state.beliefs)
        for j, b in enumerate(beliefs):
            bad = bool(res.degenerate[j]) or not (np.all(np.isfinite(b.particles))
                                                  and np.all(np.isfinite(b.log_weights))
                                                  and np.all(np.isfinite(res.means[j])))
            if not bad:
                self._last_good[j] = (res.means[j].copy(), res.covs[j].copy())
                continue
            mean, cov = self._last_good[j] or (setup.initial_means[j], setup.initial_cov)
            cov = 4.0 * cov + setup.initial_cov
            try:
                beliefs[j] = tracking.initialise(mean, cov, len(b.particles), self.rng)
            except np.linalg.LinAlgError:
                beliefs[j] = tracking.initialise(mean, setup.initial_cov, len(b.particles), self.rng)
            out.append(j)
        if out:
            self.core_state = type(self.core_state)(tuple(beliefs), self.core_state.plans,
                                                    self.core_state.step)
        return out

    def _report_guidance(self, res) -> None:
        """Guidance time-outs and fallbacks: counted every tick (PMON_STAT, the run log); said
        when a target's guidance stays on a fallback FALLBACK_SAY_TICKS ticks in a row, and when
        it is back after that. A single tick on the previous plan (the time ran out around an
        obstacle) is the designed degradation, not news for the pilot. Under the lock."""
        if any(p.status == "timeout" for p in res.plans):
            self._count("guidance_timeouts")
        for j, plan in enumerate(res.plans):
            fb = plan.status.startswith("fallback")
            if fb:
                self._count(plan.status)
                self._fallback[j] += 1
                if self._fallback[j] == FALLBACK_SAY_TICKS:
                    how = "previous plan shifted" if plan.status == "fallback_previous" else "coasting"
                    self.say(f"T{j + 1} guidance failed {FALLBACK_SAY_TICKS} ticks: {how}",
                             mavlink.MAV_SEVERITY_WARNING)
            else:
                if self._fallback[j] >= FALLBACK_SAY_TICKS:
                    self.say(f"T{j + 1} guidance back")
                self._fallback[j] = 0

    def _record(self, job, res, sensor_pos, centre, nxt, sent, refused, t_start, t_sent, ap_sent) -> dict:
        sig = np.sqrt(np.maximum(np.diagonal(res.covs, axis1=1, axis2=2), 0.0))
        sum_trace = None
        if res.planning is not None and res.planning.index is not None:
            sum_trace = float(res.planning.scores[res.planning.index])
        rec = {
            "t": job.t, "state": int(self.state), "planned": None, "sent_t": ap_sent, "due_t": job.due_t,
            "arrived_t": job.arrived_t,
            "channels": sorted(job.scans), "n_bearings": [len(job.scans[c].bearings) if c in job.scans else None
                                                         for c in range(self.M)],
            "uav_enu": None if sensor_pos is None else [round(float(x), 3) for x in sensor_pos],
            "plan_from": None if centre is None else [round(float(x), 3) for x in centre],
            "means": np.round(res.means, 3).tolist(),
            "sigmas_xy": np.round(sig[:, :2], 3).tolist(),
            "cov_xy": np.round(res.covs[:, 0, 1], 3).tolist(),  # with sigmas_xy: the 1-sigma ellipse
            "next": None if nxt is None else [round(float(x), 3) for x in nxt],
            "sent": sent, "refused": refused, "skipped_before": job.skipped,
            "n_candidates": None if res.planning is None else int(len(res.planning.candidates)),
            "n_admissible": None if res.planning is None else int(res.planning.admissible.sum()),
            "sum_trace": sum_trace,
            "timings_ms": {k: round(v * 1e3, 2) for k, v in res.timings_s.items()},
            "tick_ms": round(res.timings_s["tick"] * 1e3, 2),
            "latency_ms": round((t_sent - job.started_local) * 1e3, 2) if sent else None,
            "wait_ms": round((t_start - job.started_local) * 1e3, 2),
        }
        self.latest = rec
        self.ticks.append(rec)
        return rec

    def _publish_tick(self, rec: dict, res) -> None:
        if self.vehicle.sysid is None:
            return
        for j in range(self.M):
            c = res.covs[j]
            since = rec["t"] - self._scan_t_used[j] if math.isfinite(self._scan_t_used[j]) else -1.0
            values = [*res.means[j], math.sqrt(max(c[0, 0], 0)), math.sqrt(max(c[1, 1], 0)), since,
                      c[0, 1], math.sqrt(max(c[3, 3], 0)), math.sqrt(max(c[4, 4], 0)),
                      float(res.degenerate[j]), rec["t"]]
            self._debug_array("PMON_TGT", j, values, rec["t"])
        self._publish_stat()
        self._stat_local = self.mono()


def _malloc_trim():
    """glibc's ``malloc_trim`` (returns free heap pages of every arena to the OS), or None where
    the C library has none (musl, macOS: their allocators return memory by themselves)."""
    try:
        fn = ctypes.CDLL(None).malloc_trim  # the C library the interpreter is linked with
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


def _msg_type(msg) -> str:
    try:
        return str(msg.get_type())
    except Exception:
        return "?"


def _nan(x: float | None) -> float:
    return math.nan if x is None else float(x)


def _with_grid(setup: MonitorSetup, grid: CandidateGrid) -> MonitorSetup:
    return replace(setup, grid=grid)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


__all__ = ["AppConfig", "OnboardApp", "State", "Action", "Reason", "TGT_FIELDS", "STAT_FIELDS",
           "SPECS"]
