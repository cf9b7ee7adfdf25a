"""``pmon``: the Passive Monitor command line.

    pmon check-config [FILE]     validate a scenario (default: the built-in paper scenario)
    pmon simulate [--ticks N]    fly the monitor's core in closed loop on a scenario, no sockets
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from onboard.config import ConfigError, load_scenario


def _check(args) -> int:
    sc = load_scenario(args.scenario)
    print(f"{sc.source}: ok: {len(sc.targets)} targets, {len(sc.obstacles)} obstacles, "
          f"{len(sc.goals)} goal region(s), horizon T={sc.guidance.horizon}, "
          f"{sc.tracking.particles} particles/target")
    return 0


def _simulate(args) -> int:
    from rich.console import Console
    from rich.table import Table

    from onboard.core.bearings import bearing, wrap
    from onboard.core.guidance import GuidanceWorkspace
    from onboard.core.monitor import MonitorSetup, Scan, initial_state, tick

    sc = load_scenario(args.scenario)
    setup = MonitorSetup.from_scenario(sc)
    rng = np.random.default_rng(args.seed)
    truth_rng = np.random.default_rng(args.seed + 1)
    state = initial_state(setup, rng)
    truth = np.array([truth_rng.multivariate_normal(m, setup.initial_cov) for m in setup.initial_means])
    uav = np.array([sc.uav.start_m[0], sc.uav.start_m[1], sc.uav.altitude_m])
    ws = GuidanceWorkspace()
    console = Console()
    errors = []
    for k in range(args.ticks):
        # direction finder: target bearing with p_D and noise, plus Poisson clutter, per channel
        bearings = []
        for j in range(setup.n_targets):
            b = list(truth_rng.uniform(-np.pi, np.pi, truth_rng.poisson(setup.sensor.clutter_rate)))
            if truth_rng.random() < setup.sensor.p_detect:
                b.append(float(wrap(bearing(truth[j], uav) + truth_rng.normal(0, setup.sensor.sigma_rad))))
            bearings.append(np.array(b))
        state, res = tick(setup, state, [Scan(uav, tuple(bearings))], rng, plan_from=uav, workspace=ws)
        err = np.linalg.norm(res.means[:, :2] - truth[:, :2], axis=1)
        errors.append(err)
        console.print(f"t={k:3d}s  uav=({uav[0]:6.1f}, {uav[1]:6.1f})  error per target [m]: "
                      + " ".join(f"{e:6.1f}" for e in err)
                      + f"   tick {res.timings_s['tick'] * 1e3:6.1f} ms")
        # truth: each target follows its own guidance from its true state, with process noise Q
        truth = np.array([p.means[0] for p in res.plans]) + truth_rng.standard_normal(truth.shape) * setup.model.Q_sqrt
        if res.next_position is not None:
            uav = res.next_position
    errors = np.array(errors)
    table = Table(title=f"position error after {args.ticks} ticks (seed {args.seed})")
    for col in ("target", "final [m]", "mean over run [m]"):
        table.add_column(col, justify="right")
    for j, t in enumerate(sc.targets):
        table.add_row(t.name, f"{errors[-1, j]:.1f}", f"{errors[:, j].mean():.1f}")
    console.print(table)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="pmon", description="Passive Monitor")
    sub = ap.add_subparsers(dest="command", required=True)
    c = sub.add_parser("check-config", help="validate a scenario file")
    c.add_argument("scenario", nargs="?", default="paper", help="YAML file or built-in name (default: paper)")
    c.set_defaults(func=_check)
    s = sub.add_parser("simulate", help="closed loop on the core, no sockets (truth, DF model, monitor)")
    s.add_argument("scenario", nargs="?", default="paper")
    s.add_argument("--ticks", type=int, default=30, help="seconds of mission (default 30)")
    s.add_argument("--seed", type=int, default=1)
    s.set_defaults(func=_simulate)
    args = ap.parse_args(argv)
    if getattr(args, "ticks", 1) < 1:
        ap.error("--ticks must be >= 1")
    try:
        return args.func(args)
    except ConfigError as exc:
        print(f"pmon: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
