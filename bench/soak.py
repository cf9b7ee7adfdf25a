"""Soak: a long accelerated mission against the mock autopilot; memory, misses, errors, fence.

    python -m bench.soak [--duration 7200] [--speedup 5]

Flies like bench/latency.py (mock autopilot + app in this process, the DF feed as a process)
and prints: RSS growth of this process (app + mock autopilot; measured from the end of the first
10 % of the mission, after warm-up, to the end), ticks missed (bench/latency.py's TickAccount:
the same definition, counted over the whole mission, not from the app's capped tick history),
exceptions (app io/tick/listener errors, mock loop/handler errors), and setpoints the AUTOPILOT
received outside the fence (area, altitude band PMON_ALT_MIN..MAX, obstacles inflated by the UAV
margin), checked independently of the app. The bench's own bookkeeping is constant in size
(counters, fixed histograms, the first few examples), so the RSS growth is the app's and the
mock's. ``--tracemalloc N``: also print the N biggest allocation growths (file:line) between the
same two points (slower; for finding a leak, not for the figure). The app runs with its default
``history``. Issue 7's figure is --duration 7200 (2 h of mission; 24 min of wall time at 5x).
Last line: JSON figures (with the 1-minute load average at the start and the end).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tracemalloc

import numpy as np

from bench import latency
from onboard.config import load_scenario
from onboard.core.obstacles import Obstacles


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _fence_check(sc, fence: dict, st: dict):
    """A setpoint listener counting into ``fence`` the setpoints outside the area, the app's
    altitude band or an inflated obstacle."""
    lo, hi = np.array(sc.area.min_m), np.array(sc.area.max_m)
    inflated = Obstacles.from_boxes(sc.obstacles).inflate(sc.uav.obstacle_margin_m)

    def check(msg):  # mock home = mission origin: local NED = (north, east, -up)
        fence["received"] += 1
        p = np.array([msg.y, msg.x, -msg.z])
        app = st["app"]
        band = (app.params.settings.app.fence_min_m, app.params.settings.app.fence_max_m) if app else (0.0, 1e9)
        if np.any(p < lo) or np.any(p > hi) or not band[0] <= p[2] <= band[1] \
                or (len(inflated) and inflated.contains(p[None]).any()):
            fence["outside"] += 1
            if len(fence["examples"]) < 5:
                fence["examples"].append(p.round(2).tolist())
    return check


def soak(duration: float, speedup: float, seed: int = 1, trace: int = 0) -> dict:
    fence = {"outside": 0, "examples": [], "received": 0}
    # constant-size bookkeeping: RSS at the warm-up mark, at the end, and its max
    st = {"app": None, "base": None, "end": None, "max": -np.inf, "snap": None, "growth": None}
    check = _fence_check(load_scenario("paper"), fence, st)
    load0 = os.getloadavg()[0]
    if trace:
        tracemalloc.start(8)

    def on_app(app):
        st["app"] = app
        rss = rss_mb()
        st["max"] = max(st["max"], rss)
        if st["base"] is None and app.counters.get("ticks", 0) >= 0.1 * duration:
            st["base"] = rss
            if trace:
                st["snap"] = tracemalloc.take_snapshot()

    def after(app):  # the mission is over, nothing torn down yet
        st["end"] = rss_mb()
        if trace and st["snap"] is not None:
            stats = tracemalloc.take_snapshot().compare_to(st["snap"], "lineno")
            st["growth"] = [f"{s.size_diff / 1024:+.0f} kB {s.count_diff:+d} {s.traceback[0]}"
                            for s in stats[:trace]]
            tracemalloc.stop()

    run = latency.fly(duration, speedup, seed, on_app=on_app, on_setpoint=check, after=after)
    f = latency.figures(run, duration, speedup)
    base = st["base"] if st["base"] is not None else float("nan")
    end = st["end"] if st["end"] is not None else float("nan")
    c, ac = run["app"].counters, run["ap_counters"]
    out = {
        "mission_s": duration, "speedup": speedup, "achieved_speedup": f["achieved_speedup"],
        "rss_mb_after_warmup": round(base, 1), "rss_mb_end": round(end, 1),
        "rss_growth_mb": round(end - base, 2), "rss_mb_max": round(max(st["max"], end), 1),
        "ticks": f["ticks"], "scans": f["scans"], "ticks_missed": f["ticks_missed"],
        "ticks_late": f["ticks_late"], "scans_unticked": f["scans_unticked"],
        "ticks_skipped": f["ticks_skipped"], "late_t": f["late_t"], "unticked_t": f["unticked_t"],
        "exceptions": c.get("io_errors", 0) + c.get("tick_errors", 0) + c.get("listener_errors", 0)
        + ac.get("loop_errors", 0) + ac.get("handler_errors", 0),
        "setpoints_received": fence["received"], "setpoints_outside_fence": fence["outside"],
        "outside_examples": fence["examples"], "watchdog": dict(run["app"].watchdog.counts),
        "guidance_timeouts": f["guidance_timeouts"], "fallbacks": f["fallbacks"],
        "datagrams_rejected": f["datagrams_rejected"], "feed_late_scans": f["feed_late_scans"],
        "feed_send_lag_s_max": f["feed_send_lag_s_max"], "latency_ms_median": f["latency_ms_median"],
        "tick_ms_median": f["tick_ms_median"], "clock_slips": f["clock_slips"], "wall_s": f["wall_s"],
        "kept_tick_records": len(run["app"].ticks), "history": run["app"].cfg.history,
        "load_avg_1m_start": round(load0, 2), "load_avg_1m_end": f["load_avg_1m_end"],
    }
    if st["growth"] is not None:
        out["tracemalloc_growth"] = st["growth"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=7200.0, help="mission seconds (default 7200)")
    ap.add_argument("--speedup", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--tracemalloc", type=int, default=0, metavar="N",
                    help="also list the N biggest allocation growths after warm-up (slower)")
    args = ap.parse_args()
    r = soak(args.duration, args.speedup, args.seed, args.tracemalloc)
    for line in r.get("tracemalloc_growth", []):
        print("  " + line)
    print(f"soak {r['mission_s']:.0f} s at {r['achieved_speedup']}x: RSS growth {r['rss_growth_mb']} MB, "
          f"missed {r['ticks_missed']}, exceptions {r['exceptions']}, outside fence {r['setpoints_outside_fence']}, "
          f"load {r['load_avg_1m_start']} -> {r['load_avg_1m_end']}")
    print(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
