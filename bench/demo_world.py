"""`pmon demo --seed N`'s world flown offline: where a demo's error comes from.

    python -m bench.demo_world [--seeds 1,2,3,4,5] [--repeats 10] [--launch 17] [--workers 2]
                               [--variants eval,demo_limits,launch,demo] [--runs DIR_PATTERN]
                               [--starts 0] [--replay-draws 10] [--replay-guidance-s S] [--set KEY=VALUE ...]

The demo's truth is the feed's (sim/stack/live_feed.py: ``TruthWorld`` drawn from the first stream of
``SeedSequence(N).spawn(2)``), which ``simulate_truth`` reproduces to the last digit; its UAV
starts at the scenario's s_0 (sim/stack/rig.py: home = the UAV's start). On that world this runs the
evaluation's closed loop of the flight default (sim/evaluation/trials.py ``run_method``: the core tick,
the vehicle model flying the app's setpoints) in variants that add the demo's differences one at
a time:

- ``eval``: ``flight@stock`` as ``pmon eval`` flies it: at altitude at s_0 at t = 0;
- ``demo_limits``: the same with the demo's vehicle (``flight@demo``: DEMO_VEHICLE_PARAMS);
- ``launch``: ``eval`` with the old demo's launch: the first ``--launch`` scans (17 while the feed
  started its world at the arming: take-off and climb) taken from s_0 with the app tracking only
  (no plan, the vehicle held there), the plans from scan ``--launch`` on;
- ``demo``: both (the demo's limits and that launch: the demo as it was; the demo now is
  ``demo_limits``, its world starting with the UAV at h).

Each variant runs ``--repeats`` draws of the DF's noise and the filter's particles on the same
world (the same draws for every variant: repeat r uses the evaluation's streams of trial r for
the method ``flight``), so the world's difficulty is told from a draw's luck. ``--starts S``
also runs ``eval`` from S of the evaluation's random UAV starts (seed 2024's trials 0..S-1, one
repeat each): whether s_0 is a hard start. ``--runs DIR_PATTERN`` (e.g. '/tmp/before_s{seed}')
scores the demo runs in those directories (sim/stack/demo.py ``score``) and replays each one's
recorded bearings, from where the demo's UAV was, through the core tick (tracking only,
``--replay-draws`` draws of the filter; ``--replay-guidance-s``: with the app's wall-time limit on
each guidance call): the filter on the demo's own data, to tell the app from the path.
``--repeats 0`` runs no closed loop (only the replays).

Figures: r = the per-mission RMSE from 10 s over all targets (``pmon eval``'s per-trial figure,
the demo's "this mission"), and the mean over targets of each target's RMSE from 10 s; per seed,
the mean over the repeats (and their min-max), and the per-target RMSEs. Last line: JSON.
"""
from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

from sim.evaluation.workers import one_blas_thread

# before numpy loads BLAS: the side-aware filter amplifies last-bit differences (sim/evaluation/trials.py
# run_trials), so only one thread gives the same figures in this process as in the workers
one_blas_thread()

import numpy as np

from bench import add_set_option, set_label, set_overrides
from onboard.config import load_scenario
from onboard.core.guidance.predictor import GuidanceWorkspace
from onboard.core.monitor import Scan, UavState, initial_state, tick
from sim.evaluation import trials as ev
from sim.mock.guided import enu, fly_plan, ned
from sim.mock.multicopter import VehicleState
from sim.truth.sensors import df_scan
from sim.truth.world import simulate_truth

VARIANTS = {  # name -> (autopilot parameters, launch)
    "eval": ("stock", False),
    "demo_limits": ("demo", False),
    "launch": ("stock", True),
    "demo": ("demo", True),
}
DEMO_LAUNCH_SCANS = 17  # scans the demo took before the app monitored, its world started at the arming (seeds 1-5)
EVAL_SEED = 2024  # pmon eval paper's seed: its UAV starts for --starts


@functools.lru_cache(maxsize=8)
def demo_truth(sc, seed: int, n_scans: int) -> tuple[np.ndarray, np.ndarray]:
    """The truth (K, M, 6) and closed-loop gains of ``pmon feed live --seed N`` (sim/stack/live_feed.py):
    its truth world is drawn from the first of ``SeedSequence(seed).spawn(2)``."""
    truth_seq, _ = np.random.SeedSequence(seed).spawn(2)
    return simulate_truth(sc, n_scans - 1, np.random.default_rng(truth_seq), with_gains=True)


def wall_stops(truth: np.ndarray) -> list[tuple[int, str]]:
    """(scan k, target) where the truth held a target at an obstacle with zero velocity (sim/truth/world.py:
    every noise draw and the noise-free step entered it)."""
    K, M = truth.shape[:2]
    return [(k, f"T{j + 1}") for k in range(1, K) for j in range(M) if not np.any(truth[k, j, 3:6])]


def fly(cfg: ev.EvalConfig, method: ev.Method, repeat: int, truth: np.ndarray, start: np.ndarray,
        launch: int = 0) -> np.ndarray:
    """The horizontal errors (K, M) of ``method`` flown on ``truth`` from ``start`` with the
    streams of trial ``repeat`` of the method ``flight``; the first ``launch`` scans from the
    start, tracking only (the demo's launch), planned and flown from scan ``launch`` on.
    ``launch`` 0 is ``sim.evaluation.trials.run_method`` tick for tick (test: --check)."""
    setup, df, limits = ev._setup_for(cfg, method)
    ss = np.random.SeedSequence(cfg.seed, spawn_key=(repeat, 2, ev._method_key("flight")))
    sensor_rng, filter_rng, policy_rng = (np.random.default_rng(s) for s in ss.spawn(3))
    K = truth.shape[0]
    state, ws = initial_state(setup, filter_rng), GuidanceWorkspace()
    uav, uav_vel = np.asarray(start, float).copy(), np.zeros(2)
    ramps = setup.motion.jerk_max_mps3 > 0.0
    uav_acc = np.zeros(2) if ramps else None
    vehicle = VehicleState(pos=ned(uav))
    err = np.zeros(truth.shape[:2])
    for k in range(K):
        scans = [Scan(uav.copy(), df_scan(truth[k], uav, df, sensor_rng))]
        flying = k >= launch
        state, res = tick(setup, state, scans, filter_rng, plan_from=UavState(uav, uav_vel, uav_acc) if flying else None,
                          workspace=ws, planner_rng=policy_rng)
        err[k] = np.linalg.norm(res.means[:, :2] - truth[k, :, :2], axis=1)
        if k == K - 1 or not flying:
            continue
        p = res.planning
        v_next = np.asarray(p.velocities[p.index], float)[:2] if p is not None and p.index is not None else None
        vehicle = fly_plan(vehicle, v_next, setup.grid.altitude_m, setup.model.dt_s, limits, first=k == launch,
                           a_k=uav_acc)
        if ramps:
            uav_acc = np.zeros(2) if v_next is None else 2.0 * (v_next - uav_vel) / setup.model.dt_s - uav_acc
        uav, uav_vel = enu(vehicle.pos), enu(vehicle.vel)[:2]
    return err


def replay(sc, run_dir: Path, draws: int = 5, guidance_s: float | None = None) -> list[np.ndarray]:
    """The demo run's recorded bearings, each from where its UAV was (truth.jsonl), through the
    core tick of the flight policy, tracking only: errors (K, M) per draw of the filter.
    ``guidance_s``: each guidance call's wall-time limit (the app's: PMON_GUID_S / speedup / M,
    onboard/app/tick/worker.py; None: none, as the evaluation)."""
    from onboard.core.monitor import MonitorSetup
    from onboard.policy import with_policy

    rec = [json.loads(line) for line in open(run_dir / "truth.jsonl") if line.strip()]
    rec = [r for r in rec if "header" not in r]
    setup = MonitorSetup.from_scenario(with_policy(sc, "flight"))
    if guidance_s is not None:
        setup = replace(setup, guidance=replace(setup.guidance, max_solve_time_s=guidance_s))
    truth = np.array([r["targets"] for r in rec])
    out = []
    for d in range(draws):
        rng = np.random.default_rng(d)
        state, ws = initial_state(setup, rng), GuidanceWorkspace()
        err = np.zeros(truth.shape[:2])
        for k, r in enumerate(rec):
            uav = np.array(r["uav_enu"], float)
            bearings = tuple(np.asarray(b, float) for b in r["bearings"])
            state, res = tick(setup, state, [Scan(uav, bearings)], rng, workspace=ws)
            err[k] = np.linalg.norm(res.means[:, :2] - truth[k, :, :2], axis=1)
        out.append(err)
    return out


def figures(err: np.ndarray, w0: int) -> tuple[float, float, list[float]]:
    """(r: RMSE over the window and all targets, the mean over targets of each one's window
    RMSE, the per-target window RMSEs), m."""
    per = np.sqrt((err[w0:] ** 2).mean(axis=0))
    return float(np.sqrt((err[w0:] ** 2).mean())), float(per.mean()), per.round(1).tolist()


def _job(sc, n_scans: int, launch: int, job: tuple) -> tuple:
    kind, seed, variant, repeat = job
    cfg = ev.make_config(sc, 1, EVAL_SEED, ["flight@stock", "flight@demo"])
    truth, _ = demo_truth(sc, seed, n_scans)
    autopilot, launched = VARIANTS[variant]
    method = ev.method_named(f"flight@{autopilot}", sc)
    if kind == "start":  # the evaluation's random start of trial ``repeat``
        start = ev.draw_start(cfg, ev._rng(EVAL_SEED, repeat, 1))
    else:
        start = np.array([*sc.uav.start_m[:2], sc.uav.altitude_m])
    t0 = time.perf_counter()
    err = fly(cfg, method, repeat, truth, start, launch if launched else 0)
    return job, err, time.perf_counter() - t0


def check(sc, n_scans: int) -> bool:
    """``fly`` without a launch gives ``run_method``'s errors (the evaluation's loop, seed 1's world)."""
    cfg = ev.make_config(sc, 1, EVAL_SEED, ["flight@stock"])
    truth, gains = demo_truth(sc, 1, n_scans)
    start = np.array([*sc.uav.start_m[:2], sc.uav.altitude_m])
    m = replace(cfg.methods[0], name="flight")  # the streams ``fly`` uses
    ours = fly(cfg, cfg.methods[0], 0, truth, start)
    theirs = ev.run_method(cfg, replace(m, autopilot="stock"), 0, truth, start).error_m
    return bool(np.array_equal(ours, theirs))


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m bench.demo_world", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1,2,3,4,5")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--launch", type=int, default=DEMO_LAUNCH_SCANS, help="scans of the demo's launch")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--starts", type=int, default=0, help="also fly 'eval' from this many of the eval's starts")
    ap.add_argument("--runs", help="demo run directories, '{seed}' for the seed: scored and replayed")
    ap.add_argument("--replay-draws", type=int, default=10, help="--runs: draws of the filter per run")
    ap.add_argument("--replay-guidance-s", type=float, default=None,
                    help="--runs: each guidance call's wall-time limit, s (the app's PMON_GUID_S / speedup / "
                         "targets; default none, as the evaluation)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--check", action="store_true", help="only check fly() against sim.evaluation.trials.run_method")
    add_set_option(ap)
    return ap


def main(argv=None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    sc = load_scenario("paper", set_overrides(ap, args))
    n_scans = int(round(sc.mission.duration_s / sc.dynamics.dt_s))
    w0 = int(round(ev.DEFAULT_WINDOW_S / sc.dynamics.dt_s))
    if args.check:
        ok = check(sc, n_scans)
        print(json.dumps({"bench": "demo_world", "check_run_method": ok}))
        return 0 if ok else 1
    seeds = [int(s) for s in args.seeds.split(",")]
    variants = [v for v in args.variants.split(",") if v]
    if unknown := [v for v in variants if v not in VARIANTS]:
        ap.error(f"unknown variant {unknown[0]!r} (one of {', '.join(VARIANTS)})")
    jobs = [("s0", s, v, r) for s in seeds for v in variants for r in range(args.repeats)]
    jobs += [("start", s, "eval", r) for s in seeds for r in range(args.starts)]
    for s in seeds:
        print(f"seed {s}'s world: wall stops (scan, target) {wall_stops(demo_truth(sc, s, n_scans)[0])}")
    print(f"demo worlds {seeds}, {args.repeats} draws each, variants {', '.join(variants)}, launch {args.launch} "
          f"scans{set_label(args)}; {len(jobs)} closed loops on {args.workers} worker(s)", flush=True)
    results = _run_jobs(functools.partial(_job, sc, n_scans, args.launch), jobs, args.workers)
    out: dict = {"bench": "demo_world", "seeds": seeds, "repeats": args.repeats, "launch": args.launch,
                 "variants": {}, "demo_runs": {}, "replay": {}, "starts": {}}
    print(f"\nper seed: r (RMSE from {ev.DEFAULT_WINDOW_S:g} s, all targets) mean over draws [min-max]; "
          "mean per-target RMSE; per target (mean over draws)")
    for v in variants if args.repeats else ():
        out["variants"][v] = _variant_rows(results, v, seeds, args.repeats, w0)
    if args.starts:
        for s in seeds:
            r_ = np.array([figures(results[("start", s, "eval", r)], w0)[0] for r in range(args.starts)])
            out["starts"][s] = {"r_mean": round(float(r_.mean()), 2), "r_median": round(float(np.median(r_)), 2)}
            print(f"eval from {args.starts} random starts, s{s}: r mean {r_.mean():.1f}, median {np.median(r_):.1f}")
    if args.runs:
        _demo_runs(sc, args, seeds, w0, out)
    print(json.dumps(out))
    return 0


def _run_jobs(run, jobs: list, workers: int) -> dict:
    """Each job's errors by job, on ``workers`` spawned processes (or in this one)."""
    results: dict = {}
    if workers > 1 and jobs:
        import multiprocessing as mp

        from sim.evaluation.workers import worker_pool
        with worker_pool(mp.get_context("spawn"), workers) as pool:
            for i, (job, err, wall) in enumerate(pool.imap_unordered(run, jobs), 1):
                results[job] = err
                print(f"  {i}/{len(jobs)} {job} {wall:.0f} s", flush=True)
    else:
        for i, job in enumerate(jobs, 1):
            job, results[job], wall = run(job)
            print(f"  {i}/{len(jobs)} {job} {wall:.0f} s", flush=True)
    return results


def _variant_rows(results: dict, v: str, seeds: list[int], repeats: int, w0: int) -> dict:
    """A variant's figures per seed over its draws, printed."""
    rows = {}
    for s in seeds:
        figs = [figures(results[("s0", s, v, r)], w0) for r in range(repeats)]
        r_ = np.array([f[0] for f in figs])
        rows[s] = {"r_mean": round(float(r_.mean()), 2), "r_min": round(float(r_.min()), 2),
                   "r_max": round(float(r_.max()), 2),
                   "per_target_mean": round(float(np.mean([f[1] for f in figs])), 2),
                   "per_target": np.mean([f[2] for f in figs], axis=0).round(1).tolist()}
    print(f"{v:>12}: " + "  ".join(f"s{s} {x['r_mean']:5.1f} [{x['r_min']:.1f}-{x['r_max']:.1f}] "
                                    f"{x['per_target_mean']:.1f}" for s, x in rows.items())
          + f"  | mean r {np.mean([x['r_mean'] for x in rows.values()]):.1f}, "
          f"per-target {np.mean([x['per_target_mean'] for x in rows.values()]):.1f}")
    for s, x in rows.items():
        print(f"{'':>14}s{s} per target {x['per_target']}")
    return rows


def _demo_runs(sc, args, seeds: list[int], w0: int, out: dict) -> None:
    """--runs: each seed's demo run scored, and its bearings replayed (tracking only), into ``out``."""
    from sim.stack.demo import score
    for s in seeds:
        d = Path(args.runs.format(seed=s))
        if not (d / "run.jsonl").exists():
            continue
        rep = score(d / "run.jsonl", d / "truth.jsonl", sc)
        figs = [figures(e, w0) for e in replay(sc, d, args.replay_draws, args.replay_guidance_s)]
        r_ = [round(f[0], 1) for f in figs]
        out["demo_runs"][s] = {"r": rep["mission_rmse_m"], "per_target": rep["rmse_window_m"]}
        out["replay"][s] = {"r_mean": round(float(np.mean(r_)), 2), "r": r_,
                            "per_target": np.mean([f[2] for f in figs], axis=0).round(1).tolist()}
        print(f"demo run {d}: r {rep['mission_rmse_m']}, per target {rep['rmse_window_m']}; its bearings "
              f"replayed (tracking only, {args.replay_draws} draws, guidance limit {args.replay_guidance_s} s): "
              f"r {out['replay'][s]['r_mean']} (draws {min(r_)}-{max(r_)}), "
              f"per target {out['replay'][s]['per_target']}")


if __name__ == "__main__":
    sys.exit(main())
