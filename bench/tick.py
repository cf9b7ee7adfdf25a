"""One tick of the paper scenario, split into tracking / guidance / planning; and a large case.

    python -m bench.tick [--ticks 30] [--large-ticks 8] [--set tracking.plan_steering=true ...]

Prints a table and, last, one JSON line of figures (milliseconds, medians over ticks after the
first, which includes OSQP setup and the exploratory face search).
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from bench import add_set_option, set_label, set_overrides
from sim.evaluation.closed_loop import tick_timings
from onboard.config import load_scenario
from onboard.core.monitor import MonitorSetup
from onboard.core.obstacles import Obstacles
from onboard.policy import with_policy


def large_setup(base: MonitorSetup, rng: np.random.Generator) -> MonitorSetup:
    """20 targets and 20 obstacles in the same 1 km area."""
    boxes = []
    while len(boxes) < 20:
        c = rng.uniform(100, 900, 2)
        boxes.append(SimpleNamespace(center_m=(c[0], c[1], 15.0), size_m=(40.0, 40.0, 30.0),
                                     yaw_rad=float(rng.uniform(0, np.pi))))
    obstacles = Obstacles.from_boxes(boxes)
    inflated = obstacles.inflate(base.guidance.obstacle_margin_m + 5)
    means, goals = [], []
    while len(means) < 20:
        p = np.r_[rng.uniform(50, 950, 2), 0.0]
        if not inflated.contains(p).any():
            means.append(np.r_[p, 0, 0, 0])
    while len(goals) < 20:
        g = np.r_[rng.uniform(50, 950, 2), 0.0]
        if not inflated.contains(g).any():
            goals.append(g)
    return replace(base, obstacles=obstacles, uav_obstacles=obstacles.inflate(10.0),
                   initial_means=np.array(means), goals=np.array(goals))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ticks", type=int, default=30)
    ap.add_argument("--large-ticks", type=int, default=8)
    ap.add_argument("--seed", type=int, default=1)
    add_set_option(ap)
    args = ap.parse_args()
    sc = with_policy(load_scenario("paper", set_overrides(ap, args)), "paper")  # the paper's method
    base = MonitorSetup.from_scenario(sc)
    paper = tick_timings(base, args.ticks, args.seed)
    large = tick_timings(large_setup(base, np.random.default_rng(args.seed)), args.large_ticks, args.seed)
    print(f"paper scenario{set_label(args)}: 4 targets, {len(base.obstacles)} obstacles, "
          f"T={base.guidance.horizon}, "
          f"{base.n_particles} particles/target, {args.ticks} ticks")
    for k, v in paper.items():
        print(f"  {k:9s} median {np.median(v):8.1f} ms   p95 {np.percentile(v, 95):8.1f} ms")
    print(f"large case: 20 targets, 20 obstacles, {args.large_ticks} ticks")
    for k, v in large.items():
        print(f"  {k:9s} median {np.median(v):8.1f} ms")
    print(json.dumps({
        "tick_ms_median": round(float(np.median(paper["tick"])), 2),
        "tick_ms_p95": round(float(np.percentile(paper["tick"], 95)), 2),
        "tracking_ms_median": round(float(np.median(paper["tracking"])), 2),
        "guidance_ms_median": round(float(np.median(paper["guidance"])), 2),
        "planning_ms_median": round(float(np.median(paper["planning"])), 2),
        "large_tick_ms_median": round(float(np.median(large["tick"])), 2),
    }))


if __name__ == "__main__":
    main()
