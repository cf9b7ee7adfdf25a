"""The simulator's ``pmon`` verbs: ``pmon demo``, ``simulate``, ``eval``, ``worlds`` and ``feed``.

Each is a ``main(argv) -> exit code`` declared in pyproject.toml's entry-point group
``pmon.verbs`` (onboard/cli.py finds them there: the flight program never names the simulator),
and the first line of its docstring is its line in ``pmon --help``. This module stays light
(argparse and onboard's argument checks): ``pmon --help`` loads it to list the verbs, and what a
verb runs is imported when it runs.
"""
from __future__ import annotations

import sys

from onboard.argcheck import OUT_DIR, SEED, OneLineParser, integer


def _parser(verb: str, fn) -> OneLineParser:
    return OneLineParser(prog=f"pmon {verb}", description=fn.__doc__.split("\n\n")[0])


def _config_errors(run, args) -> int:
    """``run(args)``, a scenario's error as one line (exit 2), Ctrl-C as 130."""
    from onboard.config import ConfigError
    try:
        return run(args)
    except ConfigError as exc:
        print(f"pmon: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


def demo(argv: list[str] | None = None) -> int:
    """mock autopilot (or ArduPilot SITL) + DF feed + app on loopback, paper scenario, scored"""
    from sim.stack import demo as d

    p = _parser("demo", demo)
    d.add_arguments(p)
    return _config_errors(d.run, p.parse_args(argv))


def simulate(argv: list[str] | None = None) -> int:
    """closed loop on the core, no sockets (truth, DF model, monitor)"""
    p = _parser("simulate", simulate)
    p.add_argument("scenario", nargs="?", default="paper")
    p.add_argument("--ticks", type=integer(1, 100_000), default=30, help="seconds of mission (default 30)")
    p.add_argument("--seed", type=SEED, default=1)
    return _config_errors(_simulate, p.parse_args(argv))


def evaluate(argv: list[str] | None = None) -> int:
    """Monte Carlo evaluation: methods vs baselines, CSV, table, figures, JSON line"""
    argv = list(sys.argv[1:] if argv is None else argv)
    p = _parser("eval", evaluate)
    p.add_argument("scenario", nargs="?", default=None, help="YAML file or built-in name (default: paper)")
    p.add_argument("--trials", type=integer(1, 1_000_000), default=100, help="Monte Carlo trials (default 100)")
    p.add_argument("--seed", type=SEED, default=2024, help="master seed (default 2024)")
    p.add_argument("--methods", default="greedy_l1,greedy_l8,fixed3,hover,orbit,random",
                   help="comma-separated method names (default: the paper's six; also lookahead, "
                        "lookahead_vehicle, greedy_vehicle, and flight, the flight default; a flown "
                        "method takes its autopilot as @stock or @demo: docs/RESULTS.md)")
    p.add_argument("--out", default="eval_out", type=OUT_DIR, help="output directory (default eval_out)")
    p.add_argument("--duration", type=float, default=None, help="mission seconds (default: the scenario's)")
    from onboard.settings.sections import SETTINGS
    particles = SETTINGS["tracking.particles"]  # its range declared once (docs/SETTINGS.md)
    p.add_argument("--particles", type=integer(int(particles.lo), int(particles.hi)), default=None,
                   help="particles per target, i.e. --set tracking.particles=N (default: the scenario's)")
    p.add_argument("--workers", type=integer(1, 4096), default=None, help="local worker processes (default: all cores)")
    p.add_argument("--scheduler", default=None, help="Dask scheduler address, e.g. tcp://127.0.0.1:8786")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="change a scenario value for this run (VALUE read as YAML; repeatable), "
                        "e.g. --set planning.speed_max_mps=15")
    from sim.truth.kinds import TRUTH_KINDS
    p.add_argument("--truth", choices=TRUTH_KINDS, default="nominal",
                   help="how the true targets move (default nominal: as the scenario says; docs/RESULTS.md)")
    p.add_argument("--told", action="store_true", help="with --truth candidate_goal or stationary: the filter is "
                   "told what each target really does (the reference an untold filter is measured against)")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--worlds", default=None, metavar="FAMILY:N[,FAMILY:N...]",
                   help="instead of SCENARIO: N generated worlds of each family (town, open, crowd, corridor, "
                        "mixed; sim/truth/worlds.py), one trial each, the methods paired per world; a table per "
                        "family and pooled (docs/SCENARIO.md 'Generated worlds')")
    args = p.parse_args(argv)
    args._parser, args._argv = p, ["eval", *argv]
    if args.worlds is not None:
        from sim.evaluation.across_worlds import run_cli
        return _config_errors(run_cli, args)
    return _config_errors(_eval, args)


def worlds(argv: list[str] | None = None) -> int:
    """generated missions: N scenario files of a world family (town, open, crowd, corridor, mixed)"""
    from sim.truth.worlds import FAMILIES

    p = _parser("worlds", worlds)
    p.add_argument("family", choices=FAMILIES, help="the family (sim/truth/worlds.py; docs/SCENARIO.md)")
    p.add_argument("--n", type=integer(1, 100_000), default=10, help="worlds to write (default 10)")
    p.add_argument("--seed", type=SEED, default=2024, help="the family's seed (default 2024, as pmon eval's)")
    p.add_argument("--out", default="worlds", type=OUT_DIR, help="output directory (default worlds)")
    return _config_errors(_worlds, p.parse_args(argv))


def feed(argv: list[str] | None = None) -> int:
    """simulated DF feed: live truth world, or replay a file (pmon feed --help)"""
    from sim.stack.feed import main
    return main(argv)


def _worlds(args) -> int:
    from onboard.config import load_scenario
    from sim.truth.worlds import write_worlds

    for path in write_worlds(args.family, args.n, args.seed, args.out):
        sc = load_scenario(path)  # read back as a user's file is: the validator's word on it
        low = sum(o.size_m[2] < sc.uav.altitude_m for o in sc.obstacles)
        print(f"{path}: {len(sc.targets)} targets, {len(sc.obstacles)} obstacles ({low} lower than the UAV's "
              f"altitude), {len(sc.goals)} goal regions")
    return 0


def _simulate(args) -> int:
    import numpy as np
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from onboard.config import load_scenario
    from onboard.core.guidance.predictor import GuidanceWorkspace
    from onboard.core.monitor import MonitorSetup, Scan, UavState, initial_state, tick
    from sim.truth.sensors import DirectionFinder, df_scan
    from sim.truth.world import TruthWorld

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
        state, res = tick(setup, state, [Scan(uav, bearings)], rng, plan_from=UavState(uav), workspace=ws)
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

    from onboard.config import load_scenario, parse_overrides
    from sim.evaluation import trials as ev

    # Ctrl-C stops the evaluation (and its workers) even when started from a shell that ignores
    # SIGINT: a background job without job control inherits SIG_IGN (as pmon demo does)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    sc = load_scenario(args.scenario or "paper", parse_overrides(args.set))
    if args.scheduler is not None and not re.fullmatch(r"(tcp|tls|inproc|ucx)://\S+|[\w.\-\[\]:]+:\d+",
                                                       args.scheduler):
        args._parser.error(f"--scheduler: {args.scheduler!r} is not an address like tcp://127.0.0.1:8786")
    if args.workers is not None and args.workers < 1:
        args._parser.error(f"--workers must be >= 1, got {args.workers}")
    try:
        cfg = ev.make_config(sc, args.trials, args.seed, [m for m in args.methods.split(",") if m],
                             duration_s=args.duration, particles=args.particles, truth=args.truth,
                             told=args.told)
    except ValueError as exc:
        args._parser.error(str(exc))
    t0 = time.perf_counter()
    trials = ev.run_trials(cfg, workers=args.workers, scheduler=args.scheduler, progress=not args.quiet)
    summary = ev.summarise(cfg, trials, wall_s=time.perf_counter() - t0)
    command = "pmon " + " ".join(shlex.quote(a) for a in args._argv)
    head = ev.write_outputs(summary, trials, args.out, command, figures=not args.no_figures)
    print("\n".join(eval_summary(head, args.trials, args.out, ev.REFERENCE, not args.no_figures)), flush=True)
    if args.trials < FEW_TRIALS:
        print(f"pmon eval: warning: {args.trials} trial{'s' if args.trials > 1 else ''}: a 95 % confidence interval "
              f"means little below about {FEW_TRIALS} (the docs' figures use --trials 100)", file=sys.stderr, flush=True)
    print(json.dumps(head), flush=True)  # the last line, for scripts
    return 0


FEW_TRIALS = 10  # below this, pmon eval warns that its confidence intervals mean little


def eval_summary(head: dict, trials: int, out, reference: str, figures: bool = True) -> list[str]:
    """A short table of ``pmon eval``'s headline (the JSON line), and where its results went."""
    from pathlib import Path

    def f(x, spec=".1f"):
        return "-" if x is None else format(x, spec)
    ref = reference if reference in head["methods"] else None
    width = max(len(n) for n in head["methods"]) + 2
    rows = [f"{'method':<{width}}{'RMSE [m]':>9}{'PCRB [m]':>10}{'RMSE/PCRB':>11}{'ANEES':>7}"
            + (f"  {ref} / method (95 % CI)" if ref else "")]
    for name, m in head["methods"].items():
        r = m.get("ratio_vs_ref")
        ratio = "-" if not ref or name == ref or r is None else f"{f(r[0], '.2f')} ({f(r[1], '.2f')}, {f(r[2], '.2f')})"
        rows.append(f"{name:<{width}}{f(m['rmse_mean_m']):>9}{f(m['bound_m']):>10}{f(m['rmse_over_bound'], '.2f'):>11}"
                    f"{f(m['nees_mean'], '.2f'):>7}" + (f"  {ratio}" if ref else ""))
    over = head.get("pcrb_over_ceiling")
    if over:
        rows.append("PCRB over the clairvoyant ceiling's (95 % CI): " + "; ".join(
            f"{n} {f(v[0], '.3f')} ({f(v[1], '.3f')}, {f(v[2], '.3f')})" for n, v in over.items()))
    out = Path(out)
    pngs = sorted(p.name for p in out.glob("*.png")) if figures else []
    rows.append(f"{trials} trial{'s' if trials > 1 else ''}; RMSE averaged over the targets and the convergence "
                f"window; ANEES 2 is a consistent filter" + (f"; {ref} / method > 1: better than {ref}" if ref else ""))
    rows.append(f"results in {out}/: results.md (every table, and how each figure is made), rmse.csv, "
                "per_trial.csv" + (f", {len(pngs)} figures ({', '.join(pngs)})" if pngs else ""))
    return rows
