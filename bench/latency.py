"""Setpoint latency and missed ticks of the onboard app, flown against the mock autopilot.

    python bench/latency.py [--duration 600] [--speedup 5]

Mock autopilot and app run in this process (threads, real loopback sockets); the DF feed is a
process of its own (``pmon feed live``, as on the vehicle: its truth world must not hold this
process's GIL while the app ticks). Paper scenario; the app launches by itself. The mock runs
SITL-like (``max_lag_s=0.1``): when the machine cannot sustain the speedup its clock slips
instead of jumping (counted, printed as ``clock_slips``; the achieved speedup is printed too).

Latency: local wall time from a tick's start (its scan is due and handed to the worker) to its
setpoint leaving the socket. Missed (``TickAccount``, the one definition; bench/soak.py uses it
too): a scan sent by the feed that never reached a tick (skipped at an overrun, rejected on
arrival, e.g. as stale, or still pending at shutdown), or a monitoring tick whose setpoint was
not sent or reached the autopilot (the mock's own clock) later than PMON_BUDGET after the scan's
time (or after its arrival when the feed delivered it late; the feed lag is printed). Scans
before monitoring (take-off) are ticked like any other (tracking runs in every state) and count
the same way: a scan not ticked is missed whatever the app's state. Counted as the mission flies
(a tick listener and the autopilot's setpoint handler, in constant memory), so a mission of any
length is counted whole; quantiles come from fixed histograms (0.1 ms / 1 ms bins).
The feed's own lateness (scans it sent > 0.25 s after their time) is printed: a simulator that
cannot keep up makes misses that are not the app's. Last line: JSON figures.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path
from typing import Iterator

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sim.autopilot import MockAutopilot  # noqa: E402  (sets MAVLINK20 first)
from onboard.app.app import AppConfig, OnboardApp  # noqa: E402
from onboard.config import load_scenario  # noqa: E402
from onboard.demo import DEMO_VEHICLE_PARAMS  # noqa: E402


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

    ``on_tick(rec, budget)`` from the app's tick listener, ``on_setpoint(t, (x, y, z))`` from the
    autopilot's SET_POSITION_TARGET_LOCAL_NED handler (its time; home = mission origin, so local
    NED = (north, east, -up)). Thread-safe."""

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
        return r[0] >= p["t"] and abs(r[1] - p["n"]) < 0.01 and abs(r[2] - p["e"]) < 0.01 \
            and abs(r[3] + p["u"]) < 0.01

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
            p = {"t": t, "start": start, "budget": budget, "e": e, "n": n, "u": u}
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


def fly(duration: float, speedup: float, seed: int, cfg_extra: dict | None = None, on_app=None,
        on_setpoint=None, after=None) -> dict:
    """Fly one mission; returns the app, its TickAccount figures, the mock's counters, the feed's.

    ``on_app(app)`` every 0.5 s wall, ``on_setpoint(msg)`` per setpoint the autopilot receives,
    ``after(app)`` when the mission is over (before anything is torn down or read back)."""
    sc = load_scenario("paper")
    o = sc.origin
    account = TickAccount()
    with tempfile.TemporaryDirectory() as tmp, \
            MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=speedup, seed=seed,
                          endpoints=["tcpin:127.0.0.1:0"] * 2, params=DEMO_VEHICLE_PARAMS,
                          max_lag_s=0.1) as ap:
        orig = ap._on_set_position_target_local_ned

        def spy(link, msg):
            account.on_setpoint(ap.copter.t, (msg.x, msg.y, msg.z))
            if on_setpoint is not None:
                on_setpoint(msg)
            orig(link, msg)
        ap._on_set_position_target_local_ned = spy
        app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{ap.port('tcpin', 0)}", sensor_port=0,
                                   auto_launch=True, seed=seed, **(cfg_extra or {})), sc)
        app.tick_listeners.append(lambda rec: account.on_tick(rec, app.params["PMON_BUDGET"]))
        app.start()
        truth = Path(tmp) / "truth.jsonl"
        feed_out = Path(tmp) / "feed.out"
        wall0, t0 = time.monotonic(), ap.sim_time
        with open(feed_out, "w") as fo:
            feed = subprocess.Popen(
                [sys.executable, "-m", "sim.feed", "live", "--mavlink", f"tcp:127.0.0.1:{ap.port('tcpin', 1)}",
                 "--to", f"127.0.0.1:{app.sensor_port}", "--seed", str(seed + 1), "--duration", str(int(duration)),
                 "--truth", str(truth)], cwd=ROOT, stdout=fo)
        try:
            while feed.poll() is None:
                if on_app is not None:
                    on_app(app)
                time.sleep(0.5)
            # the last scan's tick: wait until nothing is pending or running (bounded)
            deadline = time.monotonic() + 10
            while (app.scans.pending or app._worker_busy) and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(1.5 / speedup)
            if after is not None:
                after(app)
        finally:
            if feed.poll() is None:
                feed.terminate()
            feed.wait(timeout=10)
            app.stop()
        wall = time.monotonic() - wall0
        achieved = (ap.sim_time - t0) / wall
        figures = account.finish(scan_times(truth))
        done = re.search(r"(\d+) sent > [\d.]+ s late \(max ([\d.]+) s", feed_out.read_text())
        return {"app": app, "figures": figures, "ap_counters": ap.counters(),
                "achieved_speedup": achieved, "wall_s": wall, "feed_rc": feed.returncode,
                "feed_late_scans": int(done.group(1)) if done else None,
                "feed_send_lag_s_max": float(done.group(2)) if done else None}


def figures(run: dict, duration: float, speedup: float) -> dict:
    app = run["app"]
    f = run["figures"]
    rejected = {k: v for k, v in app.scans.rejected.items() if v}
    c = app.counters
    return {
        "mission_s": duration, "speedup": speedup, "achieved_speedup": round(run["achieved_speedup"], 2),
        **f, "datagrams_rejected": rejected,
        "feed_late_scans": run["feed_late_scans"], "feed_send_lag_s_max": run["feed_send_lag_s_max"],
        "scans_without_pose": c.get("scans_without_pose", 0), "ticks_coasted": c.get("ticks_coasted", 0),
        "guidance_timeouts": c.get("guidance_timeouts", 0),
        "fallbacks": c.get("fallback_previous", 0) + c.get("fallback_coast", 0),
        "tick_errors": c.get("tick_errors", 0), "io_errors": c.get("io_errors", 0),
        "listener_errors": c.get("listener_errors", 0),
        "clock_slips": run["ap_counters"].get("clock_slips", 0), "wall_s": round(run["wall_s"], 1),
        "load_avg_1m_end": round(os.getloadavg()[0], 2),
    }


def main() -> int:
    ap_ = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap_.add_argument("--duration", type=float, default=60.0, help="mission seconds (default 60: smoke)")
    ap_.add_argument("--speedup", type=float, default=5.0)
    ap_.add_argument("--seed", type=int, default=1)
    args = ap_.parse_args()
    run = fly(args.duration, args.speedup, args.seed)
    f = figures(run, args.duration, args.speedup)
    print(f"{f['monitoring_ticks']} monitoring ticks; latency median {f['latency_ms_median']} ms; "
          f"missed {f['ticks_missed']} (late {f['ticks_late']}, unticked {f['scans_unticked']} of which "
          f"skipped {f['ticks_skipped']}); feed late {f['feed_late_scans']}; "
          f"{f['achieved_speedup']}x achieved, load {f['load_avg_1m_end']}")
    print(json.dumps(f))
    return 0


if __name__ == "__main__":
    sys.exit(main())
