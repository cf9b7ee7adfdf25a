"""How often the simulated targets' own guidance (P1) finds no plan, over pmon eval's trials.

    python -m bench.truth_guidance [--trials 100] [--seed 2024] [--show TRIAL:TARGET ...] [--trace]
                                   [--per-trial CSV ...] [--set KEY=VALUE ...]

The truth of trial i is the one ``pmon eval paper --trials N --seed S`` flies (same seeds). Each
target re-plans every step; a step without a feasible plan leaves it on its previous plan's
controls (``fallback_previous``), open loop, which no tracker's motion model predicts. Prints
the target-steps by plan status, the (trial, target) pairs whose plan's P1 cost ever jumps above 1.3
times the step before's (and above 2e5), the steps planned without the obstacle margin (``margin_m`` 0:
noise had carried the target too close to an obstacle, or too fast toward it, to keep it), the
(trial, target) pairs with at least one fallback, the wall stops (a target held at an obstacle
with zero velocity for a step: sim/truth/world.py) and one JSON line; ``--per-trial CSV`` (a ``pmon
eval`` run of the same trials): per method, its error on the trials with a wall stop and on the
others. ``--show 82:3``: also the
times (the plan made at t) at which trial 82's T3 had a plan other than ``optimal``; with
``--trace``, every step of each shown pair: the plan's status, QP solves, P1 cost and winding about
each obstacle (``guidance.winding``: + counterclockwise, - clockwise, 0 not rounded), where a
switch of side, or a plan much costlier than the last, shows (docs/LOG.md, the tails traced).
"""
from __future__ import annotations

import os

from sim.evaluation.workers import one_blas_thread  # no numpy import

one_blas_thread()  # before numpy loads: one core's figures

import argparse
import json
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from itertools import groupby

import numpy as np

from bench import add_set_option, set_label, set_overrides
from onboard.config import load_scenario
from sim.evaluation import trials as ev
from sim.truth.world import TruthWorld
from sim.evaluation.truth_plans import JUMP, JUMP_FLOOR, trial_statuses
from onboard.core.guidance.predictor import winding


def _depth(obstacles, xy: np.ndarray) -> float:
    """How deep (m) the ground point xy is inside the deepest obstacle's footprint (<= 0: outside)."""
    if not len(obstacles):
        return -np.inf
    n, b, _, _ = obstacles.lateral()  # (K, 4, 2), (K, 4)
    return float(-(np.einsum("kfd,d->kf", n, xy) - b).max(axis=1).min())


def pair_trace(overrides: dict, n_trials: int, seed: int, trial: int, target: int) -> list[str]:
    """Per step, target ``target`` (from 1) of trial ``trial``: its position and plan, one line each."""
    cfg = ev.make_config(load_scenario("paper", overrides), n_trials, seed)
    world = TruthWorld.from_scenario(cfg.scenario, ev._rng(cfg.seed, trial, 0))
    out = []
    j = target - 1
    for k in range(cfg.n_ticks - 1):
        held = world.stuck_steps[j]
        world.step()
        p, x = world.plans[j], world.states[j]
        # the plan made at t = k from the state of scan k; the state shown is scan k + 1's
        gap = _depth(world.obstacles, p.means[0, :2])
        out.append(f"  t={k:3d}  ({x[0]:6.1f}, {x[1]:6.1f}) m  ({x[3]:5.1f}, {x[4]:5.1f}) m/s  {p.status:18s} "
                   f"{p.qp_solves:3d} QPs  cost {p.cost:12.0f}  margin {p.margin_m}  next mean "
                   f"{'%.1f m inside' % gap if gap > 0 else 'clear'}  winding {winding(p.faces).tolist()}"
                   + ("  HELD at the wall" if world.stuck_steps[j] > held else ""))
    return out


def read_per_trial(path: str) -> list[tuple[int, str, float]]:
    """(trial, method, window RMSE m) rows of a ``pmon eval`` per_trial.csv; ValueError naming
    what is wrong (the file, a missing column, a bad value)."""
    import csv

    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            missing = {"trial", "method", "rmse_window_m"} - set(reader.fieldnames or ())
            if missing:
                raise ValueError(f"{path}: not a pmon eval per_trial.csv (no column {', '.join(sorted(missing))})")
            rows = []
            for n, r in enumerate(reader, 2):
                try:
                    rows.append((int(r["trial"]), r["method"], float(r["rmse_window_m"])))
                except (TypeError, ValueError):
                    raise ValueError(f"{path}, line {n}: trial {r['trial']!r} or rmse_window_m "
                                     f"{r['rmse_window_m']!r} is not a number") from None
    except OSError as exc:
        raise ValueError(f"{path}: {exc.strerror}") from None
    if not rows:
        raise ValueError(f"{path}: no rows")
    return rows


def wall_stop_rows(path: str, rows: list[tuple[int, str, float]], stopped: set[int], n_trials: int) -> str:
    """Lines: per method of a per_trial.csv's rows, the RMS of the window RMSE over the trials in
    ``stopped`` and over the other trials below ``n_trials``."""
    rows = [r for r in rows if r[0] < n_trials]
    lines = [f"{path}: RMS of the window RMSE, trials with a wall stop / the others [m]"]
    for method in sorted({m for _, m, _ in rows}):
        a = np.array([x for i, m, x in rows if m == method and i in stopped])
        b = np.array([x for i, m, x in rows if m == method and i not in stopped])
        rms = [f"{np.sqrt(np.mean(x ** 2)):.1f} ({len(x)})" if len(x) else "- (0)" for x in (a, b)]
        lines.append(f"  {method:20s} {rms[0]:>12s} / {rms[1]}")
    return "\n".join(lines)


def _not_optimal(statuses) -> list[str]:
    """A target's runs of steps whose plan was not optimal: "status at t = a-b s" each."""
    runs, k = [], 0
    for status, group in groupby(statuses):
        e = k + len(list(group)) - 1
        if status != "optimal":
            runs.append(f"{status} at t = {k}" + (f"-{e} s" if e > k else " s"))
        k = e + 1
    return runs


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--show", action="append", default=[], metavar="TRIAL:TARGET",
                    help="print the times of that pair's non-optimal plans (target from 1, as T1)")
    ap.add_argument("--trace", action="store_true", help="with --show: every step of the pair's plan")
    ap.add_argument("--per-trial", metavar="CSV", action="append", default=[],
                    help="a pmon eval per_trial.csv of these trials: per method, the RMS of the window RMSE "
                         "over the trials with a wall stop and over the others")
    add_set_option(ap, "guidance.max_qp_solves=40")
    return ap


def main() -> None:
    ap = _parser()
    args = ap.parse_args()
    try:
        shows = [tuple(int(v) for v in item.split(":")) for item in args.show]
        if any(len(x) != 2 or not 0 <= x[0] < args.trials or x[1] < 1 for x in shows):
            raise ValueError
    except ValueError:
        ap.error(f"--show takes TRIAL:TARGET, a trial below --trials and a target from 1: {args.show}")
    overrides = set_overrides(ap, args)
    try:
        per_trial = {path: read_per_trial(path) for path in args.per_trial}
    except ValueError as exc:
        ap.error(f"--per-trial: {exc}")
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        runs = list(pool.map(trial_statuses, [overrides] * args.trials, [args.trials] * args.trials,
                             [args.seed] * args.trials, range(args.trials)))
    trials = [r[0] for r in runs]
    stops = {i: r[2] for i, r in enumerate(runs) if r[2]}
    jumps = [(i, j) for i, r in enumerate(runs) for j, jumped in enumerate(r[1]) if jumped]
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
    print(f"(trial, target) pairs whose plan's cost jumps above {JUMP:g}x the step before's (and {JUMP_FLOOR:g}): "
          f"{len(jumps)} of {n_pairs}, in {len({i for i, _ in jumps})} trials")
    n_stops = sum(len(v) for v in stops.values())
    print(f"wall stops (a target held at an obstacle with zero velocity for a step): {n_stops} in "
          f"{len(stops)} of {args.trials} trials" + (": " if stops else "")
          + ", ".join(f"{i} T{j} at scan {k}" for i, v in stops.items() for k, j in v))
    for path, rows in per_trial.items():
        print(wall_stop_rows(path, rows, set(stops), args.trials))
    for trial, target in shows:
        if target > len(trials[trial]):
            ap.error(f"--show {trial}:{target}: the scenario has {len(trials[trial])} targets")
        print(f"trial {trial} T{target}: " + ("; ".join(_not_optimal(trials[trial][target - 1]))
                                              or "optimal at every step"))
        if args.trace:
            print("\n".join(pair_trace(overrides, args.trials, args.seed, trial, target)))
    print(json.dumps({"trials": args.trials, "target_steps": steps, "fallback_steps": fallback,
                      "margin0_steps": counts["margin0"], "pairs_with_fallback": len(pairs),
                      "pairs_with_cost_jump": len(jumps), "wall_stops": n_stops, "trials_with_wall_stop": len(stops), "trials_with_cost_jump": len({i for i, _ in jumps}),
                      "pairs": n_pairs, "statuses": dict(counts)}))


if __name__ == "__main__":
    main()
