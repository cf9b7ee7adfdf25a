"""What the app keeps of its ticks: one record per tick (a dict: the run log's JSONL line, the
last ``history`` in memory, ``latest`` for PMON_STAT), the listeners told of each, and the tick
rate PMON_STAT reports. Bounded: a long flight must not grow the app's memory (bench/soak.py
checks RSS); whatever must be kept for good goes to the run log. Worker thread, under the app
lock (``notify`` without it)."""
from __future__ import annotations

import json
import logging
import math
from collections import deque
from typing import Callable

import numpy as np

log = logging.getLogger("pmon.app")


class TickLog:
    def __init__(self, history: int, runlog_path: str | None, counters):
        self.ticks: deque[dict] = deque(maxlen=history)  # per-tick records
        self.latest: dict | None = None
        # called with each tick's record (worker thread, after it is complete); a listener keeps
        # what it needs (bench/latency.py counts every tick this way, whatever ``history`` is);
        # it must be quick, and an exception in it is counted (listener_errors), never raised
        self.listeners: list[Callable[[dict], None]] = []
        self.counters = counters
        self._times: list[float] = []  # scan times of the last ten ticks (the tick rate)
        self._runlog = open(runlog_path, "w", buffering=1) if runlog_path else None

    def add(self, rec: dict) -> None:
        self.latest = rec
        self.ticks.append(rec)
        if self._runlog is not None:
            self._runlog.write(json.dumps(rec, allow_nan=False, default=_json_default) + "\n")

    def note_time(self, t: float) -> None:
        """A tick at scan time ``t`` was published (the rate counts it from now on)."""
        self._times = (self._times + [t])[-10:]

    def notify(self, rec: dict, lock) -> None:
        for fn in list(self.listeners):
            try:
                fn(rec)
            except Exception:
                with lock:
                    self.counters.add("listener_errors")
                log.exception("tick listener error")

    def rate_hz(self) -> float:
        """Ticks per autopilot second over the last ten ticks (0 before two)."""
        if len(self._times) < 2:
            return 0.0
        span = self._times[-1] - self._times[0]
        return (len(self._times) - 1) / span if span > 0 else 0.0

    def restart_rate(self) -> None:
        """The scan times start on a new timeline (a clock jump, a reboot)."""
        self._times = []

    def close(self) -> None:
        if self._runlog is not None:
            self._runlog.close()
            self._runlog = None


def record(job, res, state: int, sensor_pos, centre, sent, segment) -> dict:
    """The record of one tick. ``job``: the TickJob; ``res``: the core's TickResult; ``sent``:
    the send step's outcome (worker.Sent); ``segment``: the plan the setpoints carry until the
    next tick (sent ticks only)."""
    sig = np.sqrt(np.maximum(np.diagonal(res.covs, axis1=1, axis2=2), 0.0))
    sum_trace = None
    if res.planning is not None and res.planning.index is not None:
        sum_trace = float(res.planning.scores[res.planning.index])
    nxt = res.next_position
    n_ch = len(res.means)
    return {
        "t": job.t, "state": int(state), "planned": None, "sent_t": sent.ap_t, "due_t": job.due_t,
        "arrived_t": job.arrived_t,
        "channels": sorted(job.scans), "n_bearings": [len(job.scans[c].bearings) if c in job.scans else None
                                                     for c in range(n_ch)],
        "uav_enu": _rounded(sensor_pos),
        "plan_from": _rounded(centre),
        "means": np.round(res.means, 3).tolist(),
        "sigmas_xy": np.round(sig[:, :2], 3).tolist(),
        "cov_xy": np.round(res.covs[:, 0, 1], 3).tolist(),  # with sigmas_xy: the 1-sigma ellipse
        "next": _rounded(nxt),
        # the plan to "next" (vehicle motion): what the setpoints sent until the next tick carry
        "segment": None if not sent.sent or segment is None else {
            "t0": segment.t0, "p0": segment.p0.tolist(), "v0": segment.v0.tolist(),
            "v1": segment.v1.tolist(), "tick_s": segment.tick_s,
            "a0": None if segment.a0 is None else segment.a0.tolist()},
        "sent": sent.sent, "refused": sent.refused, "skipped_before": job.skipped,
        "n_candidates": None if res.planning is None else int(len(res.planning.candidates)),
        "n_admissible": None if res.planning is None else int(res.planning.admissible.sum()),
        "sum_trace": sum_trace,
        "timings_ms": {k: round(v * 1e3, 2) for k, v in res.timings_s.items()},
        "tick_ms": round(res.timings_s["tick"] * 1e3, 2),
        "latency_ms": round((sent.t_local - job.started_local) * 1e3, 2) if sent.sent else None,
        "wait_ms": round((sent.t_start_local - job.started_local) * 1e3, 2),
    }


def target_values(res, j: int, t: float, scan_t_used: float,
                  mode: tuple[int, float, int] = (0, math.nan, -1)) -> dict[str, float]:
    """PMON_TGT's values for target ``j`` by TGT_FIELDS name (onboard/app/contract.py); ``mode``:
    (TGT_MODES code, probability, goal index) of what it most likely does."""
    c = res.covs[j]
    m = res.means[j]
    return {
        "x_east_m": m[0], "y_north_m": m[1], "z_up_m": m[2], "vx_mps": m[3], "vy_mps": m[4], "vz_mps": m[5],
        "sigma_x_m": math.sqrt(max(c[0, 0], 0)), "sigma_y_m": math.sqrt(max(c[1, 1], 0)),
        "since_scan_s": t - scan_t_used if math.isfinite(scan_t_used) else -1.0,
        "cov_xy_m2": c[0, 1], "sigma_vx_mps": math.sqrt(max(c[3, 3], 0)),
        "sigma_vy_mps": math.sqrt(max(c[4, 4], 0)), "degenerate": float(res.degenerate[j]), "tick_time_s": t,
        "mode": float(mode[0]), "mode_p": float(mode[1]), "goal_index": float(mode[2]),
    }


def _rounded(x) -> list[float] | None:
    return None if x is None else [round(float(v), 3) for v in x]


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)
