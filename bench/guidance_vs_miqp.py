"""Our P1 solver against the exact MIQP (SCIP) of the same problem, on random instances.

    python -m bench.guidance_vs_miqp [--instances 100] [--horizon 10] [--seed 11]

Each instance: 1-3 rotated cuboids, a start and a goal 120-180 m ahead behind them (sim/evaluation/miqp_reference.py
``random_instance``), the paper's weights and limits, horizon T. Ours runs cold (no previous plan,
as on a target's first tick). The exact solve gets 60 s. Prints a line per instance and, last,
one JSON line: ``instances`` (compared: the exact solver found a solution), ``within_1pct_fraction``,
``cost_ratio_median`` (ours / exact), ``cost_ratio_max``, ``infeasible_where_exact_found``,
``speedup_median`` (exact time / our time), ``ours_ms_median``, ``exact_ms_median``.
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np

from sim.evaluation.miqp_reference import random_instance, solve_p1_exact
from onboard.config import load_scenario
from onboard.core.dynamics import MotionModel
from onboard.core.guidance.predictor import GuidanceParams, GuidanceWorkspace, Solver, plan_guidance


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--instances", type=int, default=100)
    ap.add_argument("--horizon", type=int, default=10)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--time-limit", type=float, default=60.0, help="exact solver's limit per instance (s)")
    args = ap.parse_args()
    sc = load_scenario("paper")
    d = sc.dynamics
    model = MotionModel.create(d.dt_s, d.friction, d.mass_kg, d.process_noise_diag)
    params = replace(GuidanceParams.from_config(sc.guidance), horizon=args.horizon)
    rng = np.random.default_rng(args.seed)
    ws = GuidanceWorkspace()
    plan_guidance(model, params, *random_instance(np.random.default_rng(0), params.obstacle_margin_m, True),
                  solver=Solver(ws))  # one-off matrix set-up, as in flight before the first tick
    ratios, ours_ms, exact_ms, infeasible, skipped = [], [], [], 0, 0
    for i in range(args.instances):
        obs, mean0, goal = random_instance(rng, params.obstacle_margin_m, blocked=True)
        ours = plan_guidance(model, params, obs, mean0, goal, solver=Solver(ws))
        ref = solve_p1_exact(model, params, obs, mean0, goal, time_limit_s=args.time_limit)
        if not np.isfinite(ref["cost"]):
            skipped += 1
            print(f"{i:4d}  exact: no solution ({ref['status']}); ours: {ours.status}, margin {ours.margin_m} m")
            continue
        ours_ms.append(ours.solve_time_s * 1e3)
        exact_ms.append(ref["time_s"] * 1e3)
        if not ours.feasible or ours.margin_m != params.obstacle_margin_m:  # a plan inside the margin: none
            infeasible += 1
            ratios.append(np.inf)
        else:
            ratios.append(ours.cost / ref["cost"])
        print(f"{i:4d}  obstacles {len(obs)}  ours {ours.cost:12.1f} ({ours.status}, {ours.qp_solves} QPs, "
              f"{ours_ms[-1]:6.1f} ms)  exact {ref['cost']:12.1f} ({ref['status']}, {exact_ms[-1]:8.1f} ms)  "
              f"ratio {ratios[-1]:.5f}")
    ratios, ours_ms, exact_ms = np.array(ratios), np.array(ours_ms), np.array(exact_ms)
    print(json.dumps({
        "instances": int(len(ratios)),
        "exact_without_solution": skipped,
        "horizon": args.horizon,
        "within_1pct_fraction": round(float(np.mean(ratios <= 1.01)), 4),
        "cost_ratio_median": round(float(np.median(ratios)), 6),
        "cost_ratio_max": round(float(np.max(ratios)), 6),
        "infeasible_where_exact_found": infeasible,
        "speedup_median": round(float(np.median(exact_ms / ours_ms)), 1),
        "ours_ms_median": round(float(np.median(ours_ms)), 2),
        "exact_ms_median": round(float(np.median(exact_ms)), 1),
    }))


if __name__ == "__main__":
    main()
