"""How often the simulated targets' own guidance (P1) finds no plan, over pmon eval's trials.

    python bench/truth_guidance.py [--trials 100] [--seed 2024] [--show TRIAL:TARGET ...] [--trace]
                                   [--set KEY=VALUE ...]

The truth of trial i is the one ``pmon eval paper --trials N --seed S`` flies (same seeds). Each
target re-plans every step; a step without a feasible plan leaves it on its previous plan's
controls (``fallback_previous``), open loop, which no tracker's motion model predicts. Prints
the target-steps by plan status, the steps planned without the obstacle margin (``margin_m`` 0:
noise had carried the target too close to an obstacle, or too fast toward it, to keep it), the
(trial, target) pairs with at least one fallback, and one JSON line. ``--show 82:3``: also the
times (the plan made at t) at which trial 82's T3 had a plan other than ``optimal``; with
``--trace``, every step of each shown pair: the plan's status, QP solves, P1 cost and winding about
each obstacle (``guidance.winding``: + counterclockwise, - clockwise, 0 not rounded), where a
switch of side, or a plan much costlier than the last, shows (docs/TRACKING.md, the tails).
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from collections import Counter  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from itertools import groupby  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import add_set_option, set_label, set_overrides  # noqa: E402
from onboard.config import load_scenario  # noqa: E402
from sim import evaluation as ev  # noqa: E402
from sim.truth import TruthWorld  # noqa: E402
from onboard.core.guidance import winding  # noqa: E402


def trial_statuses(overrides: dict, n_trials: int, seed: int, trial: int) -> list[list[str]]:
    """Per target, the status of its plan at each step of trial ``trial`` (``margin0``: a plan
    without the margin)."""
    cfg = ev.make_config(load_scenario("paper", overrides), n_trials, seed)
    world = TruthWorld.from_scenario(cfg.scenario, ev._rng(cfg.seed, trial, 0))
    out = [[] for _ in range(len(cfg.scenario.targets))]
    for _ in range(cfg.n_ticks - 1):
        world.step()
        for j, plan in enumerate(world.plans):
            margin = getattr(plan, "margin_m", None)  # absent before the field was added
            out[j].append("margin0" if margin == 0.0 else plan.status)
    return out


def pair_trace(overrides: dict, n_trials: int, seed: int, trial: int, target: int) -> list[str]:
    """Per step, target ``target`` (from 1) of trial ``trial``: its position and plan, one line each."""
    cfg = ev.make_config(load_scenario("paper", overrides), n_trials, seed)
    world = TruthWorld.from_scenario(cfg.scenario, ev._rng(cfg.seed, trial, 0))
    out = []
    for k in range(cfg.n_ticks - 1):
        world.step()
        p, x = world.plans[target - 1], world.states[target - 1]
        out.append(f"  t={k:3d}  ({x[0]:6.0f}, {x[1]:6.0f}) m  {p.status:18s} {p.qp_solves:3d} QPs  "
                   f"cost {p.cost:12.0f}  winding {winding(p.faces).tolist()}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--show", action="append", default=[], metavar="TRIAL:TARGET",
                    help="print the times of that pair's non-optimal plans (target from 1, as T1)")
    ap.add_argument("--trace", action="store_true", help="with --show: every step of the pair's plan")
    add_set_option(ap, "guidance.max_qp_solves=40")
    args = ap.parse_args()
    try:
        shows = [tuple(int(v) for v in item.split(":")) for item in args.show]
        if any(len(x) != 2 or not 0 <= x[0] < args.trials or x[1] < 1 for x in shows):
            raise ValueError
    except ValueError:
        ap.error(f"--show takes TRIAL:TARGET, a trial below --trials and a target from 1: {args.show}")
    overrides = set_overrides(ap, args)
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        trials = list(pool.map(trial_statuses, [overrides] * args.trials, [args.trials] * args.trials,
                               [args.seed] * args.trials, range(args.trials)))
    counts = Counter(s for trial in trials for target in trial for s in target)
    steps = sum(counts.values())
    fallback = counts["fallback_previous"] + counts["fallback_coast"]
    pairs = [(i, j) for i, trial in enumerate(trials) for j, target in enumerate(trial)
             if any(s.startswith("fallback") for s in target)]
    n_pairs = sum(len(trial) for trial in trials)
    print(f"paper scenario{set_label(args)}, {args.trials} trials, seed {args.seed}: the targets' own plans")
    print(f"{'status':20s} {'target-steps':>12s} {'share':>8s}")
    for status, n in sorted(counts.items(), key=lambda x: -x[1]):
        print(f"{status:20s} {n:12d} {n / steps:8.2%}")
    print(f"(trial, target) pairs with a fallback: {len(pairs)} of {n_pairs}")
    for trial, target in shows:
        if target > len(trials[trial]):
            ap.error(f"--show {trial}:{target}: the scenario has {len(trials[trial])} targets")
        runs, k = [], 0
        for status, group in groupby(trials[trial][target - 1]):
            e = k + len(list(group)) - 1
            if status != "optimal":
                runs.append(f"{status} at t = {k}" + (f"-{e} s" if e > k else " s"))
            k = e + 1
        print(f"trial {trial} T{target}: " + ("; ".join(runs) or "optimal at every step"))
        if args.trace:
            print("\n".join(pair_trace(overrides, args.trials, args.seed, trial, target)))
    print(json.dumps({"trials": args.trials, "target_steps": steps, "fallback_steps": fallback,
                      "margin0_steps": counts["margin0"], "pairs_with_fallback": len(pairs),
                      "pairs": n_pairs, "statuses": dict(counts)}))


if __name__ == "__main__":
    main()
