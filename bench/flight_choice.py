"""Variants of the flight default on the same trials: which setting measures best.

    python -m bench.flight_choice [--trials 100] [--seed 2024] [--workers 2] [--autopilot stock]
                                  [--variant NAME KEY=VALUE ...] ... [--with greedy_l1,lookahead,fixed3]
                                  [--out DIR] [--against CSV:METHOD ...] [--set KEY=VALUE ...]

Each ``--variant NAME KEY=VALUE ...`` is the evaluation's ``flight`` method (onboard/policy.py
POLICIES["flight"], flown by the vehicle model with the autopilot's limits) with those scenario
settings on top, run as method ``flight~NAME@AUTOPILOT`` (its own random streams, as every
method has); ``flight`` itself runs as the base. ``--with`` adds registered methods. Every method
sees the same truths and UAV starts (``pmon eval``'s trials for the seed). Prints, per variant,
its RMSE, the paired difference from the base (per-trial window RMSE, mean and 95 % t-interval)
and the ratio of time-averaged RMSEs variant / base (95 % paired bootstrap CI), with the mean
ms per tick; then per method its ANEES, RMSE / bound and tails (the largest per-(trial, target)
NEES and the pairs carrying most of the squared error, as bench/consistency.py prints them); and
writes ``pmon eval``'s files to ``--out``. ``--against CSV:METHOD`` pairs the base with a stored
run on the same trials (a per_trial.csv of the same seed, e.g.
docs/results_flight_default/per_trial.csv). Last line: JSON.
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from dataclasses import replace

import numpy as np

from bench import add_set_option, set_label, set_overrides
from bench.consistency import figures
from onboard.config import ConfigError, load_scenario, parse_overrides
from sim.evaluation import trials as ev

BASE = "flight"


def variant(name: str, items: list[str], autopilot: str) -> ev.Method:
    """``flight`` with the scenario settings ``items`` (KEY=VALUE) on top of its policy's."""
    base = ev.METHODS[BASE]
    extra = parse_overrides(items)
    return replace(base, name=f"{BASE}~{name}@{autopilot}", autopilot=autopilot,
                   scenario_overrides=tuple({**dict(base.scenario_overrides), **extra}.items()),
                   description=f"{base.description}; with {', '.join(items) or 'nothing more'}; autopilot: {autopilot}")


def stored_trials(spec: str) -> np.ndarray:
    """Per-trial window RMSE (trial order) of METHOD in a stored per_trial.csv (``CSV:METHOD``)."""
    path, _, method = spec.rpartition(":")
    if not path:
        raise ValueError(f"{spec!r} is not CSV:METHOD")
    with open(path, encoding="utf-8") as f:
        rows = [r for r in csv.DictReader(f) if r["method"] == method]
    if not rows:
        raise ValueError(f"no method {method!r} in {path}")
    return np.array([float(r["rmse_window_m"]) for r in sorted(rows, key=lambda r: int(r["trial"]))])


def paired_against(a: np.ndarray, b: np.ndarray, seed: int) -> tuple[tuple, tuple]:
    """Runs a and b on the same trials (their first common ones): the mean per-trial difference
    a - b with its 95 % t-interval, and the ratio of their RMS per-trial RMSEs with a 95 % paired
    percentile bootstrap CI (the trials resampled with replacement, both runs together)."""
    n = min(len(a), len(b))
    a, b = a[:n], b[:n]
    diff = ev.t_interval(a - b)
    rng = ev.seeded_rng(seed, 2**31 - 3)
    idx = rng.integers(0, n, (ev.BOOTSTRAP_RESAMPLES, n))
    boot = np.sqrt((a[idx] ** 2).mean(axis=1) / (b[idx] ** 2).mean(axis=1))
    ratio = (float(np.sqrt(np.mean(a ** 2) / np.mean(b ** 2))), float(np.percentile(boot, 2.5)),
             float(np.percentile(boot, 97.5)))
    return diff, ratio


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    try:
        stored = [(spec, stored_trials(spec)) for spec in args.against]
    except (OSError, ValueError) as exc:
        ap.error(f"--against: {exc}")
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
    out = _method_rows(cfg, summary, base, variants)
    tails = figures(cfg, trials)  # bench/consistency.py's: where each filter's error and NEES come from
    for m in cfg.methods:
        s, t = summary.methods[m.name], tails[m.name]
        print(f"{m.name:34s} ANEES {s.nees_mean:.2f}, RMSE / bound {s.rmse_over_bound:.2f}, median per-trial ratio "
              f"{t.get('over_bound_trial_median', float('nan'))}; largest (trial, target) NEES {t['top5']}; "
              "largest shares of the squared error: " + ", ".join(
                  f"trial {p['trial']} {p['target']} {p['rmse_m']} m ({100 * p['share']:.1f} %, NEES {p['nees']})"
                  for p in t["worst_pairs"]))
        out[m.name].update(anees=round(s.nees_mean, 4), over_bound=round(s.rmse_over_bound, 4), top5_nees=t["top5"],
                           worst_pairs=t["worst_pairs"])
    _against_stored(summary, base, stored, args.seed, out)
    if args.out:
        command = "python -m bench.flight_choice " + " ".join(sys.argv[1:] if argv is None else argv)
        ev.write_outputs(summary, trials, args.out, command, figures=False)
    print(json.dumps(out))
    return 0


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m bench.flight_choice", description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--autopilot", default="stock", choices=sorted(ev.AUTOPILOTS),
                    help="the autopilot parameters every flight variant flies with (default stock)")
    ap.add_argument("--variant", nargs="+", action="append", default=[], metavar=("NAME", "KEY=VALUE"),
                    help="a variant: its name, then the scenario settings it changes; repeatable")
    ap.add_argument("--with", dest="others", default="", help="comma-separated registered methods run beside")
    ap.add_argument("--out", default=None, help="write pmon eval's files here (default: none)")
    ap.add_argument("--against", action="append", default=[], metavar="CSV:METHOD",
                    help="a stored run's per_trial.csv and method (same seed and truths): the base paired "
                         "with it trial by trial; repeatable")
    ap.add_argument("--quiet", action="store_true")
    add_set_option(ap)
    return ap


def _method_rows(cfg, summary, base, variants) -> dict:
    """Each method's RMSE and ms per tick, a variant's paired with the base, printed; by method."""
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
    return out


def _against_stored(summary, base, stored, seed: int, out: dict) -> None:
    """--against: the base paired trial by trial with each stored run, printed and into ``out``."""
    for spec, other in stored:
        base_r = summary.methods[base.name].per_trial_rmse
        d, ratio = paired_against(base_r, other, seed)
        n = min(len(base_r), len(other))
        print(f"{base.name} against {spec} (trials 0-{n - 1}, paired): minus it {d[0]:+.2f} m ({d[1]:+.2f}, {d[2]:+.2f}), "
              f"RMS of per-trial RMSE over its {ratio[0]:.3f} ({ratio[1]:.3f}, {ratio[2]:.3f})")
        out[f"{base.name} against {spec}"] = {"minus_m": [round(x, 4) for x in d], "over": [round(x, 4) for x in ratio]}


if __name__ == "__main__":
    sys.exit(main())
