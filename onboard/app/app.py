"""The onboard app: the imperative shell around ``onboard.core.monitor.tick``, built from parts
that own their state (each in its module):

  autopilot side   autopilot/side.py              the autopilot it serves (and its profile), its vehicle
                                                  record, pose history, clock and origin; link health
  router           gcs/dispatch.py                MAVLink in: message type -> handler, who is obeyed
  state machine    state_machine.py               idle / monitoring / paused / pilot override / fault;
                                                  commands, launch sequence
  parameters       gcs/param_server.py            PMON_* on the parameter protocol (params.py: the values)
  DF scans         df/scans.py                    datagrams into the scan buffer (df/udp_input.py: the socket)
  KrakenSDR        kraken/source.py               its DoA output into the scan buffer (optional: --kraken)
  tick schedule    tick/schedule.py               which scan the worker ticks next
  worker           tick/worker.py                 snapshot -> tick -> check -> send -> record
  core             tick/core_side.py              the core setup and state between ticks
  setpoint stream  autopilot/setpoint_stream.py   the adopted setpoint, re-sent, fenced as it goes out
  plan limits      autopilot/plan_limits.py       the planner's speed, acceleration, jerk against the autopilot's
  publisher        gcs/publisher.py               HEARTBEAT, STATUSTEXT, PMON_STAT, PMON_TGT
  tick log         tick/log.py                    tick records, run log, listeners
  watchdog         tick/watchdog.py               a stuck loop or tick, reported

Each part gets the app's shared context (context.py: config, link, clocks, parameters, counters,
voice, lock) and keeps one contract (part.py): the MAVLink types it handles (``handlers()``; the
router dispatches on message type) and its periodic jobs (``jobs()``, each ``run(local_s,
now_s)``). This module builds them, holds them in ``parts`` in the order their jobs run, and
runs the threads (all daemon; ``stop()`` joins them):
  io      MAVLink in, DF datagrams in (parsed), and every periodic job on the autopilot clock:
          heartbeat, setpoint re-send, tick scheduling, launch sequence, link watchdog,
          PMON_STAT. Each message, datagram and job is its own contained handler
          (onboard/app/contain.py): an error is counted under its kind and the loop goes on, so
          nothing a peer sends can skip the schedule; reads are bounded per iteration
          (``IO_MAVLINK_MAX``, ``IO_DF_MAX``).
  df      reads the DF port at line rate, drops foreign and rate-limited senders unparsed, and
          queues the rest for the io thread (onboard/app/df/udp_input.py).
  kraken  (with a KrakenSDR) polls its output and queues each new document, parsed, for the io
          thread (onboard/app/kraken/fetch.py).
  worker  one core tick at a time. A scan that becomes due while the worker is busy waits;
          when it frees, only the newest due scan is ticked and older ones are counted as
          skipped: an overrun is skipped, never queued.
  watchdog  reports, without the app lock.
With ``rt_priority`` N the io thread runs at SCHED_FIFO N and the worker at N - 1 (realtime.py);
under systemd the worker's loop feeds the service watchdog (sd_notify.py, ``_service_beat``).

Tracking runs whenever scans arrive (every state): the filters stay in step with the targets
while the vehicle takes off or a pilot flies; planning whenever the vehicle flies, from where it
is (PMON_STAT's advice: what ``advisory`` publishes), setpoints only in ``monitoring``.
"""
from __future__ import annotations

import logging
import math
import select
import threading
import time
from typing import Callable

import numpy as np

from onboard.app.df import datagram as dg
from onboard.app.autopilot import launch
from onboard.app.app_config import AppConfig
from onboard.app.autopilot.side import AutopilotSide
from onboard.app.autopilot.clock import AutopilotClock
from onboard.app.contain import Contained
from onboard.app.context import AppContext
from onboard.app.contract import ADVICE_FIELDS, KRAKEN_STAT_FIELDS, STAT_FIELDS, TGT_FIELDS, Action, Reason, State
from onboard.app.counters import Counters
from onboard.app.df.udp_input import DfInput
from onboard.app.df.scans import DfScans
from onboard.app.gcs.dispatch import Commands, Router
from onboard.app.kraken.source import KrakenInput
from onboard.app.mavlink_connection import Link, mavlink
from onboard.app.tick.core_side import MonitorCore
from onboard.app.gcs.param_server import ParamServer
from onboard.app.params import SPECS, ParamTable
from onboard.app.part import Job, Part
from onboard.app.autopilot.plan_limits import PlanLimits
from onboard.app.autopilot.pose import Frame
from onboard.app.tick.overrun import stage_code
from onboard.app.gcs.publisher import Publisher
from onboard.app.realtime import Outcome, name_thread, set_fifo
from onboard.app.sd_notify import Notifier
from onboard.app.autopilot.setpoint_stream import SetpointStream
from onboard.app.state_machine import StateMachine
from onboard.app.tick.log import TickLog
from onboard.app.tick.schedule import TickSchedule
from onboard.app.autopilot.vehicle import Vehicle
from onboard.app.tick.watchdog import Health, Watchdog
from onboard.app.tick.worker import TickWorker
from onboard.core import monitor

log = logging.getLogger("pmon.app")

IO_MAVLINK_MAX = 500  # MAVLink messages handled per io iteration, then the periodic jobs
IO_DF_MAX = 200  # DF datagrams parsed per io iteration (the reader's rate limit bounds the rest)
SERVICE_STALE_S = 2.0  # local s: an io loop silent this long gets no service watchdog ping


class OnboardApp:
    """The app: its parts, its threads, and what a rig reads of it (``state``, ``ticks``,
    ``events``, ``counters``, ``vehicle``, ``poses``, ``params`` ...). ``tick``: the core tick
    the worker calls (a test injects faults here); ``clock``, ``link``, ``monotonic``: injectable."""

    def __init__(self, cfg: AppConfig, scenario, clock=None, link: Link | None = None,
                 monotonic: Callable[[], float] = time.monotonic, tick: Callable = monitor.tick):
        self.cfg = cfg
        self.mono = monotonic
        self.clock = clock if clock is not None else AutopilotClock(monotonic)
        self.events_meta = None
        if cfg.px4_events_path is not None:
            from onboard.app.autopilot.px4_events import EventMetadata
            self.events_meta = EventMetadata.load(cfg.px4_events_path)  # EventMetadataError: refuse to start
        self.link = link or _open_link(cfg)
        self.params = ParamTable.from_scenario(scenario)
        self.counters = Counters()
        self.lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        try:
            self.df = DfInput(cfg.sensor_host, cfg.sensor_port, cfg.df_sources, cfg.df_rate_hz, monotonic=monotonic)
            self.tick_log = TickLog(cfg.history, cfg.runlog_path, self.counters)
        except BaseException:
            self.link.close()
            if hasattr(self, "df"):
                self.df.stop()
            raise
        self.sensor_port = self.df.port
        self.scans = dg.ScanBuffer(len(scenario.targets))
        try:
            self._build_parts(cfg, scenario, tick)
        except BaseException:  # a KrakenSDR section without VFOs, a poller that cannot start
            self.df.stop()
            self.link.close()
            self.tick_log.close()
            raise
        self.errors = Contained(log, on_first=self._say_error)  # io-thread handler errors by kind
        self._io_beat = self.mono()
        self.realtime: dict[str, Outcome] = {}  # per real-time thread: its SCHED_FIFO, or why not
        self.notifier = Notifier.from_env()  # systemd's notify socket (a service), else None
        self._ready_sent = False
        self._pinged = -math.inf  # local s of the last WATCHDOG=1
        self.worker.beat = self._service_beat

    def _build_parts(self, cfg: AppConfig, scenario, tick: Callable) -> None:
        vehicle = Vehicle()
        o = scenario.origin
        self.publisher = Publisher(self.link, self.clock, vehicle, lambda: self.machine.state, self._status)
        say = self.publisher.say
        ctx = AppContext(cfg, self.link, self.clock, self.mono, self.params, self.counters, say, self.lock)
        self.autopilot = AutopilotSide(ctx, Frame(o.lat_deg, o.lon_deg, o.alt_m), vehicle, self, self.events_meta)
        self.limits = PlanLimits(scenario, self.params, vehicle, say)
        self.core = MonitorCore(scenario, self.params, self.limits, np.random.default_rng(cfg.seed))
        self.stream = SetpointStream(ctx, self.autopilot, lambda: self.core.setup, lambda: self.machine.may_stream())
        self.machine = StateMachine(ctx, self.autopilot, self.publisher, self.stream, self.limits, self.scans)
        self.worker = TickWorker(ctx, self.core, self.autopilot, self.machine, self.stream, self.publisher,
                                 self.tick_log, tick)
        self.schedule = TickSchedule(ctx, self.scans, self.worker)
        self.df_scans = DfScans(self.df, self.scans, self.clock, self.counters, say)
        self.kraken = KrakenInput(ctx, scenario, self.autopilot, self.scans) if cfg.kraken else None
        self.param_server = ParamServer(ctx, lambda name: self.limits.check())
        commands = Commands(self.link, self.publisher.publish_stat, self.machine.on_command)
        # in the order their periodic jobs run (a job's place is its timing: the schedule hands
        # out the tick before the stream re-sends the setpoint)
        self.parts: list[Part] = [self.publisher, self.autopilot, commands, self.param_server, self.df_scans,
                                  *([self.kraken] if self.kraken is not None else []), self.machine,
                                  self.schedule, self.stream]
        self.jobs: tuple[Job, ...] = tuple(job for part in self.parts for job in part.jobs())
        self.router = Router(ctx, self.autopilot, self.parts)
        self.watchdog = Watchdog(cfg.watchdog_s, self.publisher.alarm, lambda: getattr(self.clock, "rate", 1.0),
                                 lambda: self.params.settings.app.scan_wait_s)

    # ------------------------------------------------------------------ what a rig reads
    @property
    def state(self) -> State:
        return self.machine.state

    @property
    def vehicle(self) -> Vehicle:
        return self.autopilot.vehicle

    @property
    def poses(self):
        return self.autopilot.poses

    @property
    def ticks(self):
        return self.tick_log.ticks

    @property
    def tick_listeners(self) -> list[Callable[[dict], None]]:
        return self.tick_log.listeners

    @property
    def events(self):
        return self.publisher.events

    def say(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO, once: str | None = None) -> None:
        self.publisher.say(text, severity, once)

    def signing_counts(self) -> dict[str, int]:
        """MAVLink signing counters of the autopilot link (all zero when signing is off)."""
        from onboard.app.signing import counts
        return counts(self.link.mav)

    def _status(self) -> dict[str, float]:
        """PMON_STAT's values by name (contract.STAT_FIELDS)."""
        tk = self.tick_log.latest or {}
        nxt = self.stream.setpoint if self.stream.setpoint is not None else (math.nan,) * 3
        pose = self.autopilot.poses.latest()
        uav = pose.pos if pose is not None else (math.nan,) * 3
        v, c, lim = self.autopilot.vehicle, self.counters, self.limits
        launch_phase = self.machine.launch
        return {
            "state": int(self.machine.state), "tick_rate_hz": self.tick_log.rate_hz(),
            "last_tick_time_s": tk.get("t", math.nan), "tick_ms": tk.get("tick_ms", math.nan),
            "next_e_m": nxt[0], "next_n_m": nxt[1], "next_u_m": nxt[2],
            "dgram_accepted": self.scans.accepted,
            "dgram_rejected": self.scans.rejected_total + self.df.dropped_total,
            "ticks": c.get("ticks", 0), "ticks_skipped": c.get("ticks_skipped", 0),
            "latency_ms": _nan(tk.get("latency_ms")),
            "autopilot_mode": v.custom_mode if v.custom_mode is not None else -1, "armed": float(v.armed),
            "uav_e_m": uav[0], "uav_n_m": uav[1], "uav_u_m": uav[2], "sum_trace": _nan(tk.get("sum_trace")),
            "ticks_late": c.get("ticks_late", 0), "setpoints_refused": c.get("setpoints_refused", 0),
            "warnings": lim.warnings, "speed_limit_mps": _nan(v.speed_limit_mps), "speed_plan_mps": lim.plan[0],
            "accel_limit_mps2": _nan(v.accel_limit_mps2), "accel_plan_mps2": lim.plan[1],
            "launch_phase": -1 if launch_phase is None else launch.PHASES.index(launch_phase.phase),
            **(self.kraken.status() if self.kraken is not None else dict.fromkeys(KRAKEN_STAT_FIELDS, math.nan)),
            "jerk_limit_mps3": _nan(v.jerk_limit_mps3), "jerk_plan_mps3": lim.plan[2],
            "overruns": c.get("overruns", 0), "overrun_stage": stage_code(self.worker.last_overrun),
            **dict(zip(ADVICE_FIELDS, tk.get("next") or (math.nan,) * 3)),
        }

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> "OnboardApp":
        self.df.start()
        if self.kraken is not None:
            self.kraken.start()
        for name, fn in (("pmon-io", self._io_loop), ("pmon-worker", lambda: self.worker.loop(self._stop)),
                         ("pmon-watchdog", self._watchdog_loop)):
            th = threading.Thread(target=fn, name=name, daemon=True)
            th.start()
            self._threads.append(th)
        self._scheduling()
        return self

    def _scheduling(self) -> None:
        """The threads named as ps -L shows them; with ``rt_priority`` N, the io thread (MAVLink
        in, setpoints out, the schedule) at SCHED_FIFO N and the worker at N - 1: FIFO does not
        time-slice equal priorities, so on a shared core the io thread's short jobs preempt a
        long tick, never wait behind it (onboard/app/realtime.py)."""
        n = self.cfg.rt_priority
        rt = {"pmon-io": n, "pmon-worker": max(n - 1, 1)} if n > 0 else {}
        if self.df.thread_id is not None:
            name_thread(self.df.thread_id, "pmon-df")
        for th in self._threads:
            name_thread(th.native_id, th.name)
            if th.name in rt:
                self.realtime[th.name] = set_fifo(th.native_id, rt[th.name])

    def stop(self) -> None:
        if self.notifier is not None:
            self.notifier.send("STOPPING=1")
        self._stop.set()
        self.worker.wake()
        for th in self._threads:
            th.join(timeout=10.0)
        self._threads = []
        self.df.stop()
        if self.kraken is not None:
            self.kraken.stop()
        self.link.close()
        self.tick_log.close()
        if self.notifier is not None:
            self.notifier.close()

    def __enter__(self) -> "OnboardApp":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ the autopilot's news (AutopilotEvents)
    def on_heartbeat(self) -> None:
        self.machine.check_mode()

    def on_link_lost(self) -> None:
        self.machine.on_link_lost()

    def on_link_back(self, lost_s: float) -> None:
        self.machine.on_link_back(lost_s)

    def on_reboot(self) -> None:
        """DF scans are stamped with the autopilot's clock: the scan bookkeeping starts over;
        the filters keep their state (the targets did not reboot) and go on from the next scan."""
        self.schedule.on_reboot()
        self.worker.on_reboot()
        self.tick_log.restart_rate()
        self.machine.on_reboot()

    def on_origin_moved(self, off_m: float) -> None:
        self.machine.on_origin_moved(off_m)

    def on_clock_jump(self, jump_s: float, now: float | None) -> None:
        if self.schedule.on_clock_jump(jump_s, now):
            self.tick_log.restart_rate()

    def on_limits(self) -> None:
        self.limits.check()

    # ------------------------------------------------------------------ io thread
    def _io_loop(self) -> None:
        while not self._stop.is_set():
            self._io_beat = self.mono()
            try:
                self._io_once()
            except Exception as exc:  # the glue itself: every handler below is contained already
                self.counters.add("io_errors")
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
                self.counters.add("io_errors")
        for data, addr in self.df.pop(IO_DF_MAX):
            with self.lock:
                self._handle("DF datagram", self.df_scans.on_datagram, data, addr)
        if self.kraken is not None:
            with self.lock:
                self._handle("KrakenSDR input", self.kraken.drain)
        with self.lock:
            self._periodic()

    def _read_mavlink(self) -> None:
        for _ in range(IO_MAVLINK_MAX):  # pymavlink buffers several messages per read
            msg = self.link.recv()
            if msg is None:
                break
            with self.lock:
                self._handle(f"MAVLink {_msg_type(msg)}", self.router.handle, msg)

    def _handle(self, where: str, fn, *args) -> bool:
        """Run one handler contained (io thread, under the lock): an error is counted
        (``io_errors``, ``errors.counts`` by kind), the first of a kind logged and said."""
        ok = self.errors.run(where, fn, *args)
        if not ok:
            self.counters.add("io_errors")
        return ok

    def _say_error(self, kind: str, exc: BaseException) -> None:
        with self.lock:  # the MAVLink read's handler runs without it
            self.publisher.say(f"error in {kind}"[:44], mavlink.MAV_SEVERITY_ERROR)

    def _periodic(self) -> None:
        """The parts' jobs in order, each on its own: one that raises is counted and the others
        still run (the tick schedule and the setpoint stream above all); a clocked job waits for
        the autopilot's clock. io thread, under the lock."""
        local = self.mono()
        now = self.clock.now()
        for job in self.jobs:
            if now is not None or not job.clocked:
                self._handle(job.where, job.run, local, now)

    # ------------------------------------------------------------------ the service manager
    def _service_beat(self) -> None:
        """(worker thread, each loop iteration) READY=1 once the io loop has run; WATCHDOG=1 every
        half watchdog period while the io loop iterates and the tick schedule runs (the app's
        own watchdog sees neither stuck). A hung tick stops the worker's loop, so its pings."""
        n = self.notifier
        if n is None:
            return
        local = self.mono()
        io_ok = local - self._io_beat < SERVICE_STALE_S and not self.watchdog.alarmed & {"io", "schedule"}
        if not self._ready_sent and io_ok:
            self._ready_sent = n.send("READY=1")
        every = n.ping_every_s
        if self._ready_sent and every is not None and io_ok and local - self._pinged >= every:
            n.send("WATCHDOG=1")
            self._pinged = local

    # ------------------------------------------------------------------ watchdog thread
    def _watchdog_loop(self) -> None:
        while not self._stop.wait(0.1):
            self.watchdog.check(Health(self.mono(), self.clock.now(), self._io_beat, self.schedule.ran_local,
                                       self.schedule.submitted_t, self.schedule.last_tick_t, self.worker.running))


def _open_link(cfg: AppConfig) -> Link:
    key = None
    if cfg.signing_key_path is not None:
        from onboard.app.signing import load_key
        key = load_key(cfg.signing_key_path)  # KeyFileError: refuse to start
    # an autopilot still booting (TCP refused) is waited for, as after a reboot
    unsigned = ((cfg.target_system or 1, mavlink.MAV_COMP_ID_AUTOPILOT1),) if cfg.autopilot_unsigned else ()
    return Link(cfg.mavlink_url, cfg.baud, cfg.tlog_path, source_system=cfg.target_system or 1,
                signing_key=key, wait_for_peer=True, unsigned_from=unsigned)


def _msg_type(msg) -> str:
    try:
        return str(msg.get_type())
    except Exception:
        return "?"


def _nan(x: float | None) -> float:
    return math.nan if x is None else float(x)


__all__ = ["AppConfig", "OnboardApp", "State", "Action", "Reason", "TGT_FIELDS", "STAT_FIELDS", "SPECS"]
