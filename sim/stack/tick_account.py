"""Missed ticks and latency of a mission, counted as it flies (one definition for every bench and
test that counts them: bench/latency.py and bench/soak.py against the mock autopilot, the
ArduPilot SITL procedure in sim/stack/procedure.py). docs/SITL.md says what counts as a miss.
"""
from __future__ import annotations

import json
import math
import threading
from collections import deque
from typing import Iterator

import numpy as np

from onboard.core.setpoint import plan_setpoint

# a planned segment's setpoint at time t, against one received or reported then: the sender's
# and the autopilot's clocks differ by the link's delay (~10 m/s x 20 ms), the firmware advances
# the target between messages itself
SEGMENT_TOL_M = 0.5
# ... or holds it as sent until the next message (PX4's OFFBOARD): the segment's position at the
# report, or as it was up to one re-send period (10 Hz) and the report's delay before
HELD_BACK_S = (0.0, 0.04, 0.08, 0.12, 0.16)


class Dist:
    """Count, max and quantiles of a stream in constant memory: a fixed histogram of ``step``
    wide bins on [0, hi) (values above land in the last bin; the max is exact)."""

    def __init__(self, step: float, hi: float):
        self.step = step
        self.counts = np.zeros(int(math.ceil(hi / step)) + 1, dtype=np.int64)
        self.counts.fill(0)  # touch every page now: resident from the start, not as bins fill
        self.n = 0
        self.max = -math.inf

    def add(self, x: float) -> None:
        i = min(max(int(x / self.step), 0), len(self.counts) - 1)
        self.counts[i] += 1
        self.n += 1
        self.max = max(self.max, x)

    def quantile(self, q: float) -> float | None:
        if not self.n:
            return None
        i = int(np.searchsorted(np.cumsum(self.counts), max(math.ceil(q * self.n), 1)))
        return min((i + 0.5) * self.step, self.max)


class TickAccount:
    """Issue 5's missed ticks, counted as the mission flies (constant memory). A scan is missed if

    * it never reached a tick: skipped at an overrun, rejected on arrival (stale: delivered after
      its time had been coasted, or > 5 s late), never arrived, or still pending at the end
      (= scans the feed sent - scans ticked; skipped ones are counted here, once), or
    * its tick was a monitoring tick whose setpoint was not sent, or reached the autopilot (its
      own clock) later than PMON_BUDGET after the scan's time, or after the scan's arrival when
      the feed delivered it late.

    ``on_tick(rec, budget)`` with each of the app's tick records (its tick listener, or its run
    log), ``on_setpoint(t, (n, e, d))`` with each setpoint the autopilot received (its own time,
    s; the position in NED at the mission origin = (north, east, -up) of the mission ENU frame:
    the mock's home is the origin; an ArduPilot's reported targets are converted). Thread-safe."""

    RX_KEEP_S = 30.0  # autopilot s of received setpoints kept to match a tick's setpoint
    GIVE_UP_S = 10.0  # a tick's setpoint not received this long after its budget: missed

    def __init__(self):
        self._lock = threading.Lock()
        self._rx: deque = deque()  # (autopilot t, x, y, z), the last RX_KEEP_S
        self._pending: list[dict] = []  # monitoring ticks waiting for their setpoint's receipt
        self.ticks = 0  # ticks of a scan (coast ticks, which have none, are not counted)
        self.monitoring_ticks = 0
        self.late: list[float] = []  # first 20 scan times (the count is n_late)
        self.n_late = 0
        self.skipped = 0
        self.latency_ms = Dist(0.1, 2000.0)
        self.tick_ms = Dist(0.1, 5000.0)
        self.delay_s = Dist(0.001, 30.0)
        self.lag_s = Dist(0.001, 30.0)
        self.first_t: float | None = None
        self.last_t: float | None = None
        self.gaps: list[float] = []  # candidate unticked scan times (checked against the feed's)

    def _late(self, t: float) -> None:
        self.n_late += 1
        if len(self.late) < 20:
            self.late.append(t)

    @staticmethod
    def _matches(r, p: dict) -> bool:
        """A received setpoint (or a target the autopilot reports holding) is the tick's: its
        point exactly, or, for a planned segment (position + velocity + acceleration, moved on
        by the autopilot itself), the segment's position at that moment within SEGMENT_TOL_M, or
        at a moment up to HELD_BACK_S before (a target held as sent: PX4). Not before the app
        sent it (its ``sent_t``, autopilot s): a plan continuous with the last one (it starts at
        the scan, where the vehicle flying the last one was) is within SEGMENT_TOL_M of the
        target the autopilot already holds, which is not the tick's setpoint's receipt."""
        if r[0] < max(p["t"], p.get("sent_t") or p["t"]):
            return False
        seg = p.get("segment")
        if seg is None:
            return abs(r[1] - p["n"]) < 0.01 and abs(r[2] - p["e"]) < 0.01 and abs(r[3] + p["u"]) < 0.01
        if abs(r[3] + seg["p0"][2]) >= 0.05:
            return False
        for back in HELD_BACK_S:
            d = min(max(r[0] - back - seg["t0"], 0.0), seg["tick_s"])
            pos, _, _ = plan_setpoint(seg["p0"][:2], seg["v0"], seg["v1"], seg["tick_s"], d, seg.get("a0"))
            if math.hypot(r[1] - pos[1], r[2] - pos[0]) < SEGMENT_TOL_M:
                return True
        return False

    def _resolve(self, p: dict, t_rx: float) -> None:
        d = t_rx - p["start"]
        self.delay_s.add(d)
        if d > p["budget"]:
            self._late(p["t"])

    def on_setpoint(self, t: float, xyz) -> None:
        r = (t, float(xyz[0]), float(xyz[1]), float(xyz[2]))
        with self._lock:
            self._rx.append(r)
            while self._rx and self._rx[0][0] < t - self.RX_KEEP_S:
                self._rx.popleft()
            keep = []
            for p in self._pending:
                if self._matches(r, p):
                    self._resolve(p, t)
                elif t > p["start"] + p["budget"] + self.GIVE_UP_S:
                    self._late(p["t"])
                else:
                    keep.append(p)
            self._pending = keep

    def on_tick(self, rec: dict, budget: float) -> None:
        if not rec["channels"]:
            return
        t = rec["t"]
        with self._lock:
            self.ticks += 1
            self.skipped += rec["skipped_before"]
            self.tick_ms.add(rec["tick_ms"])
            if self.last_t is not None:
                k = self.last_t + 1.0
                while k < t - 0.5 and len(self.gaps) < 100:
                    self.gaps.append(k)
                    k += 1.0
            self.first_t = t if self.first_t is None else self.first_t
            self.last_t = t
            if not rec["planned"]:
                return
            self.monitoring_ticks += 1
            if rec["latency_ms"] is not None:
                self.latency_ms.add(rec["latency_ms"])
            start = max(t, rec["arrived_t"] if rec["arrived_t"] is not None else t)
            self.lag_s.add(start - t)
            if not rec["sent"] or rec["next"] is None:
                self._late(t)
                return
            e, n, u = rec["next"]
            p = {"t": t, "start": start, "budget": budget, "e": e, "n": n, "u": u,
                 "segment": rec.get("segment"), "sent_t": rec.get("sent_t")}
            hit = next((r for r in self._rx if self._matches(r, p)), None)
            if hit is not None:
                self._resolve(p, hit[0])
            else:
                self._pending.append(p)

    def finish(self, scan_times) -> dict:
        """Figures, given the times of the scans the feed sent (an iterable, streamed)."""
        with self._lock:
            for p in self._pending:  # never received
                self._late(p["t"])
            self._pending = []
            sent, unticked_t, gaps = 0, [], set(self.gaps)
            for t in scan_times:
                sent += 1
                if len(unticked_t) < 20 and (self.first_t is None or t < self.first_t or t > self.last_t
                                             or t in gaps):
                    unticked_t.append(t)
            unticked = sent - self.ticks
            r = lambda x, n: None if x is None else round(float(x), n)  # noqa: E731
            return {
                "scans": sent, "ticks": self.ticks, "monitoring_ticks": self.monitoring_ticks,
                "latency_ms_median": r(self.latency_ms.quantile(0.5), 1),
                "latency_ms_p95": r(self.latency_ms.quantile(0.95), 1),
                "latency_ms_max": r(self.latency_ms.max if self.latency_ms.n else None, 1),
                "setpoint_delay_s_median": r(self.delay_s.quantile(0.5), 3),
                "setpoint_delay_s_max": r(self.delay_s.max if self.delay_s.n else None, 3),
                "feed_lag_s_max": r(self.lag_s.max if self.lag_s.n else None, 3),
                "tick_ms_median": r(self.tick_ms.quantile(0.5), 1),
                "ticks_missed": self.n_late + unticked,
                "ticks_late": self.n_late, "late_t": list(self.late),
                "scans_unticked": unticked, "ticks_skipped": self.skipped, "unticked_t": unticked_t,
            }


def scan_times(truth_path) -> Iterator[float]:
    """Times of the scans the feed sent (its truth JSONL, streamed)."""
    with open(truth_path) as f:
        for line in f:
            if line.strip() and '"header"' not in line:
                yield float(json.loads(line)["t"])
