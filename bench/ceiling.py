"""The clairvoyant ceiling of a real copter (issue 29, item 2): per evaluation trial, the path a
vehicle at given limits would fly knowing the true target trajectories, chosen to minimise the
evaluation's PCRB, beside the flight default's PCRB and RMSE on the same trial.

    python -m bench.ceiling run    --trials 100 [--speed 9 --accel 2.5] [--starts quick|all]
    python -m bench.ceiling check  --trials 10  [--speed 9 --accel 2.5]    # near-optimality
    python -m bench.ceiling hop    --trials 20  [--rounds 3]                # basin hopping from it
    python -m bench.ceiling aggregate --trials 100                         # the N-trial bound itself
    python -m bench.ceiling greedy --trials 10                             # the myopic far path
    python -m bench.ceiling report [--figures DIR]

Common options: --seed 2024, --cache DIR (the trials, bench/ceiling_cache.py fills it: the
evaluation's truth, gains, start and flight@stock run, as ``pmon eval paper --seed 2024 --methods
flight@stock``), --out DIR (each stage's per-trial results, so a stage resumes where it
stopped). ``run``: ``sim.evaluation.ceiling_search.search`` per trial (quick: 6 pursuit starts + the flight
path; all: 12 + the flight path, 3 refined). ``check``: on the same trials, the search from all
starts and the cross-entropy method from rest (two seeds, then refined by the SQP): the spread
says how near the minimum is to the global one. ``hop``: basin hopping from the run's paths (perturbed restarts). ``aggregate``: one majorise-minimise round of the N-trial bound
(the evaluation's sqrt of the trial mean) from the per-trial optima. ``greedy``: the one-step greedy among 33 points
within 9 m (sim-side method ``myopic9``) flown on the same truths with our filter: RMSE, PCRB,
range. ``report``: the tables and the figures; last line JSON. CPU seconds are per trial, one
process (the machine may be shared: wall time is not the cost).
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from sim.evaluation.workers import one_blas_thread  # no numpy import

one_blas_thread()  # before numpy loads: one core's figures

from sim.evaluation.numerics import PINNED  # no numpy import

for _k, _v in PINNED.items():  # the evaluation's kernels (sim/evaluation/numerics.py), set before numpy loads
    os.environ.setdefault(_k, _v)

import numpy as np

from bench.ceiling_cache import (DEFAULT_CACHE, FLIGHT, _setup, fill_cache, label,
                                 load_trial)
from sim.evaluation import ceiling as ce
from sim.evaluation import ceiling_search as cs

DEFAULT_OUT = "/tmp/ceiling/out"


def problem(setup, d: dict, speed: float, accel: float) -> ce.CeilingProblem:
    return ce.problem_for_trial(setup, d["truth"], d["gains"], d["start"], 10, speed, accel)


def _trials(args) -> list[int]:
    return list(range(args.first, args.first + args.trials))


def _pending(args, out: Path):
    """(trial, its result file, its cached truth) for each trial of the run not yet written to out
    (a stage resumes where it stopped)."""
    for t in _trials(args):
        f = out / f"t{t:03d}.npz"
        if not f.exists():
            yield t, f, load_trial(Path(args.cache), args.seed, t)


def _ensure_cache(args) -> None:
    fill_cache(_trials(args), args.seed, ["flight@stock"], Path(args.cache), 1)


# --------------------------------------------------------------------------- run


def cmd_run(args) -> dict:
    _ensure_cache(args)
    setup = _setup()
    out = Path(args.out) / label(args.speed, args.accel) / args.starts
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for t in _trials(args):
        f = out / f"t{t:03d}.npz"
        if not f.exists():
            d = load_trial(Path(args.cache), args.seed, t)
            pb = problem(setup, d, args.speed, args.accel)
            flown = d[f"{FLIGHT}.uav"][:, :2]
            c0 = time.process_time()
            c = cs.search(pb, (cs.track(pb, flown)[None], ["flight"]),
                          only=None if args.starts == "all" else cs.QUICK_STARTS,
                          keep=3 if args.starts == "all" else 2)
            np.savez_compressed(f, path=c.path, acc=c.acc, bound_m2=c.bound_m2, value=c.value,
                                names=np.array(c.names), start_values=c.start_values,
                                local_values=c.local_values, refined=c.refined,
                                refined_values=c.refined_values, cpu_s=time.process_time() - c0)
        with np.load(f) as r:
            rows.append((t, float(r["value"]), float(r["cpu_s"])))
            print(f"trial {t}: ceiling {rows[-1][1]:.3f} m, {rows[-1][2]:.1f} s CPU", flush=True)
    return {"trials": len(rows), "cpu_s_median": round(float(np.median([r[2] for r in rows])), 1)}


# --------------------------------------------------------------------------- check


def cmd_check(args) -> dict:
    """All starts, and the cross-entropy method (two seeds) refined by the SQP, per trial."""
    _ensure_cache(args)
    setup = _setup()
    out = Path(args.out) / label(args.speed, args.accel) / "check"
    out.mkdir(parents=True, exist_ok=True)
    for t, f, d in _pending(args, out):
        pb = problem(setup, d, args.speed, args.accel)
        flown = d[f"{FLIGHT}.uav"][:, :2]
        c0 = time.process_time()
        full = cs.search(pb, (cs.track(pb, flown)[None], ["flight"]), only=None, keep=3)
        c1 = time.process_time()
        cem_options = cs.CrossEntropyOptions(block=3, population=256, iterations=80)
        cem = [cs.cross_entropy(pb, np.random.default_rng([args.seed, t, s]), cem_options) for s in range(2)]
        c2 = time.process_time()
        cem_acc = np.stack([c.acc[0] for c in cem])
        polished = cs.evaluate(pb, cs.sqp(pb, cem_acc, block=1, maxiter=200)[0])
        c3 = time.process_time()
        np.savez_compressed(f, full=full.value, full_path=full.path, full_local=full.local_values,
                            full_refined=full.refined_values, names=np.array(full.names),
                            cem=np.array([c.value[0] for c in cem]), cem_paths=np.stack([c.paths[0] for c in cem]),
                            cem_polished=polished.value, cem_polished_paths=polished.paths,
                            cpu_full_s=c1 - c0, cpu_cem_s=c2 - c1, cpu_polish_s=c3 - c2)
        print(f"trial {t}: all starts {full.value:.3f}, CEM {cem[0].value[0]:.3f} / {cem[1].value[0]:.3f}, "
              f"refined {polished.value[0]:.3f} / {polished.value[1]:.3f} m ({c1 - c0:.0f}, {c2 - c1:.0f}, "
              f"{c3 - c2:.0f} s CPU)", flush=True)
    return {}


def cmd_hop(args) -> dict:
    """Basin hopping from the run's best path: ``rounds`` times, 8 starts made of the best path
    so far plus smooth random accelerations (a 10-tick moving average of white noise, scaled to
    0.5 and 1 m/s^2 rms), the search's SQPs from them, the best kept. A lower minimum near the
    one found says the search stopped short."""
    setup = _setup()
    base = Path(args.out) / label(args.speed, args.accel) / args.starts
    out = Path(args.out) / label(args.speed, args.accel) / "hop"
    out.mkdir(parents=True, exist_ok=True)
    for t, f, d in _pending(args, out):
        pb = problem(setup, d, args.speed, args.accel)
        with np.load(base / f"t{t:03d}.npz") as r:
            best_acc, start_value = r["acc"], float(r["value"])
        best, values = start_value, []
        rng = np.random.default_rng([args.seed, t, 7])
        c0 = time.process_time()
        for _ in range(args.rounds):
            noise = rng.normal(size=(8, pb.K + 8, 2))
            sm = np.stack([np.convolve(n[:, c], np.ones(10) / np.sqrt(10), mode="valid")[:pb.K - 1]
                           for n in noise for c in range(2)]).reshape(8, 2, pb.K - 1).transpose(0, 2, 1)
            scale = np.repeat([0.5, 1.0], 4)[:, None, None]
            starts = ce.fly(pb, best_acc[None] + scale * sm)[1]
            coarse = cs.evaluate(pb, cs.sqp(pb, starts, block=3, maxiter=60)[0])
            o = np.argsort(coarse.value)[:2]
            fine = cs.evaluate(pb, cs.sqp(pb, coarse.acc[o], block=1, maxiter=120)[0])
            values += list(coarse.value) + list(fine.value)
            i = int(np.argmin(fine.value))
            if fine.value[i] < best:
                best, best_acc = float(fine.value[i]), fine.acc[i]
        np.savez_compressed(f, start=start_value, best=best, values=np.array(values), cpu_s=time.process_time() - c0)
        print(f"trial {t}: run {start_value:.3f}, after {args.rounds} rounds of 8 hops {best:.3f} m "
              f"({100 * (best / start_value - 1):+.2f} %, {time.process_time() - c0:.0f} s CPU)", flush=True)
    return {}


# --------------------------------------------------------------------------- aggregate


def cmd_aggregate(args) -> dict:
    """One majorise-minimise round on the evaluation's N-trial bound: sqrt is concave, so
    sqrt(mean_n B_n) <= its tangent at the current paths, a sum over trials of w * B_n with
    w = 1 / (2 sqrt(mean_n B_n)) per (tick, target) in the window; minimising each trial's
    weighted sum from its current path (SQP, one acceleration per tick) can only lower the
    aggregate, which is what ``pmon eval`` reports. Needs ``run`` on the same trials."""
    setup = _setup()
    base = Path(args.out) / label(args.speed, args.accel) / args.starts
    out = Path(args.out) / label(args.speed, args.accel) / "aggregate"
    out.mkdir(parents=True, exist_ok=True)
    trials = _trials(args)
    cur = {}
    for t in trials:
        with np.load(base / f"t{t:03d}.npz") as r:
            cur[t] = (r["acc"], r["bound_m2"])
    B = np.stack([cur[t][1] for t in trials])
    w = np.zeros(B.shape[1:])
    w[10:] = 0.5 / np.sqrt(B.mean(axis=0)[10:]) / ((B.shape[1] - 10) * B.shape[2])  # x N: per trial
    before = ce.aggregate_bound(B, 10)
    for t in trials:
        f = out / f"t{t:03d}.npz"
        if not f.exists():
            d = load_trial(Path(args.cache), args.seed, t)
            pb = problem(setup, d, args.speed, args.accel)
            c0 = time.process_time()
            acc = cs.sqp(pb, cur[t][0][None], block=1, maxiter=150, weights=w)[0]
            new = cs.evaluate(pb, acc)
            old_lin = float(np.sum(w * cur[t][1]))
            keep = new.ok[0] and float(np.sum(w * new.bound_m2[0])) < old_lin
            np.savez_compressed(f, path=new.paths[0] if keep else ce.fly(pb, cur[t][0][None])[0][0],
                                bound_m2=new.bound_m2[0] if keep else cur[t][1],
                                value=ce.window_bound(pb, (new.bound_m2 if keep else cur[t][1][None]))[0],
                                improved=keep, cpu_s=time.process_time() - c0)
        with np.load(f) as r:
            cur[t] = (None, r["bound_m2"])
    after = ce.aggregate_bound(np.stack([cur[t][1] for t in trials]), 10)
    print(f"N = {len(trials)}: aggregate bound {before:.4f} m from the per-trial optima, {after:.4f} m after one "
          f"majorise-minimise round ({100 * (after / before - 1):+.2f} %)")
    return {"before_m": round(before, 4), "after_m": round(after, 4)}


# --------------------------------------------------------------------------- greedy


def cmd_greedy(args) -> dict:
    from bench.ceiling_greedy import register, run_greedy

    _ensure_cache(args)
    register()
    out = Path(args.out) / "greedy"
    out.mkdir(parents=True, exist_ok=True)
    for t, f, d in _pending(args, out):
        c0 = time.process_time()
        tr = run_greedy(args.seed, t, d)
        np.savez_compressed(f, uav=tr.uav, error_m=tr.error_m, bound_m2=tr.bound_m2, cpu_s=time.process_time() - c0)
        e = np.sqrt(np.mean(tr.error_m[10:] ** 2))
        print(f"trial {t}: myopic9 RMSE {e:.2f} m, PCRB {np.sqrt(tr.bound_m2[10:]).mean():.2f} m", flush=True)
    return {}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("stage", choices=("run", "check", "hop", "aggregate", "greedy", "report"))
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--cache", default=DEFAULT_CACHE)
    ap.add_argument("--out", default=DEFAULT_OUT)
    ap.add_argument("--speed", type=float, default=9.0, help="v_max, m/s (the flight policy's 9)")
    ap.add_argument("--accel", type=float, default=2.5, help="a_max, m/s^2 (the flight policy's 2.5)")
    ap.add_argument("--starts", choices=("quick", "all"), default="quick")
    ap.add_argument("--figures", default=None, help="report: write the figures here")
    ap.add_argument("--rounds", type=int, default=3, help="hop: rounds of 8 perturbed restarts")
    args = ap.parse_args()
    if args.stage == "report":
        from bench.ceiling_report import report

        res = report(args)
    else:
        res = {"run": cmd_run, "check": cmd_check, "hop": cmd_hop, "aggregate": cmd_aggregate,
               "greedy": cmd_greedy}[args.stage](args)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
