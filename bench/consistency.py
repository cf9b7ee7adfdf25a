"""Filter consistency per method: where the average NEES comes from (bulk or tails).

    python -m bench.consistency [SCENARIO] [--methods orbit,fixed3,greedy_l8,hover] [--trials 20 | --trial-ids 6,62]
                                [--set tracking.regularise_bandwidth=0 ...] [--out DIR]

Runs the evaluation's trials (``sim.evaluation.trials.run_trials``, the flight code) with the same
trials and seeds as ``pmon eval`` (seed 2024), on every core by default, and prints per method: ANEES
(the mean NEES over trials, targets and the window, as ``pmon eval`` reports it), the median of
the per-(trial, target) window-mean NEES (the bulk: 2 for a consistent filter, below for a
conservative one), the five largest per-(trial, target) values (the tails: a filter confidently
wrong on one trial shows here), the window RMSE, the three (trial, target) pairs with the largest
shares of the window's squared error (the trials to look at first), for a UAV method the error
along and across the lines of sight, near an obstacle and free (``error_split``), and RMSE / PCRB
per 10 s of the mission and the median of the per-trial ratio (where the bound gap comes from).
docs/TRACKING.md compares filter settings with it (``--set KEY=VALUE``: a scenario value changed,
VALUE read as YAML). ``--out DIR`` also writes ``pmon eval``'s files for the same trials
(per_trial.csv, rmse.csv, results.md; no figures), so one run gives both; a bound-only method
(``ceiling``) has no filter and only appears there. Last line: JSON figures.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass

import numpy as np

from bench import add_set_option, set_overrides
from onboard.config import load_scenario
from sim.evaluation import trials as ev
from sim.evaluation.metrics import error_split


@dataclass(frozen=True)
class EvalFiles:
    """Where ``pmon eval``'s files for the same trials go (``out``), and the command they say
    made them."""

    out: str
    command: str = ""


def consistency(scenario: str, methods: list[str], trials: int, seed: int = 2024,
                overrides: dict | None = None, workers: int | None = None, trial_ids: list[int] | None = None,
                files: EvalFiles | None = None) -> dict:
    n = trials if trial_ids is None else max(trial_ids) + 1
    cfg = ev.make_config(load_scenario(scenario, overrides), n, seed, methods=methods)
    t0 = time.perf_counter()
    # the trials of ``pmon eval``, each as a run of all of them computes it
    results = ev.run_trials(cfg, workers=workers, progress=False, trials=trial_ids)
    if files is not None:
        summary = ev.summarise(cfg, results, wall_s=time.perf_counter() - t0)
        ev.write_outputs(summary, results, files.out, files.command, figures=False)
    return figures(cfg, results)


def figures(cfg, results) -> dict:
    """Per method of ``cfg``, the figures above from the evaluation's trial results."""
    w = slice(cfg.window_start, None)
    out = {}
    for m in (m.name for m in cfg.methods if not m.bound_only):
        nees = np.stack([r.traces[m].nees[w].mean(axis=0) for r in results])  # (N, M)
        e_all = np.stack([r.traces[m].error_m for r in results])  # (N, K, M)
        out[m] = {"anees": round(float(nees.mean()), 2), "median": round(float(np.median(nees)), 2),
                  "top5": np.sort(nees.ravel())[-5:].round(1).tolist(),
                  "rmse_m": round(float(np.sqrt(np.mean(e_all[:, w] ** 2))), 1)}
        # the (trial, target) pairs that carry the most of the window's squared error
        sq = np.mean(e_all[:, w] ** 2, axis=1)  # (N, M)
        out[m]["worst_pairs"] = [
            {"trial": int(results[i].trial), "target": f"T{j + 1}", "rmse_m": round(float(np.sqrt(sq[i, j])), 1),
             "share": round(float(sq[i, j] / sq.sum()), 3), "nees": round(float(nees[i, j]), 1)}
            for i, j in zip(*np.unravel_index(np.argsort(sq, axis=None)[::-1][:3], sq.shape))]
        if all(r.traces[m].uav is not None for r in results):
            out[m]["error_split"] = error_split(cfg, results, m)
        if all(r.traces[m].bound_m2 is not None for r in results):
            # RMSE / PCRB (as pmon eval forms them) per 10 s of the mission, and per trial
            b_all = np.stack([r.traces[m].bound_m2 for r in results])
            eps, bnd = np.sqrt(np.mean(e_all ** 2, axis=0)).mean(axis=1), np.sqrt(b_all.mean(axis=0)).mean(axis=1)
            out[m]["over_bound_by_10s"] = [round(float(eps[k:k + 10].mean() / bnd[k:k + 10].mean()), 2)
                                           for k in range(0, len(eps), 10)]
            out[m]["over_bound"] = round(float(eps[w].mean() / bnd[w].mean()), 2)  # as pmon eval reports it
            per_trial = np.sqrt(np.mean(e_all[:, w] ** 2, axis=(1, 2)) / b_all[:, w].mean(axis=(1, 2)))
            out[m]["over_bound_trial_median"] = round(float(np.median(per_trial)), 2)
    return out


def report(res: dict, label: str = "") -> None:
    """Print consistency()'s figures a method a line (and RMSE / bound a line), then the JSON."""
    for name, r in res.items():
        head = f"{label}{name:12s}"
        print(f"{head} ANEES {r['anees']:6.2f}  median {r['median']:5.2f}  top5 {r['top5']}  RMSE {r['rmse_m']} m")
        worst = ", ".join(f"trial {p['trial']} {p['target']} {p['rmse_m']} m ({100 * p['share']:.1f} %, NEES {p['nees']})"
                          for p in r["worst_pairs"])
        print(f"{'':{len(head)}s} largest shares of the squared error: {worst}")
        for key, v in r.get("error_split", {}).items():
            print(f"{'':{len(head)}s} {key + ' an obstacle' if key == 'near' else 'free':16s} {100 * v['share']:3.0f} % of "
                  f"the squared error: RMS along the line of sight {v['along_m']} m, across {v['across_m']} m, "
                  f"mean range {v['range_m']} m ({v['cells']} target-ticks)")
        if "over_bound_by_10s" in r:
            print(f"{'':{len(head)}s} RMSE / bound {r['over_bound']}; per 10 s {r['over_bound_by_10s']}; "
                  f"median over trials {r['over_bound_trial_median']}")
    print(json.dumps(res))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario", nargs="?", default="paper")
    ap.add_argument("--methods", default="orbit,fixed3,greedy_l8,hover")
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--workers", type=int, default=None, help="local processes (default: one per core)")
    ap.add_argument("--trial-ids", default=None, help="comma-separated trial numbers to run instead of 0..N-1 "
                                                      "(each exactly as pmon eval runs it)")
    ap.add_argument("--out", default=None, help="also write pmon eval's files for these trials here")
    add_set_option(ap, "tracking.regularise_bandwidth=0")
    args = ap.parse_args()
    overrides = set_overrides(ap, args)
    try:
        ids = None if args.trial_ids is None else sorted({int(i) for i in args.trial_ids.split(",")})
    except ValueError:
        ap.error(f"--trial-ids: not a comma-separated list of trial numbers: {args.trial_ids!r}")
    if ids is not None and (not ids or ids[0] < 0):
        ap.error("--trial-ids: trial numbers are >= 0")
    files = None if args.out is None else EvalFiles(args.out, "python -m bench.consistency " + " ".join(sys.argv[1:]))
    res = consistency(args.scenario, args.methods.split(","), args.trials, overrides=overrides,
                      workers=args.workers, trial_ids=ids, files=files)
    report(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
