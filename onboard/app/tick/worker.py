"""The worker thread: one core tick at a time, as

    snapshot -> tick -> check -> send -> record

- snapshot (under the app lock): the core setup, where the DF was at the scan's time, where the
  vehicle is now and how fast, and whether this tick's point is to be sent;
- tick: the core tick, injected (``tick``: ``onboard.core.monitor.tick`` unless a test injects
  a fault), with the guidance time left in the tick's budget;
- check: particle collapse (re-seeded), guidance fallbacks (reported);
- send: the next point through the fence to the setpoint stream, unless the state changed
  during the tick;
- record: the tick's record (run log, memory, listeners), PMON_TGT and PMON_STAT.

The schedule (onboard/app/tick/schedule.py) hands it a job when it is free; the worker gives
freed heap memory back to the OS while idle.
"""
from __future__ import annotations

import ctypes
import logging
import math
import threading
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from onboard.app.contract import TGT_MODES, State
from onboard.app.context import AppContext
from onboard.app.mavlink_connection import mavlink
from onboard.app.tick.core_side import MonitorCore
from onboard.app.tick.overrun import StageTimer, core_stages, describe, overrun_stage
from onboard.app.df.pairing import scans_for_tick
from onboard.app.replay_record import ReplayRecorder
from onboard.app.autopilot.setpoint_stream import PlannedSegment
from onboard.app.tick.log import TickLog, record, target_values
from onboard.app.tick.schedule import PLAN_RESERVE_S, TickJob
from onboard.core.tracking import intent_tick
from onboard.core import monitor
from onboard.core.clock_stops import SearchClock
from onboard.core.monitor import MonitorSetup, Scan, UavState

# ArduCopter's GUID_TIMEOUT default (s): a target older than this it no longer carries on
GUID_TIMEOUT_S = 3.0

log = logging.getLogger("pmon.app")
FALLBACK_SAY_TICKS = 3  # a target's guidance on a fallback this many ticks in a row is said
MODE_SAY_P = 0.9  # a target's most likely mode is said when it changes and holds this probability
OVERRUN_SAY_S = 10.0  # autopilot s: at most one overrun said per this (each is counted and logged)


@dataclass(frozen=True)
class Snapshot:
    """What a tick starts from, read under the app lock."""

    setup: MonitorSetup  # with the candidate grid within reach
    generation: int  # the state machine's, at the snapshot
    planning: bool  # the tick's point is to be sent
    now: float  # autopilot s
    sensor_pos: np.ndarray | None  # ENU m: where the DF was at the scan's time (telemetry)
    centre: np.ndarray | None  # ENU m: where the plan starts, the vehicle at the scan (None: no plan this tick)
    velocity: np.ndarray  # ENU m/s, planar: its velocity there
    acceleration: np.ndarray  # ENU m/s^2, planar: the plan's there (the last segment's end; 0 without one)


@dataclass(frozen=True)
class Sent:
    """The send step's outcome."""

    sent: bool
    refused: str | None  # why the point was not sent
    t_start_local: float  # local s the worker began the tick
    t_local: float  # local s after the send step
    ap_t: float | None  # autopilot s after the send step


class TickWorker:
    """``ctx``: the app's lock, clocks, parameters, counters and config (``trim_memory_s``);
    ``autopilot``: its poses and vehicle; ``machine``: the state machine; ``stream``: the
    setpoint stream; ``publisher``: says, PMON_TGT, PMON_STAT; ``log``: the tick log."""

    def __init__(self, ctx: AppContext, core: MonitorCore, autopilot, machine, stream, publisher,
                 log: TickLog, tick: Callable = monitor.tick):
        self.core = core
        self.lock = ctx.lock
        self.clock = ctx.clock
        self.mono = ctx.mono
        self.params = ctx.params
        self.autopilot = autopilot
        self.machine = machine
        self.stream = stream
        self.publisher = publisher
        self.say = publisher.say
        self.log = log
        self.counters = ctx.counters
        self.tick = tick
        self.recorder = ReplayRecorder(core, ctx.cfg.seed)  # the run log's replay fields
        self.busy = False  # a job handed over and not finished
        self.running: TickJob | None = None  # the job being ticked (the watchdog reads it)
        self._job: TickJob | None = None
        self._event = threading.Event()
        n = core.n_targets
        self.scan_t_used = [-math.inf] * n  # newest scan time <= a tick, per channel (PMON_TGT)
        self._fallback = [0] * n  # consecutive ticks target j's guidance was on a fallback
        self._announced: list[str | None] = [None] * n  # the mode last said per target (MODE_SAY_P)
        self._modes: list[tuple[int, float, int]] = [(0, math.nan, -1)] * n  # PMON_TGT's mode fields
        # autopilot s between returns of freed heap memory to the OS (see _trim_memory)
        self.trim_memory_s = ctx.cfg.trim_memory_s
        self._malloc_trim = _malloc_trim() if self.trim_memory_s > 0 else None
        self._trimmed_t = -math.inf
        self.last_overrun: str | None = None  # the stage the newest overrun passed its budget in
        self._overrun_said_t = -math.inf  # autopilot s an overrun was last said
        self._unsaid_overruns = 0
        # called every loop iteration (between ticks, and at most 0.1 s apart while idle): the
        # service watchdog's ping (onboard/app/app.py), which a hung tick therefore stops
        self.beat: Callable[[], None] | None = None

    # ----- the thread
    def submit(self, job: TickJob) -> None:
        self.busy = True
        self._job = job
        self._event.set()

    def wake(self) -> None:
        self._event.set()

    def loop(self, stop: threading.Event) -> None:
        while not stop.is_set():
            if self.beat is not None:
                try:
                    self.beat()
                except Exception:  # never the loop's end
                    with self.lock:
                        self.counters.add("beat_errors")
            self._event.wait(0.1)
            self._event.clear()
            job, self._job = self._job, None
            if job is None:
                self._trim_memory()
                continue
            job.run_local = self.mono()
            self.running = job
            try:
                self.run(job)
            except Exception:
                with self.lock:
                    self.counters.add("tick_errors")
                log.exception("tick error")
            finally:
                self.running = None
                with self.lock:
                    self.busy = False

    def on_reboot(self) -> None:
        self.scan_t_used = [-math.inf] * self.core.n_targets
        self._overrun_said_t = -math.inf  # the autopilot's clock started over

    # ----- one tick
    def run(self, job: TickJob) -> None:
        t_start, ap_start = self.mono(), self.clock.now()
        snap = self._snapshot(job)
        scans = self._scans(job, snap)
        setup = self._with_guidance_time(snap.setup, job)
        timer = StageTimer()
        clock = SearchClock(timer)  # the guidance's deadlines, and where they stopped it (the replay's)
        rng_state = self.core.rng.bit_generator.state
        t_core = self.mono()
        plan_from = None if snap.centre is None else UavState(snap.centre, snap.velocity, snap.acceleration)
        self.core.state, res = self.tick(setup, self.core.state, scans, self.core.rng, plan_from=plan_from,
                                         workspace=self.core.workspace, timer=clock)
        t_core_end = self.mono()
        reseeded = self.core.reseed_collapsed(setup, res)
        stages = core_stages(res.timings_s, timer.marks)
        stages["update"] += t_core - t_start  # the snapshot and the pairing: the update's inputs
        with self.lock:
            self._report(res, reseeded)
            sent = self._send(job, snap, setup, res, t_start)
            stages["send"] = sent.t_local - t_core_end
            overrun = self._overrun(job, sent, stages, ap_start)
            self._count(job, snap, sent)
            rec = self._record(job, snap, res, sent, reseeded, stage_ms={k: round(v * 1e3, 2) for k, v in stages.items()},
                               overrun=overrun, replay=self.recorder.fields(setup, scans, plan_from, rng_state, clock, res))
        self.log.notify(rec, self.lock)

    def _snapshot(self, job: TickJob) -> Snapshot:
        with self.lock:
            setup = self.core.tick_setup()
            planning = self.machine.commanding()
            now = self.clock.now() or job.t
            poses, v = self.autopilot.poses, self.autopilot.vehicle
            # the planner runs whenever the vehicle flies (its first plan costs several times a
            # warm one: ~0.4 s of a 0.9 s budget measured on ArduCopter SITL at the start of
            # monitoring), but its point is sent only while monitoring
            plan = planning or (v.armed and v.airborne())
            # the plan starts from the vehicle's state at the scan (job.t), not at the snapshot:
            # its next point is then where the vehicle is to be at the next scan, one tick on.
            # From the state at the snapshot (~0.09 s later on ArduCopter SITL) the plan ran that
            # much past the next scan: at 8 m/s the copter was 0.6-0.7 m short of every planned
            # point at it (bench/ardupilot.py, docs/SITL.md)
            sensor = poses.at(job.t)
            vel = poses.velocity_at(job.t) if plan else None
            return Snapshot(setup, self.machine.generation, planning, now, sensor,
                            sensor if plan else None, vel[:2].copy() if vel is not None else np.zeros(2),
                            self._plan_acceleration(setup, job.t))

    def _plan_acceleration(self, setup: MonitorSetup, t: float) -> np.ndarray:
        """(under the lock) The acceleration the plan has at ``t`` with a continuous acceleration
        (``planning.jerk_max_mps3`` > 0): the last segment's at its end, where the autopilot's
        target carries it on (a segment ended GUID_TIMEOUT_S before ``t`` or none: 0, the
        autopilot has stopped, or the vehicle was not in the app's hands)."""
        seg = self.stream.segment
        if setup.motion.jerk_max_mps3 <= 0.0 or seg is None or seg.a0 is None \
                or not -0.5 * seg.tick_s <= t - (seg.t0 + seg.tick_s) <= GUID_TIMEOUT_S:
            return np.zeros(2)
        return seg.end_acceleration()

    def _scans(self, job: TickJob, snap: Snapshot) -> list[Scan]:
        """The job's bearings as core scans, each channel paired with where the DF was when it
        measured (onboard/app/df/pairing.py; a channel without a position is dropped)."""
        for ch in job.scans:  # newest scan time <= this tick per channel (PMON_TGT)
            self.scan_t_used[ch] = max(self.scan_t_used[ch], job.t)
        poses = self.autopilot.poses
        scans, unpaired = scans_for_tick(job.scans, job.t, self.core.n_targets,
                                         lambda tm: snap.sensor_pos if tm == job.t else poses.at(tm))
        if unpaired:
            with self.lock:
                self.counters.add("scans_without_pose")
                self.say("DF scan without a vehicle position: dropped", mavlink.MAV_SEVERITY_WARNING, once="nopose")
        return scans

    def _with_guidance_time(self, setup: MonitorSetup, job: TickJob) -> MonitorSetup:
        """Guidance time, in autopilot s: PMON_GUID_S, and never more than what is left of the
        tick's budget after a reserve for planning and sending (converted to local seconds at
        the clock's rate: at a SITL speedup of 4, 0.3 s of autopilot time is 75 ms)."""
        rate = getattr(self.clock, "rate", 1.0) or 1.0
        left = job.t + self.params.settings.app.tick_budget_s - PLAN_RESERVE_S - (self.clock.now() or job.t)
        per_target_s = max(min(self.params.settings.app.guidance_s, left), 0.0) / rate / max(setup.n_targets, 1)
        return replace(setup, guidance=replace(setup.guidance, max_solve_time_s=per_target_s))

    def _report(self, res, reseeded: list[int]) -> None:
        """Guidance time-outs and fallbacks: counted every tick (PMON_STAT, the run log); said
        when a target's guidance stays on a fallback FALLBACK_SAY_TICKS ticks in a row, and when
        it is back after that (a single tick on the previous plan is the designed degradation,
        not news for the pilot). Re-seeded targets: counted and said."""
        if any(p.status == "timeout" for p in res.plans):
            self.counters.add("guidance_timeouts")
        for j, plan in enumerate(res.plans):
            if plan.status.startswith("fallback"):
                self.counters.add(plan.status)
                self._fallback[j] += 1
                if self._fallback[j] == FALLBACK_SAY_TICKS:
                    how = "previous plan shifted" if plan.status == "fallback_previous" else "coasting"
                    self.say(f"T{j + 1} guidance failed {FALLBACK_SAY_TICKS} ticks: {how}", mavlink.MAV_SEVERITY_WARNING)
            else:
                if self._fallback[j] >= FALLBACK_SAY_TICKS:
                    self.say(f"T{j + 1} guidance back")
                self._fallback[j] = 0
        for j in reseeded:
            self.counters.add("reseeds")
            self.say(f"T{j + 1}: particle collapse: re-seeded from its last estimate", mavlink.MAV_SEVERITY_ERROR)
        self._report_modes(res)

    def _report_modes(self, res) -> None:
        """What each target most likely does (PMON_TGT's mode fields), said when it changes with
        confidence ("T2: stationary 0.93", "T1: heading for G 0.95"); a target the bearings no
        longer explain, re-seeded along them, is counted and said."""
        if res.mode_probabilities is None:
            return
        setup = self.core.setup
        goals = [g.name for g in self.core.scenario.goals]
        for j, (kind, goal, p) in enumerate(intent_tick.most_likely(setup, res.mode_probabilities)):
            self._modes[j] = (TGT_MODES.index(kind), p, goals.index(goal) if goal in goals else -1)
            said = f"heading for {goal}" if goal is not None else kind
            if p >= MODE_SAY_P and said != self._announced[j]:
                self._announced[j] = said
                self.say(f"T{j + 1}: {said} {p:.2f}")
        for j in np.flatnonzero(res.reseeded):
            self.counters.add("lost_reseeds")
            self.say(f"T{j + 1}: bearings unexplained: re-seeded along them", mavlink.MAV_SEVERITY_WARNING)

    def _send(self, job: TickJob, snap: Snapshot, setup: MonitorSetup, res, t_start: float) -> Sent:
        sent, refused = False, None
        nxt = res.next_position
        if nxt is not None and snap.planning:
            if self.machine.generation != snap.generation or self.machine.state != State.MONITORING:
                refused = "state changed during the tick"
            else:
                segment = _segment(setup, res, job.t, snap.centre, snap.velocity, snap.acceleration)
                sent, refused = self.stream.adopt(nxt, segment, self.clock.now() or job.t, snap.centre, setup)
        return Sent(sent, refused, t_start, self.mono(), self.clock.now())

    def _overrun(self, job: TickJob, sent: Sent, stages: dict[str, float], ap_start: float | None) -> str | None:
        """(under the lock) A tick whose send step ended past its budget: the stage it passed
        the deadline in (onboard/app/tick/overrun.py), counted per stage and said in one line, at
        most once per OVERRUN_SAY_S of autopilot time (with how many more since)."""
        deadline = job.t + self.params.settings.app.tick_budget_s
        if sent.ap_t is None or sent.ap_t <= deadline or not job.scans:  # a coast tick has no scan to be late for
            return None
        rate = getattr(self.clock, "rate", 1.0) or 1.0
        left_s = (deadline - (job.t if ap_start is None else ap_start)) / rate
        stage = overrun_stage(left_s, stages)
        self.last_overrun = stage
        self.counters.add("overruns")
        self.counters.add(f"overruns_{stage}")
        self._unsaid_overruns += 1
        if sent.ap_t >= self._overrun_said_t + OVERRUN_SAY_S:
            more = self._unsaid_overruns - 1
            self.say(describe(job.t, sent.ap_t - deadline, stage, stages)
                     + (f"; {more} more since the last said" if more and math.isfinite(self._overrun_said_t) else ""),
                     mavlink.MAV_SEVERITY_WARNING)
            self._overrun_said_t, self._unsaid_overruns = sent.ap_t, 0
        return stage

    def _count(self, job: TickJob, snap: Snapshot, sent: Sent) -> None:
        self.counters.add("ticks")
        late = sent.ap_t is not None and sent.ap_t > job.t + self.params.settings.app.tick_budget_s
        if late and snap.planning and job.scans:  # a coast tick has no scan to be late for
            self.counters.add("ticks_late")

    def _record(self, job: TickJob, snap: Snapshot, res, sent: Sent, reseeded: list[int], **more) -> dict:
        rec = record(job, res, self.machine.state, snap.sensor_pos, snap.centre, sent, self.stream.segment)
        rec.update(planned=snap.planning, plans=[p.status for p in res.plans],
                   qp_solves=[p.qp_solves for p in res.plans],
                   guidance_timeouts=[p.status == "timeout" for p in res.plans], reseeded=reseeded, **more)
        self.log.add(rec)
        if self.autopilot.vehicle.sysid is not None:
            for j in range(self.core.n_targets):
                self.publisher.publish_target(j, target_values(res, j, rec["t"], self.scan_t_used[j], self._modes[j]),
                                              rec["t"])
            self.publisher.publish_stat(self.mono())
        self.log.note_time(job.t)
        return rec

    # ----- memory
    def _trim_memory(self) -> None:
        """Give freed heap pages back to the OS, once per ``trim_memory_s`` of autopilot time,
        from the worker while it is idle (between ticks). Python frees a tick's temporary arrays
        at once, but glibc keeps the pages (its mmap threshold rises to the largest array ever
        freed; arenas are trimmed only at the top), so the resident size would follow the
        largest tick so far, not what is in use. A few ms per call; worker thread."""
        now = self.clock.now()
        if self._malloc_trim is None or now is None or now < self._trimmed_t + self.trim_memory_s:
            return
        self._trimmed_t = now
        try:
            self._malloc_trim(0)
        except Exception:  # ctypes failure: never again, never fatal
            self._malloc_trim = None
            return
        with self.lock:
            self.counters.add("memory_trims")


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


def _segment(setup: MonitorSetup, res, t0: float, centre, velocity, acceleration) -> PlannedSegment | None:
    """The planned segment to the next point, for the vehicle motion (the jump model has none:
    its point is sent alone). It starts at ``t0``, the scan's time, where the vehicle was then
    (``centre``, at ``velocity``), in the plane, and at the planned
    point's altitude (h): the planner flies at h, so the setpoints hold h, and a vehicle off it
    (h just changed, a pilot flew it lower) is flown back to it. With a continuous acceleration
    its acceleration starts at ``acceleration``, the plan's (Snapshot.acceleration)."""
    p = res.planning
    if setup.motion.kind != "vehicle" or p is None or p.index is None or p.velocities is None:
        return None
    start = np.array([centre[0], centre[1], res.next_position[2]], float)
    a0 = np.asarray(acceleration, float)[:2].copy() if setup.motion.jerk_max_mps3 > 0.0 else None
    return PlannedSegment(t0, start, np.asarray(velocity, float)[:2],
                          np.asarray(p.velocities[p.index], float)[:2], setup.model.dt_s, a0)
