"""``pmon``: the Passive Monitor command line.

    pmon check-config [FILE]     validate a scenario (default: the built-in paper scenario)
    pmon simulate [--ticks N]    fly the monitor's core in closed loop on a scenario, no sockets
    pmon eval [--trials N] ...   Monte Carlo evaluation against baselines (docs/RESULTS.md)
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from onboard.argcheck import OUT_DIR, SEED, OneLineParser, integer
from onboard.config import ConfigError, load_scenario, parse_overrides


def _check(args) -> int:
    sc = load_scenario(args.scenario)
    print(f"{sc.source}: ok: {len(sc.targets)} targets, {len(sc.obstacles)} obstacles, "
          f"{len(sc.goals)} goal region(s), horizon T={sc.guidance.horizon}, "
          f"{sc.tracking.particles} particles/target")
    return 0


def _simulate(args) -> int:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from onboard.core.guidance import GuidanceWorkspace
    from onboard.core.monitor import MonitorSetup, Scan, initial_state, tick
    from sim.sensors import DirectionFinder, df_scan
    from sim.truth import TruthWorld

    sc = load_scenario(args.scenario)
    setup = MonitorSetup.from_scenario(sc)
    rng = np.random.default_rng(args.seed)
    truth_rng = np.random.default_rng(args.seed + 1)
    state = initial_state(setup, rng)
    world = TruthWorld.from_scenario(sc, truth_rng)
    truth = world.states
    df = DirectionFinder.from_config(sc.sensor)
    uav = np.array([sc.uav.start_m[0], sc.uav.start_m[1], sc.uav.altitude_m])
    ws = GuidanceWorkspace()
    console = Console()
    errors = []
    for k in range(args.ticks):
        bearings = df_scan(truth, uav, df, truth_rng)
        state, res = tick(setup, state, [Scan(uav, bearings)], rng, plan_from=uav, workspace=ws)
        err = np.linalg.norm(res.means[:, :2] - truth[:, :2], axis=1)
        errors.append(err)
        console.print(f"t={k:3d}s  uav=({uav[0]:6.1f}, {uav[1]:6.1f})  error per target \\[m]: "
                      + " ".join(f"{e:6.1f}" for e in err)
                      + f"   tick {res.timings_s['tick'] * 1e3:6.1f} ms")
        truth = world.step()  # each target follows its own guidance from its true state, noise Q
        if res.next_position is not None:
            uav = res.next_position
    errors = np.array(errors)
    table = Table(title=f"position error after {args.ticks} ticks (seed {args.seed})")
    for col in ("target", "final [m]", "mean over run [m]"):
        table.add_column(escape(col), justify="right")  # "[m]" is rich markup otherwise
    for j, t in enumerate(sc.targets):
        table.add_row(t.name, f"{errors[-1, j]:.1f}", f"{errors[:, j].mean():.1f}")
    console.print(table)
    return 0


def _eval(args) -> int:
    import json
    import re
    import shlex
    import signal
    import time

    from sim import evaluation as ev

    # Ctrl-C stops the evaluation (and its workers) even when started from a shell that ignores
    # SIGINT: a background job without job control inherits SIG_IGN (as pmon demo does)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    sc = load_scenario(args.scenario, parse_overrides(args.set))
    if args.scheduler is not None and not re.fullmatch(r"(tcp|tls|inproc|ucx)://\S+|[\w.\-\[\]:]+:\d+",
                                                       args.scheduler):
        args._parser.error(f"--scheduler: {args.scheduler!r} is not an address like tcp://127.0.0.1:8786")
    if args.workers is not None and args.workers < 1:
        args._parser.error(f"--workers must be >= 1, got {args.workers}")
    try:
        cfg = ev.make_config(sc, args.trials, args.seed, [m for m in args.methods.split(",") if m],
                             duration_s=args.duration, particles=args.particles)
    except ValueError as exc:
        args._parser.error(str(exc))
    t0 = time.perf_counter()
    trials = ev.run_trials(cfg, workers=args.workers, scheduler=args.scheduler, progress=not args.quiet)
    summary = ev.summarise(cfg, trials, wall_s=time.perf_counter() - t0)
    command = "pmon " + " ".join(shlex.quote(a) for a in args._argv)
    head = ev.write_outputs(summary, trials, args.out, command, figures=not args.no_figures)
    print(json.dumps(head), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    args_in = list(sys.argv[1:] if argv is None else argv)
    if args_in[:1] == ["gcs"]:  # own parsers, --help included: options before the command
        from groundstation.cli import main as gcs_main
        return gcs_main(args_in[1:])
    if args_in[:1] == ["feed"]:
        from sim.feed import main as feed_main
        return feed_main(args_in[1:])
    ap = OneLineParser(prog="pmon", description="Passive Monitor")  # subparsers are OneLineParsers too
    sub = ap.add_subparsers(dest="command", required=True)
    c = sub.add_parser("check-config", help="validate a scenario file")
    c.add_argument("scenario", nargs="?", default="paper", help="YAML file or built-in name (default: paper)")
    c.set_defaults(func=_check)
    s = sub.add_parser("simulate", help="closed loop on the core, no sockets (truth, DF model, monitor)")
    s.add_argument("scenario", nargs="?", default="paper")
    s.add_argument("--ticks", type=integer(1, 100_000), default=30, help="seconds of mission (default 30)")
    s.add_argument("--seed", type=SEED, default=1)
    s.set_defaults(func=_simulate)
    e = sub.add_parser("eval", help="Monte Carlo evaluation: methods vs baselines, CSV, table, figures, JSON line")
    e.add_argument("scenario", nargs="?", default="paper")
    e.add_argument("--trials", type=integer(1, 1_000_000), default=100, help="Monte Carlo trials (default 100)")
    e.add_argument("--seed", type=SEED, default=2024, help="master seed (default 2024)")
    e.add_argument("--methods", default="greedy_l1,greedy_l8,fixed3,hover,orbit,random",
                   help="comma-separated method names (default: the paper's six; also lookahead, "
                        "lookahead_vehicle, greedy_vehicle, and flight, the flight default; a flown "
                        "method takes its autopilot as @stock or @demo: docs/RESULTS.md)")
    e.add_argument("--out", default="eval_out", type=OUT_DIR, help="output directory (default eval_out)")
    e.add_argument("--duration", type=float, default=None, help="mission seconds (default: the scenario's)")
    from onboard.settings import SETTINGS
    particles = SETTINGS["tracking.particles"]  # its range declared once (docs/SETTINGS.md)
    e.add_argument("--particles", type=integer(int(particles.lo), int(particles.hi)), default=None,
                   help="particles per target, i.e. --set tracking.particles=N (default: the scenario's)")
    e.add_argument("--workers", type=integer(1, 4096), default=None, help="local worker processes (default: all cores)")
    e.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://127.0.0.1:8786")
    e.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change a scenario value for this run (VALUE read as YAML; repeatable), "
                        "e.g. --set planning.speed_max_mps=15")
    e.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    e.add_argument("--quiet", action="store_true", help="no progress bar")
    e.set_defaults(func=_eval, _parser=e)
    from onboard.app import run as _run_mod
    r = sub.add_parser("run", help="the onboard app: MAVLink to the autopilot, DF datagrams in")
    _run_mod.add_arguments(r)
    r.set_defaults(func=_run_mod.run)
    sub.add_parser("feed", help="simulated DF feed: live truth world, or replay a file (pmon feed --help)",
                   add_help=False)
    d = sub.add_parser("demo", help="mock autopilot + feed + app on loopback, paper scenario")
    from onboard import demo as _demo_mod
    _demo_mod.add_arguments(d)
    d.set_defaults(func=_demo_mod.run)
    g = sub.add_parser("gcs", help="ground station: status, watch, commands, parameters over MAVLink "
                       "(pmon gcs --help)", add_help=False)
    g.add_argument("rest", nargs=argparse.REMAINDER)
    g.set_defaults(func=lambda a: __import__("groundstation.cli", fromlist=["main"]).main(a.rest))
    args = ap.parse_args(argv)
    args._argv = list(sys.argv[1:] if argv is None else argv)
    try:
        return args.func(args)
    except ConfigError as exc:
        print(f"pmon: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
