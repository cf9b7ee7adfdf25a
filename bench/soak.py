"""Soak: a long accelerated mission against the mock autopilot; memory, misses, errors, fence.

    python bench/soak.py [--duration 7200] [--speedup 5]

Flies like bench/latency.py (mock autopilot + app in this process, the DF feed as a process)
and prints: RSS growth of this process (the app's; measured from the end of the first 10 % of
the mission, after warm-up, to the end), ticks missed (late, skipped, unticked; see
bench/latency.py), exceptions (app io/tick errors, mock loop/handler errors), and setpoints
the AUTOPILOT received outside the fence (area, altitude band PMON_ALT_MIN..MAX, obstacles
inflated by the UAV margin), checked independently of the app. Issue 7's figure is
--duration 7200 (2 h of mission; 24 min of wall time at 5x). Last line: JSON figures.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import latency  # noqa: E402
from onboard.config import load_scenario  # noqa: E402
from onboard.core.obstacles import Obstacles  # noqa: E402


def rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def soak(duration: float, speedup: float, seed: int = 1) -> dict:
    sc = load_scenario("paper")
    lo, hi = np.array(sc.area.min_m), np.array(sc.area.max_m)
    inflated = Obstacles.from_boxes(sc.obstacles).inflate(sc.uav.obstacle_margin_m)
    outside: list = []
    samples: list[tuple[int, float]] = []
    state = {"app": None}

    def check(msg):  # mock home = mission origin: local NED = (north, east, -up)
        p = np.array([msg.y, msg.x, -msg.z])
        app = state["app"]
        band = (app.params["PMON_ALT_MIN"], app.params["PMON_ALT_MAX"]) if app else (0.0, 1e9)
        if np.any(p < lo) or np.any(p > hi) or not band[0] <= p[2] <= band[1] \
                or (len(inflated) and inflated.contains(p[None]).any()):
            outside.append(p.round(2).tolist())

    def on_app(app):
        state["app"] = app
        samples.append((app.counters.get("ticks", 0), rss_mb()))

    run = latency.fly(duration, speedup, seed, cfg_extra={"history": 2000}, on_app=on_app, on_setpoint=check)
    f = latency.figures(run, duration, speedup)
    n = len(samples)
    base = samples[max(n // 10, 0)][1] if samples else float("nan")
    end = samples[-1][1] if samples else float("nan")
    c, ac = run["app"].counters, run["ap_counters"]
    return {
        "mission_s": duration, "speedup": speedup, "achieved_speedup": f["achieved_speedup"],
        "rss_mb_after_warmup": round(base, 1), "rss_mb_end": round(end, 1),
        "rss_growth_mb": round(end - base, 2), "rss_mb_max": round(max(r for _, r in samples), 1) if samples else None,
        "ticks": f["ticks"], "ticks_missed": f["ticks_missed"], "ticks_late": f["ticks_late"],
        "ticks_skipped": f["ticks_skipped"], "scans_unticked": f["scans_unticked"],
        "exceptions": c.get("io_errors", 0) + c.get("tick_errors", 0) + ac.get("loop_errors", 0)
        + ac.get("handler_errors", 0),
        "setpoints_received": len(run["rx"]), "setpoints_outside_fence": len(outside),
        "outside_examples": outside[:5], "watchdog": dict(run["app"].watchdog),
        "guidance_timeouts": f["guidance_timeouts"], "fallbacks": f["fallbacks"],
        "datagrams_rejected": f["datagrams_rejected"], "latency_ms_median": f["latency_ms_median"],
        "tick_ms_median": f["tick_ms_median"], "wall_s": f["wall_s"],
        "kept_tick_records": len(run["app"].ticks),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=7200.0, help="mission seconds (default 7200)")
    ap.add_argument("--speedup", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    r = soak(args.duration, args.speedup, args.seed)
    print(f"soak {r['mission_s']:.0f} s at {r['achieved_speedup']}x: RSS growth {r['rss_growth_mb']} MB, "
          f"missed {r['ticks_missed']}, exceptions {r['exceptions']}, outside fence {r['setpoints_outside_fence']}")
    print(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
