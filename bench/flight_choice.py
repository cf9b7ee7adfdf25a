"""Variants of the flight default on the same trials: which setting measures best.

    python bench/flight_choice.py [--trials 100] [--seed 2024] [--workers 2] [--autopilot stock]
                                  [--variant NAME KEY=VALUE ...] ... [--with greedy_l1,lookahead,fixed3]
                                  [--out DIR] [--set KEY=VALUE ...]

Each ``--variant NAME KEY=VALUE ...`` is the evaluation's ``flight`` method (onboard/policy.py
POLICIES["flight"], flown by the vehicle model with the autopilot's limits) with those scenario
settings on top, run as method ``flight~NAME@AUTOPILOT`` (its own random streams, as every
method has); ``flight`` itself runs as the base. ``--with`` adds registered methods. Every method
sees the same truths and UAV starts (``pmon eval``'s trials for the seed). Prints, per variant,
its RMSE, the paired difference from the base (per-trial window RMSE, mean and 95 % t-interval)
and the ratio of time-averaged RMSEs variant / base (95 % paired bootstrap CI), with the mean
ms per tick, and writes ``pmon eval``'s files to ``--out``. Last line: JSON.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import add_set_option, set_label, set_overrides  # noqa: E402
from onboard.config import ConfigError, load_scenario, parse_overrides  # noqa: E402
from sim import evaluation as ev  # noqa: E402

BASE = "flight"


def variant(name: str, items: list[str], autopilot: str) -> ev.Method:
    """``flight`` with the scenario settings ``items`` (KEY=VALUE) on top of its policy's."""
    base = ev.METHODS[BASE]
    extra = parse_overrides(items)
    return replace(base, name=f"{BASE}~{name}@{autopilot}", autopilot=autopilot,
                   scenario_overrides=tuple({**dict(base.scenario_overrides), **extra}.items()),
                   description=f"{base.description}; with {', '.join(items) or 'nothing more'}; autopilot: {autopilot}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python bench/flight_choice.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--autopilot", default="stock", choices=sorted(ev.AUTOPILOTS),
                    help="the autopilot parameters every flight variant flies with (default stock)")
    ap.add_argument("--variant", nargs="+", action="append", default=[], metavar=("NAME", "KEY=VALUE"),
                    help="a variant: its name, then the scenario settings it changes; repeatable")
    ap.add_argument("--with", dest="others", default="", help="comma-separated registered methods run beside")
    ap.add_argument("--out", default=None, help="write pmon eval's files here (default: none)")
    ap.add_argument("--quiet", action="store_true")
    add_set_option(ap)
    args = ap.parse_args(argv)
    try:
        sc = load_scenario("paper", set_overrides(ap, args))
        base = replace(ev.METHODS[BASE], name=f"{BASE}@{args.autopilot}", autopilot=args.autopilot)
        variants = [variant(v[0], v[1:], args.autopilot) for v in args.variant]
        others = [m for m in args.others.split(",") if m]
        cfg = ev.make_config(sc, args.trials, args.seed, others + [BASE])
        cfg = replace(cfg, methods=cfg.methods[:-1] + (base, *variants))
        for m in (base, *variants):  # a bad setting is said before any trial runs
            ev._setup_for(cfg, m)
    except (ConfigError, ValueError) as exc:
        ap.error(str(exc))
    t0 = time.perf_counter()
    trials = ev.run_trials(cfg, workers=args.workers, progress=not args.quiet)
    summary = ev.summarise(cfg, trials, wall_s=time.perf_counter() - t0)
    print(f"paper scenario{set_label(args)}, {args.trials} trials, seed {args.seed}, autopilot {args.autopilot}, "
          f"wall {summary.wall_s:.0f} s")
    print(f"{'method':34s} {'RMSE':>6s} {'minus base (95 % CI)':>24s} {'over base (95 % CI)':>22s} "
          f"{'ms/tick':>8s} {'from plan med/p95':>18s}")
    out = {}
    for m in cfg.methods:
        s = summary.methods[m.name]
        f = s.flown
        plan = f"{f['miss_median_m']:.2f} / {f['miss_p95_m']:.2f}" if f else ""
        if m in variants:
            r, d = summary.pairs[(m.name, base.name)]  # paired on the same trials by summarise
            c = {"rmse_m": s.rmse_mean_m, "minus_base_m": d, "over_base": r, "ms_per_tick": s.tick_ms}
            print(f"{m.name:34s} {s.rmse_mean_m:6.1f} {d[0]:+7.2f} ({d[1]:+6.2f}, {d[2]:+6.2f}) "
                  f"{r[0]:6.3f} ({r[1]:.3f}, {r[2]:.3f}) {s.tick_ms:8.0f} {plan:>18s}")
            out[m.name] = {k: (round(v, 4) if isinstance(v, float) else [round(x, 4) for x in v])
                           for k, v in c.items()}
        else:
            print(f"{m.name:34s} {s.rmse_mean_m:6.1f} {'':24s} {'':22s} {s.tick_ms:8.0f} {plan:>18s}")
            out[m.name] = {"rmse_m": round(s.rmse_mean_m, 4), "ms_per_tick": round(s.tick_ms, 1)}
    if args.out:
        command = "python bench/flight_choice.py " + " ".join(sys.argv[1:] if argv is None else argv)
        ev.write_outputs(summary, trials, args.out, command, figures=False)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
