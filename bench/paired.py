"""Methods of several stored ``pmon eval`` runs, paired trial by trial.

    python -m bench.paired DIR[:METHOD[=LABEL]] ... [--against LABEL]

Each argument names a run's output directory (its per_trial.csv, rmse.csv and results.md) and,
optionally, one of its methods and the label it gets here (default: every method of the run,
labelled by name; a name already taken by an earlier run gets ``@DIRNAME`` appended). The runs
must be of the same seed, window and trial numbers (checked: the trial indices of every method
must be the same set; so the same truths, starts and DF draws, ``pmon eval``'s trials for that
seed). Prints per method: its RMSE (the evaluation's: eps_t averaged over the targets and the
window, from rmse.csv), PCRB and RMSE / bound (results.md's table); then, for every other method,
``--against`` over it: the mean per-trial window-RMSE difference (95 % t-interval) and the ratio
of the RMS per-trial window RMSEs with its 95 % paired percentile bootstrap CI
(``bench.flight_choice.paired_against``; this ratio is not the evaluation's own ratio of
time-averaged RMSEs, which needs every tick's error and is not stored). Last line: JSON.
"""
from __future__ import annotations

import argparse
import csv
import json
import re
from pathlib import Path

import numpy as np

from bench.flight_choice import paired_against


def run_header(run: Path) -> tuple[int, int, str]:
    """(seed, window start, the command) from a run's results.md."""
    text = (run / "results.md").read_text(encoding="utf-8")
    seed = re.search(r"seed (\d+)", text)
    window = re.search(r"Convergence window: ticks (\d+)\.\.", text)
    command = re.search(r"- Command: `([^`]*)`", text)
    if not (seed and window):
        raise ValueError(f"{run}/results.md: no seed or convergence window line")
    return int(seed.group(1)), int(window.group(1)), command.group(1) if command else "?"


def table_rows(run: Path) -> dict[str, dict[str, str]]:
    """results.md's first table (the RMSE table) as {method: {column: cell}}."""
    lines = [ln for ln in (run / "results.md").read_text(encoding="utf-8").splitlines() if ln.startswith("| ")]
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    rows = {}
    for ln in lines[1:]:
        cells = [c.strip() for c in ln.strip("|").split("|")]
        if cells[0] == "method":  # the next table
            break
        rows[cells[0]] = dict(zip(head, cells))
    return rows


def window_rmse(run: Path, method: str, w0: int) -> float:
    """The evaluation's RMSE of ``method``: the target-mean eps_t of rmse.csv over steps >= w0."""
    with open(run / "rmse.csv", encoding="utf-8") as f:
        v = [float(r["rmse_m"]) for r in csv.DictReader(f)
             if r["method"] == method and r["target"] == "mean" and int(r["step"]) >= w0]
    return float(np.mean(v))


def per_trial(run: Path) -> dict[str, dict[int, float]]:
    out: dict[str, dict[int, float]] = {}
    with open(run / "per_trial.csv", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            out.setdefault(r["method"], {})[int(r["trial"])] = float(r["rmse_window_m"])
    return out


def load(specs: list[str], common: bool = False) -> tuple[dict, int, int]:
    """{label: {run, method, trials (dict), rmse, pcrb, over_bound}}, the seed, the window start;
    ``common``: every run's trials cut to those all of them have (else they must be the same)."""
    found: dict[str, dict] = {}
    seeds, windows = set(), set()
    for spec in specs:
        path, _, rest = spec.partition(":")
        run = Path(path)
        method, _, label = rest.partition("=")
        seed, w0, command = run_header(run)
        seeds.add(seed)
        windows.add(w0)
        trials = per_trial(run)
        table = table_rows(run)
        names = [method] if method else list(trials)
        for m in names:
            if m not in trials:
                raise ValueError(f"{run}: no method {m!r} in per_trial.csv (has {', '.join(trials)})")
            lab = label or (m if m not in found else f"{m}@{run.name}")
            if lab in found:
                raise ValueError(f"label {lab!r} given twice")
            row = table.get(m, {})
            found[lab] = {"run": str(run), "method": m, "command": command, "trials": trials[m],
                          "rmse_m": window_rmse(run, m, w0), "pcrb_m": row.get("PCRB [m]", ""),
                          "over_bound": row.get("RMSE / bound", "")}
    if len(seeds) > 1 or len(windows) > 1:
        raise ValueError(f"the runs differ in seed {sorted(seeds)} or window start {sorted(windows)}")
    if common:
        keep = set.intersection(*(set(v["trials"]) for v in found.values()))
        if not keep:
            raise ValueError("the runs have no trial in common")
        for v in found.values():
            v["trials"] = {i: r for i, r in v["trials"].items() if i in keep}
    ids = {lab: sorted(v["trials"]) for lab, v in found.items()}
    first = next(iter(ids.values()))
    bad = [lab for lab, i in ids.items() if i != first]
    if bad:
        raise ValueError(f"trial indices differ: {bad[0]} has {len(ids[bad[0]])} trials "
                         f"({ids[bad[0]][:3]}...), the first {len(first)} ({first[:3]}...)")
    return found, seeds.pop(), windows.pop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.paired", description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", metavar="DIR[:METHOD[=LABEL]]")
    ap.add_argument("--against", default=None, help="the label every other method is paired with "
                                                     "(default: the first)")
    ap.add_argument("--common", action="store_true", help="pair on the trials every run has (a run of 50 "
                    "with one of 30: its first 30); the RMSE column stays each run's own")
    args = ap.parse_args(argv)
    try:
        found, seed, w0 = load(args.runs, args.common)
    except (OSError, ValueError, KeyError) as exc:
        ap.error(str(exc))
    base = args.against or next(iter(found))
    if base not in found:
        ap.error(f"--against {base!r}: not a label here ({', '.join(found)})")
    n = len(found[base]["trials"])
    print(f"{n} trials, seed {seed}, window from tick {w0}")
    print(f"{'label':28s} {'RMSE [m]':>9s} {'PCRB [m]':>9s} {'RMSE/bound':>11s}  run")
    for lab, v in found.items():
        print(f"{lab:28s} {v['rmse_m']:9.2f} {v['pcrb_m']:>9s} {v['over_bound']:>11s}  {v['run']}")
    out: dict = {"trials": n, "seed": seed, "against": base,
                 "rmse_m": {lab: round(v["rmse_m"], 4) for lab, v in found.items()}, "pairs": {}}
    a = np.array([found[base]["trials"][i] for i in sorted(found[base]["trials"])])
    print(f"\n{base} against each (per-trial window RMSE: mean difference, 95 % t-interval; "
          f"ratio of RMS, 95 % paired bootstrap CI)")
    for lab, v in found.items():
        if lab == base:
            continue
        b = np.array([v["trials"][i] for i in sorted(v["trials"])])
        d, r = paired_against(a, b, seed)
        print(f"{base + ' / ' + lab:48s} {r[0]:6.3f} ({r[1]:.3f}, {r[2]:.3f})   "
              f"minus {d[0]:+6.2f} m ({d[1]:+.2f}, {d[2]:+.2f})")
        out["pairs"][lab] = {"ratio": [round(x, 4) for x in r], "minus_m": [round(x, 4) for x in d]}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
