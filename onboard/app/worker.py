"""The worker thread: one core tick at a time (onboard.core.monitor.tick), the safety checks on
its result (belief collapse, the fence), its record (run log, PMON_TGT, PMON_STAT) and the
memory it gives back. A mixin of ``OnboardApp`` (onboard/app/app.py)."""
from __future__ import annotations

import ctypes
import json
import logging
import math
from dataclasses import replace

import numpy as np

from onboard.app.contract import State
from onboard.app.fence import Fence, violation
from onboard.app.mavlink_connection import mavlink
from onboard.app.schedule import PLAN_RESERVE_S, TickRecord
from onboard.app.setpoint_stream import PlannedSegment
from onboard.core import tracking
from onboard.core.monitor import MonitorSetup, Scan, tick
from onboard.core.planning import CandidateGrid

log = logging.getLogger("pmon.app")
FALLBACK_SAY_TICKS = 3  # a target's guidance on a fallback this many ticks in a row is said


class TickWorker:
    """Methods of ``OnboardApp``; the attributes they use are set up in ``OnboardApp.__init__``."""

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
            # the planner runs whenever the vehicle flies (its first plan costs several times a
            # warm one: ~0.4 s of a 0.9 s budget measured on ArduCopter SITL at the start of
            # monitoring), but its point is sent only while monitoring
            plan = planning or (self.vehicle.armed and self.vehicle.airborne())
            centre = self.poses.at(now) if plan else None  # where the vehicle is now
            pose = self.poses.latest()
            velocity = pose.vel[:2].copy() if plan and pose is not None else np.zeros(2)
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
                                    plan_from=centre, workspace=self.workspace, uav_velocity=velocity)
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
                        previous = self.setpoint, self.segment
                        self.setpoint, self.segment = np.array(nxt, float), _segment(setup, res, now, centre, velocity)
                        sent = self._send_setpoint(self.setpoint, self.clock.now() or job.t, centre)
                        if self.setpoint is None:  # refused as sent: the previous one stays
                            refused = "refused as sent"
                            self.setpoint, self.segment = previous
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
            # the plan to "next" (vehicle motion): what the setpoints sent until the next tick carry
            "segment": None if not sent or self.segment is None else {
                "t0": self.segment.t0, "p0": self.segment.p0.tolist(), "v0": self.segment.v0.tolist(),
                "v1": self.segment.v1.tolist(), "tick_s": self.segment.tick_s},
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


def _segment(setup: MonitorSetup, res, t0: float, centre, velocity) -> PlannedSegment | None:
    """The planned segment to the next point, for the vehicle motion (the jump model has none:
    its point is sent alone)."""
    p = res.planning
    if setup.motion.kind != "vehicle" or p is None or p.index is None or p.velocities is None:
        return None
    return PlannedSegment(t0, np.asarray(centre, float), np.asarray(velocity, float)[:2],
                          np.asarray(p.velocities[p.index], float)[:2], setup.model.dt_s)


def _with_grid(setup: MonitorSetup, grid: CandidateGrid) -> MonitorSetup:
    return replace(setup, grid=grid)


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)
