"""Benchmarks: each prints the figures the docs quote. Shared here: the ``--set`` option, the
evaluation with a patched planner (``patched_eval_parser``, ``run_patched_eval``)."""
from __future__ import annotations

import argparse


def add_set_option(ap: argparse.ArgumentParser, example: str = "tracking.plan_steering=true") -> None:
    """``--set KEY=VALUE`` (repeatable): a scenario value changed for this run, VALUE read as YAML."""
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help=f"change a scenario value, e.g. {example}")


def set_overrides(ap: argparse.ArgumentParser, args: argparse.Namespace) -> dict:
    """The ``--set`` items as ``load_scenario`` overrides; a bad item exits 2 naming it."""
    from onboard.config import ConfigError, parse_overrides

    try:
        return parse_overrides(args.set)
    except ConfigError as exc:
        ap.error(str(exc))


def set_label(args: argparse.Namespace) -> str:
    """The run's ``--set`` items as they were given, for the benches' headings."""
    return "".join(f" --set {x}" for x in args.set)


def patched_eval_parser(doc: str, methods_help: str) -> argparse.ArgumentParser:
    """The options of a bench that runs ``pmon eval paper`` with its planner patched
    (bench/oracle_routes.py, route_variants.py): --out, --trials, --seed, --methods, --workers,
    --set; the bench adds its own."""
    from onboard.argcheck import SEED, integer

    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="directory for pmon eval's files")
    ap.add_argument("--trials", type=integer(1, 100_000), default=100)
    ap.add_argument("--seed", type=SEED, default=2024)
    ap.add_argument("--methods", default="flight@stock", help=methods_help)
    ap.add_argument("--workers", type=integer(1, 1024), default=2)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="as pmon eval's --set")
    return ap


def run_patched_eval(a: argparse.Namespace) -> int:
    """``pmon eval paper`` with the options of ``patched_eval_parser`` (no figures, quiet)."""
    from onboard.cli import main as pmon

    extra = [x for kv in a.set for x in ("--set", kv)]
    return pmon(["eval", "paper", "--trials", str(a.trials), "--seed", str(a.seed), "--methods", a.methods,
                 "--workers", str(a.workers), "--no-figures", "--quiet", "--out", a.out, *extra])


def closed_loop(setup, ticks: int, seed: int, start_xy=(150.0, 200.0), timer=None):
    """The core's closed loop without sockets (bench/tick.py, planner.py, route_score.py): each
    target's truth follows its own plan, the DF's bearings carry noise, and the UAV, starting at
    start_xy (m, ENU), goes where the planner says, with the velocity it says for the vehicle
    motion. Yields (k, state, result, uav) for k = 0..ticks-1: the state and TickResult after
    tick k, and where that tick's scan was taken (x, y, z). ``timer``: the tick's clock (default
    ``time.perf_counter``; ``time.process_time`` counts this process's CPU only)."""
    import time

    import numpy as np

    from onboard.core.bearings import bearing, wrap
    from onboard.core.guidance import GuidanceWorkspace
    from onboard.core.monitor import Scan, initial_state, tick

    rng = np.random.default_rng(seed)
    state = initial_state(setup, rng)
    truth = setup.initial_means.copy()
    uav = np.array([*start_xy, setup.grid.altitude_m], float)
    vel = np.zeros(2)
    ws = GuidanceWorkspace()
    for k in range(ticks):
        bearings = tuple(np.array([float(wrap(bearing(truth[j], uav) + rng.normal(0, setup.sensor.sigma_rad)))])
                         for j in range(setup.n_targets))
        state, res = tick(setup, state, [Scan(uav, bearings)], rng, plan_from=uav, workspace=ws, uav_velocity=vel,
                          timer=timer or time.perf_counter)
        yield k, state, res, uav
        truth = np.array([p.means[0] for p in res.plans])
        p = res.planning
        if p is not None and p.index is not None:
            uav = p.position
            vel = p.velocities[p.index] if p.velocities is not None else np.zeros(2)


def tick_timings(setup, ticks: int, seed: int, timer=None) -> dict:
    """ms per tick of ``closed_loop`` from its defaults, split as TickResult.timings_s (tick,
    tracking, guidance, planning): arrays over the ticks after the first, which includes the
    guidance's first exploratory face search."""
    import numpy as np

    out = {k: [] for k in ("tick", "tracking", "guidance", "planning")}
    for _, _, res, _ in closed_loop(setup, ticks, seed, timer=timer):
        for k in out:
            out[k].append(res.timings_s[k] * 1e3)
    return {k: np.array(v[1:]) for k, v in out.items()}
