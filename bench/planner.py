"""Tick time with each UAV planner on the paper scenario (or others), on one core.

    python -m bench.planner [--ticks 60] [--seed 1 | --seeds 1,2,3] [--figure docs/planner_tick.png]
                            [--cases greedy/jump,lookahead/jump,greedy/vehicle,lookahead/vehicle,flight,...]
                            [--clock wall|cpu] [--repeat 1] [--set tracking.plan_steering=true ...]
                            [--scenarios paper,config/scale_8x10.yaml]

Closed loop on the core alone (as bench/tick.py): the targets follow their own plans, the DF
bearings carry noise, the UAV goes where the planner says (and, for the vehicle motion, with
the velocity it says). One BLAS thread unless OPENBLAS_NUM_THREADS says otherwise (set before
numpy loads), so the figures are one core's; the header says the count and the CPU and packages.
Prints a table per planner x motion (medians and p95 over ticks after the first, which includes
the guidance's exploratory face search), writes a figure of the tick-time distributions, and
ends with one JSON line. The case ``flight`` is the flight default (onboard/policy.py
POLICIES["flight"], with ArduCopter's stock WPNAV_SPEED / WPNAV_ACCEL as the app reads them,
capped as the policy says), the scenario's ``--set`` on top; ``flight~free`` is it with the default
filter (the free steering: ``plan_steering``, ``plan_sides`` off), ``flight~sides`` with the
side-aware filter (both on), whatever the policy says; ``flight~nointent`` is the flight
default without the motion modes (``tracking.intent`` off: the filter before intent tracking).

On a shared machine: ``--clock cpu`` times the ticks by this process's CPU time (time.process_time)
instead of the wall clock, and ``--repeat R`` flies each case's closed loop R times, the cases in
turn, and keeps each tick's least time (the loops are deterministic: tick k does the same work
every time). ``--seeds`` pools the ticks of several closed loops.

``--scenarios``: the scenarios to time (built-in names or files, comma-separated; default
``paper``), the UAV starting where each says; each gets its table, and each repetition runs every
scenario's cases in turn, so a ratio between them is of one run on one machine's load (issue 47:
``config/scale_8x10.yaml``, eight targets and ten obstacles, against the paper's four and four).
With more than one, the JSON line maps each scenario's name to its table's entries.
"""
from __future__ import annotations

import os

from sim.evaluation.workers import one_blas_thread  # no numpy import

one_blas_thread()  # before numpy loads: one core's figures

import argparse
import json
import time

import numpy as np

from bench import add_set_option, set_label, set_overrides
from sim.evaluation.closed_loop import tick_timings
from onboard.config import ConfigError, load_scenario, override
from onboard.core.monitor import MonitorSetup
from onboard.policy import vehicle_motion, with_policy
from sim.evaluation.numerics import numerics_description
from sim.mock.multicopter import VehicleLimits

CASES = ("greedy/jump", "lookahead/jump", "greedy/vehicle", "lookahead/vehicle", "flight", "flight~free",
         "flight~sides", "flight~nointent")
# variants of the flight default: its filter as declared, the paper's free steering (plan_steering
# and plan_sides off), the side-aware filter (both on)
FLIGHT_FILTERS = {"flight": {}, "flight~nointent": {"tracking.intent": False},
                  "flight~free": {"tracking.plan_steering": False, "tracking.plan_sides": False},
                  "flight~sides": {"tracking.plan_steering": True, "tracking.plan_sides": True}}


def setup_for(sc, case: str) -> MonitorSetup:
    if case in FLIGHT_FILTERS:
        fl = override(with_policy(sc, "flight"), FLIGHT_FILTERS[case])
        stock = VehicleLimits()  # ArduCopter's stock WPNAV_SPEED, WPNAV_ACCEL, PSC_JERK_XY
        m = vehicle_motion(fl.planning, stock.speed_xy, stock.accel_xy, stock.jerk_xy_max())
        return MonitorSetup.from_scenario(override(fl, {"planning.speed_max_mps": m.speed_max_mps,
                                                        "planning.accel_max_mps2": m.accel_max_mps2,
                                                        "planning.jerk_max_mps3": m.jerk_max_mps3}))
    planner, motion = case.split("/")  # the paper's method with this planner and motion
    return MonitorSetup.from_scenario(override(with_policy(sc, "paper"),
                                               {"planning.planner": planner, "planning.motion": motion}))


def timings(sc, cases: list[str], ticks: int, seeds: list[int], repeat: int, timer) -> dict:
    """Per case, ms per tick (tick, tracking, guidance, planning) over the seeds' closed loops: each
    tick's least over ``repeat`` runs, the cases run in turn within each repetition."""
    return scenario_timings([sc], cases, ticks, seeds, repeat, timer)[0]


def scenario_timings(scs: list, cases: list[str], ticks: int, seeds: list[int], repeat: int, timer) -> list[dict]:
    """``timings`` of each scenario, the UAV starting at the scenario's ``uav.start_m``; each
    repetition runs every scenario's cases in turn, so the machine's load falls on all of them."""
    runs: list[dict[str, list[dict]]] = [{c: [] for c in cases} for _ in scs]
    for _ in range(repeat):
        for sc, run in zip(scs, runs):
            start = tuple(sc.uav.start_m[:2])
            for case in cases:
                setup = setup_for(sc, case)
                per_seed = [tick_timings(setup, ticks, seed, timer=timer, start_xy=start) for seed in seeds]
                run[case].append({k: np.concatenate([t[k] for t in per_seed]) for k in per_seed[0]})
    return [{c: {k: np.min([r[k] for r in rs], axis=0) for k in rs[0]} for c, rs in run.items()} for run in runs]


def load_scenarios(ap: argparse.ArgumentParser, text: str, overrides: dict) -> list:
    """The ``--scenarios`` list (built-in names or files), each with the ``--set`` overrides; a
    bad item (no such file, not a valid scenario, a name twice) exits 2 with one line."""
    items = [x.strip() for x in text.split(",") if x.strip()]
    if not items:
        ap.error("--scenarios is empty")
    scs = []
    for item in items:
        try:
            sc = load_scenario(item, overrides)
        except ConfigError as exc:
            ap.error(f"--scenarios: {' '.join(str(exc).split())}")
        if any(o.name == sc.name for o in scs):
            ap.error(f"--scenarios: two scenarios named {sc.name!r}")
        scs.append(sc)
    return scs


def parse_args(argv=None) -> tuple[argparse.Namespace, list[str], list[int], list]:
    """The options, the cases, the seeds and the scenarios; a bad one exits 2 naming it."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ticks", type=int, default=60)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--seeds", default=None, help="comma-separated seeds, their ticks pooled (instead of --seed)")
    ap.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                    help="time ticks by the wall clock or by this process's CPU time")
    ap.add_argument("--repeat", type=int, default=1, help="fly each case this many times; each tick's least time")
    ap.add_argument("--figure", default="",
                    help="where to write the figure (default: none, so a run writes nothing in the repository; "
                         "docs/planner_tick.png is the one docs/LOG.md shows)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--scenarios", default="paper",
                    help="comma-separated scenarios to time in one run, built-in names or files "
                         "(e.g. paper,config/scale_8x10.yaml)")
    add_set_option(ap)
    args = ap.parse_args(argv)
    cases = [c for c in args.cases.split(",") if c]
    bad = [c for c in cases if c not in CASES]
    if bad or not cases:
        ap.error(f"--cases: unknown case {bad[0]!r}" if bad else "--cases is empty")
    try:
        seeds = [int(x) for x in args.seeds.split(",")] if args.seeds else [args.seed]
    except ValueError:
        ap.error(f"--seeds: not a comma-separated list of integers: {args.seeds!r}")
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    return args, cases, seeds, load_scenarios(ap, args.scenarios, set_overrides(ap, args))


def print_table(results: dict) -> None:
    print(f"{'planner/motion':20s} {'tick med':>9s} {'tick p95':>9s} {'planning med':>13s} {'planning p95':>13s}")
    for name, r in results.items():
        print(f"{name:20s} {np.median(r['tick']):9.1f} {np.percentile(r['tick'], 95):9.1f} "
              f"{np.median(r['planning']):13.1f} {np.percentile(r['planning'], 95):13.1f}")


def write_figure(path: str, results: dict, where: str) -> None:
    """Box plots of the tick and planning times of ``results`` ({label: timings}) at ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(1, 2, figsize=(11, 4))
    names = list(results)
    for ax, key in zip(axs, ("tick", "planning")):
        ax.boxplot([results[n][key] for n in names], showfliers=True)
        ax.set_xticks(range(1, len(names) + 1), names, rotation=15)
        ax.set_ylabel(f"{key} time [ms]")
        ax.set_title(f"{key} per tick ({where}, one core)")
        if key == "tick":
            ax.axhline(250.0, color="tab:red", ls="--", lw=1, label="budget 250 ms")
            ax.axhline(150.0, color="tab:orange", ls=":", lw=1, label="flight default target 150 ms")
            ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def summary(results: dict, clock: str) -> dict:
    """A table's entries as the JSON line has them."""
    return {name: {"clock": clock, "tick_ms_median": round(float(np.median(r["tick"])), 2),
                   "tick_ms_p95": round(float(np.percentile(r["tick"], 95)), 2),
                   "planning_ms_median": round(float(np.median(r["planning"])), 2)}
            for name, r in results.items()}


def main(argv=None) -> None:
    args, cases, seeds, scs = parse_args(argv)
    timer = time.process_time if args.clock == "cpu" else None
    per_sc = scenario_timings(scs, cases, args.ticks, seeds, args.repeat, timer)
    names = [sc.name for sc in scs]
    where = f"{' and '.join(names)} scenario{'s' if len(scs) > 1 else ''}"
    print(f"{where}{set_label(args)}, {args.ticks} ticks x seeds {','.join(map(str, seeds))}, "
          f"{args.clock} clock, least of {args.repeat} run(s) per tick, lookahead over "
          f"{scs[0].planning.lookahead_steps} ticks (flight: {with_policy(scs[0], 'flight').planning.lookahead_steps}), "
          f"BLAS threads: {os.environ['OPENBLAS_NUM_THREADS']}")
    print(f"numerics: {numerics_description()}")
    for sc, results in zip(scs, per_sc):
        if len(scs) > 1:
            print(f"\n{sc.name} ({sc.source}): {len(sc.targets)} targets, {len(sc.obstacles)} obstacles")
        print_table(results)
    if args.figure:
        flat = per_sc[0] if len(scs) == 1 else {f"{n}:{c}": r for n, res in zip(names, per_sc) for c, r in res.items()}
        write_figure(args.figure, flat, where)
    if len(scs) == 1:
        print(json.dumps(summary(per_sc[0], args.clock)))
    else:
        print(json.dumps({n: summary(res, args.clock) for n, res in zip(names, per_sc)}))


if __name__ == "__main__":
    main()
