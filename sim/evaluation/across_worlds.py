"""The evaluation across generated worlds (``pmon eval --worlds FAMILY:N[,FAMILY:N...]``).

World i of a family (``sim.truth.worlds.draw_world(family, seed, i)``, the run's ``--set`` applied) is
flown once, as trial i of ``pmon eval``'s seed: every method on the same truth and UAV start
(``sim.evaluation.trials.run_trial``), so the methods are paired per world, and the trial is the one
``pmon eval WORLD.yaml --seed S --trials i+1`` runs as its trial i (the world's file is written
beside the results).

Per world and method: its window RMSE (sqrt of the mean over the convergence window's ticks and
the world's targets of the squared horizontal error, as ``pmon eval``'s per-trial RMSE) and PCRB.
Per family and pooled over every world: the RMSE is the RMS over the worlds of those window
RMSEs (each world weighs the same, whatever its number of targets), and the first method of
``--methods`` is set against each other by the ratio of those RMSEs with a 95 % paired percentile
bootstrap CI (the worlds resampled with replacement, both methods together: bench/paired.py's
ratio, which docs/RESULTS.md's tables give).
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from sim.evaluation import trials as ev
from sim.evaluation.metrics import BOOTSTRAP_RESAMPLES, seeded_rng
from sim.truth.worlds import parse_spec, world_name, world_yaml

POOLED = "pooled"


@dataclass(frozen=True, eq=False)
class WorldJob:
    family: str
    index: int
    cfg: ev.EvalConfig


@dataclass(frozen=True)
class WorldResult:
    """One world's figures: per method, its window RMSE and PCRB (m; NaN where undefined)."""

    family: str
    index: int
    targets: int
    obstacles: int
    rmse_m: dict
    pcrb_m: dict


def world_jobs(spec: str, seed: int, methods: Sequence[str], overrides: dict, **config) -> list[WorldJob]:
    """Every world of ``spec`` with its evaluation's configuration (``sim.evaluation.trials.make_config``:
    ``config`` are its keywords). ValueError or ConfigError, one line, for a bad spec or setting."""
    from onboard.config import override
    from sim.truth.worlds import draw_world

    jobs = []
    for family, n in parse_spec(spec):
        for i in range(n):
            sc = override(draw_world(family, seed, i), overrides)
            jobs.append(WorldJob(family, i, ev.make_config(sc, 1, seed, methods, **config)))
    return jobs


def _run_job(job: WorldJob) -> WorldResult:
    res = ev.run_trial(job.cfg, job.index)
    w0 = job.cfg.window_start
    rmse, pcrb = {}, {}
    for name, tr in res.traces.items():
        rmse[name] = float(np.sqrt(np.mean(tr.error_m[w0:] ** 2)))  # NaN for a bound-only method
        pcrb[name] = float("nan") if tr.bound_m2 is None else float(np.sqrt(np.mean(tr.bound_m2[w0:])))
    sc = job.cfg.scenario
    return WorldResult(job.family, job.index, len(sc.targets), len(sc.obstacles), rmse, pcrb)


def run_worlds(jobs: Sequence[WorldJob], workers: int = 1, progress: bool = True) -> list[WorldResult]:
    """Every job's trial in ``workers`` spawned processes of one BLAS thread each (as
    ``sim.evaluation.trials.run_trials``: the same figures whatever the workers), in the jobs' order."""
    import multiprocessing as mp

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from sim.evaluation.numerics import pin_kernels
    from sim.evaluation.workers import one_blas_thread, worker_pool

    one_blas_thread()
    pin_kernels()
    out: dict = {}
    bar = Progress(TextColumn("[bold]eval --worlds[/]"), BarColumn(), MofNCompleteColumn(), TextColumn("worlds"),
                   TimeElapsedColumn(), disable=not progress, refresh_per_second=2)
    with bar, worker_pool(mp.get_context("spawn"), max(1, min(workers, len(jobs)))) as pool:
        task = bar.add_task("", total=len(jobs))
        for r in pool.imap_unordered(_run_job, jobs):
            out[(r.family, r.index)] = r
            bar.advance(task)
    return [out[(j.family, j.index)] for j in jobs]


def rms_ratio(a: np.ndarray, b: np.ndarray, seed: int) -> tuple[float, float, float]:
    """RMS(a) / RMS(b) of per-world RMSEs of the same worlds, with a 95 % paired percentile
    bootstrap CI (NaN bounds for one world)."""
    ratio = float(np.sqrt(np.mean(a ** 2) / np.mean(b ** 2)))
    if len(a) < 2:
        return ratio, float("nan"), float("nan")
    idx = seeded_rng(seed, 2**31 - 3).integers(0, len(a), (BOOTSTRAP_RESAMPLES, len(a)))
    boot = np.sqrt((a[idx] ** 2).mean(axis=1) / (b[idx] ** 2).mean(axis=1))
    return ratio, float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))


def family_rows(results: Sequence[WorldResult], methods: Sequence[str], seed: int) -> list[dict]:
    """Per family (in the order run), then pooled over every world: worlds, mean targets, each
    method's RMSE and PCRB (RMS over the worlds), the first method over each other filtered
    one (ratio, CI low, CI high) with the worlds where it was the lower, and the first's PCRB
    over each bound-only method's (the clairvoyant ceiling: ratio, CI low, CI high)."""
    groups: dict = {}
    for r in results:
        groups.setdefault(r.family, []).append(r)
    if len(groups) > 1:
        groups[POOLED] = list(results)
    first, rows = methods[0], []
    for fam, rs in groups.items():
        rm = {m: np.array([r.rmse_m[m] for r in rs]) for m in methods}
        pc = {m: np.array([r.pcrb_m[m] for r in rs]) for m in methods}
        row = {"family": fam, "worlds": len(rs), "targets": float(np.mean([r.targets for r in rs])),
               "rmse_m": {m: float(np.sqrt(np.mean(v ** 2))) for m, v in rm.items()},
               "pcrb_m": {m: float(np.sqrt(np.mean(v ** 2))) for m, v in pc.items()}, "ratios": {}}
        if not np.isnan(rm[first]).any():
            for m in methods[1:]:
                if not np.isnan(rm[m]).any():
                    row["ratios"][m] = (*rms_ratio(rm[first], rm[m], seed), int(np.sum(rm[first] < rm[m])))
        row["bound_ratios"] = {m: rms_ratio(pc[first], pc[m], seed) for m in methods[1:]
                               if np.isnan(rm[m]).all() and not np.isnan(pc[m]).any() and not np.isnan(pc[first]).any()}
        rows.append(row)
    return rows


def _f(x: float, spec: str = ".1f") -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, spec)


def table_markdown(rows: Sequence[dict], methods: Sequence[str]) -> list[str]:
    first = methods[0]
    others = [m for m in methods[1:] if m in rows[0]["ratios"]]
    bound = list(rows[0]["bound_ratios"])
    head = (["family", "worlds", "targets"] + [f"{m} RMSE [m]" for m in methods]
            + [f"{first} / {m} (95 % CI; worlds lower)" for m in others]
            + [f"{first} PCRB / {m} PCRB (95 % CI)" for m in bound])
    L = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        cells = [r["family"], str(r["worlds"]), f"{r['targets']:.1f}"]
        cells += [_f(r["rmse_m"][m]) if np.isfinite(r["rmse_m"][m]) else f"(PCRB {_f(r['pcrb_m'][m])})"
                  for m in methods]
        for m in others:
            v, lo, hi, k = r["ratios"][m]
            cells.append(f"{v:.2f} ({_f(lo, '.2f')}, {_f(hi, '.2f')}); {k}/{r['worlds']}")
        for m in bound:
            v, lo, hi = r["bound_ratios"][m]
            cells.append(f"{v:.3f} ({_f(lo, '.3f')}, {_f(hi, '.3f')})")
        L.append("| " + " | ".join(cells) + " |")
    return L


def write_outputs(jobs, results, rows, out_dir, command: str, wall_s: float) -> dict:
    """worlds.md (the table, the command), worlds.csv (per world and method) and each world's
    scenario file in worlds/; the headline (the JSON line) returned."""
    out = Path(out_dir)
    (out / "worlds").mkdir(parents=True, exist_ok=True)
    cfg = jobs[0].cfg
    for j in jobs:
        (out / "worlds" / f"{world_name(j.family, cfg.seed, j.index)}.yaml").write_text(
            world_yaml(j.family, cfg.seed, j.index), encoding="utf-8")
    with open(out / "worlds.csv", "w", encoding="utf-8") as f:
        f.write("family,index,world,targets,obstacles,method,rmse_window_m,pcrb_window_m\n")
        for r in results:
            for m in cfg.method_names:
                f.write(f"{r.family},{r.index},{world_name(r.family, cfg.seed, r.index)},{r.targets},{r.obstacles},"
                        f"{m},{r.rmse_m[m]:.4f},{r.pcrb_m[m]:.4f}\n")
    methods = cfg.method_names
    md = ["# pmon eval across generated worlds", "", f"- Command: `{command}`",
          f"- seed {cfg.seed}, truth {cfg.truth_kind}, {cfg.n_ticks} ticks, convergence window: ticks "
          f"{cfg.window_start}..{cfg.n_ticks - 1}; {len(jobs)} worlds, one trial each; wall {wall_s:.0f} s",
          f"- {ev.machine_description()}", "",
          "RMSE: the RMS over the worlds of each world's window RMSE; the ratio: of those RMSEs, paired per "
          f"world, 95 % percentile bootstrap CI ({BOOTSTRAP_RESAMPLES} resamples), and in how many worlds "
          f"{methods[0]}'s window RMSE was the lower (sim/evaluation/across_worlds.py).", ""]
    md += table_markdown(rows, methods) + ["", "Methods:", ""]
    md += [f"- `{m.name}`: {m.description}" for m in cfg.methods]
    (out / "worlds.md").write_text("\n".join(md) + "\n", encoding="utf-8")
    def num(x):
        return round(x, 4) if np.isfinite(x) else None  # JSON has no NaN
    return {"worlds": {r["family"]: {"worlds": r["worlds"], "rmse_m": {k: num(v) for k, v in r["rmse_m"].items()},
                                     "ratios": {f"{methods[0]} / {k}": [num(x) for x in v[:3]] + [v[3]]
                                                for k, v in r["ratios"].items()},
                                     "pcrb_ratios": {f"{methods[0]} / {k}": [num(x) for x in v]
                                                     for k, v in r["bound_ratios"].items()}} for r in rows},
            "seed": cfg.seed, "truth": cfg.truth_kind}


def run_cli(args) -> int:
    """``pmon eval --worlds``: the parsed arguments of ``pmon eval`` (sim/verbs.py)."""
    import shlex

    from onboard.config import parse_overrides

    p = args._parser
    if args.scenario is not None:
        p.error("--worlds draws its own scenarios: give no SCENARIO")
    if args.scheduler is not None:
        p.error("--worlds runs on local workers only (no --scheduler)")
    if any(a == "--trials" or a.startswith("--trials=") for a in args._argv):
        p.error("--worlds runs one trial per world: give the worlds' number in FAMILY:N, not --trials")
    try:
        jobs = world_jobs(args.worlds, args.seed, [m for m in args.methods.split(",") if m],
                          parse_overrides(args.set), duration_s=args.duration, particles=args.particles,
                          truth=args.truth, told=args.told)
    except ValueError as exc:
        p.error(str(exc))
    t0 = time.perf_counter()
    results = run_worlds(jobs, workers=args.workers or os.cpu_count() or 1, progress=not args.quiet)
    methods = jobs[0].cfg.method_names
    rows = family_rows(results, methods, args.seed)
    command = "pmon " + " ".join(shlex.quote(a) for a in args._argv)
    head = write_outputs(jobs, results, rows, args.out, command, time.perf_counter() - t0)
    print("\n".join(table_markdown(rows, methods)))
    print(f"results in {args.out}/: worlds.md, worlds.csv, worlds/ (each world's scenario file)")
    print(json.dumps(head), flush=True)
    return 0


__all__ = ["WorldJob", "WorldResult", "world_jobs", "run_worlds", "rms_ratio", "family_rows", "table_markdown",
           "write_outputs", "run_cli"]
