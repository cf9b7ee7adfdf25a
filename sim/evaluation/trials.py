"""Monte Carlo evaluation of the monitor (Sec. V of the paper): truth, sensors, methods, metrics.

The closed loop runs the flight code itself (``onboard.core.monitor.tick``); nothing of the
algorithm is copied here. One *trial* is one draw of the world:

* the true target trajectories (``sim.truth.world``: each target's own guidance from its true state,
  noise Q), computed once per trial and shared by every method;
* the UAV start, uniform over the area at altitude h, outside the (inflated) obstacles, shared
  by every UAV method (the paper: "in each trial the UAV initial position was randomly
  initialized inside the surveillance area");
* per method, its own random streams (sensor, filter, policy) derived from (seed, trial, method
  name) with ``numpy.random.SeedSequence``, so adding or removing a method changes no other
  method's numbers, and a trial's result does not depend on which worker ran it.

Timeline of a tick k = 0..K-1 (t = k dt): the sensors scan the truth at k from where they are;
the monitor updates, predicts and (greedy) picks the UAV position for k+1; the policy moves the
UAV there. So the UAV moves at most N_r Delta_r per tick and the estimates at tick k are
posterior estimates given the scans up to k.

Methods are registered by name in ``METHODS`` (name -> ``Method``; both in sim/evaluation/methods.py); a method is a sensing mode
and, for a UAV, the planner the monitor's tick runs (``onboard.core.planning.planners``: the paper's
greedy rule, the lookahead; sim/evaluation/baselines.py: the baselines hover, orbit, random). A new method registers
itself with ``register_method``.

The configuration (``make_config``) is in sim/evaluation/config.py, the metrics (``summarise``) in
sim/evaluation/summary.py; this module runs the trials and is the evaluation's interface (``__all__``).
"""
from __future__ import annotations

import os
import time
import zlib
from dataclasses import replace
from typing import Sequence

import numpy as np

from onboard.core.guidance.predictor import GuidanceWorkspace
from onboard.core.planning.information import information_reduction_factor
from onboard.core.monitor import MonitorSetup, Scan, UavState, initial_state, tick
from sim.evaluation.config import DEFAULT_WINDOW_S, EvalConfig, _setup_for, make_config, method_named
from sim.evaluation.summary import summarise
from sim.mock.guided import enu, fly_plan, ned
from sim.evaluation.methods import AUTOPILOTS, DEFAULT_METHODS, METHODS, Method, register_method
from sim.mock.multicopter import VehicleLimits, VehicleState
from sim.evaluation.metrics import (BOOTSTRAP_RESAMPLES, FIXED, REFERENCE, MethodSummary, MethodTrace, Summary, TrialResult,
                         is_flight, nees_band, pcrb_position, seeded_rng, t_interval)
from sim.evaluation.numerics import pin_kernels
from sim.evaluation.report import headline, machine_description, results_markdown, write_csv, write_outputs, write_per_trial_csv
from sim.truth.sensors import FIXED_SENSORS_M, df_scan, fixed_scans
from sim.truth.kinds import KindDraw, draw_kind, filter_scenario, simulate_kind
from sim.evaluation.workers import one_blas_thread as _one_blas_thread, worker_pool as _worker_pool

# the evaluation's interface, wherever its parts are held (sim.evaluation.methods: the methods; sim.evaluation.config: the
# configuration; sim.evaluation.summary: the summary; sim.evaluation.metrics: the statistics; sim.evaluation.report: the outputs)
__all__ = ["AUTOPILOTS", "DEFAULT_METHODS", "DEFAULT_WINDOW_S", "METHODS", "Method", "register_method", "EvalConfig",
           "make_config", "method_named", "MethodTrace", "TrialResult", "draw_start", "run_method", "run_trial",
           "run_trials", "summarise", "REFERENCE", "FIXED", "BOOTSTRAP_RESAMPLES", "MethodSummary", "Summary",
           "nees_band", "t_interval", "pcrb_position", "is_flight", "headline", "write_csv", "write_per_trial_csv",
           "machine_description", "results_markdown", "write_outputs"]


# --------------------------------------------------------------------------- one trial


_rng = seeded_rng


def _method_key(name: str) -> int:
    return zlib.crc32(name.encode("utf-8"))  # stable across processes (unlike hash())


def draw_start(cfg: EvalConfig, rng: np.random.Generator) -> np.ndarray:
    """UAV start: uniform over the area's (x, y), at altitude h, outside the UAV's obstacles."""
    setup = MonitorSetup.from_scenario(cfg.scenario)
    lo, hi = setup.area_min, setup.area_max
    for _ in range(1000):
        p = np.array([rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1]), setup.grid.altitude_m])
        if not len(setup.uav_obstacles) or not setup.uav_obstacles.contains(p).any():
            return p
    raise RuntimeError("could not draw a UAV start outside the obstacles in 1000 tries")


def _true_columns(setup: MonitorSetup, cfg: EvalConfig, draw: KindDraw | None) -> np.ndarray | None:
    """Per target, the column of its filter's modes that is what it really does (its true goal's,
    or stationary's); -1 where none is; None for a filter without modes."""
    if setup.intents is None:
        return None
    out = np.full(setup.n_targets, -1)
    for j, intent in enumerate(setup.intents):
        if cfg.truth_kind == "stationary":
            out[j] = intent.n_goals
        elif cfg.truth_kind in ("nominal", "candidate_goal"):
            name = cfg.scenario.targets[j].goal if draw is None else draw.goal_names[j]
            if name in intent.names:
                out[j] = intent.names.index(name)
    return out


def trial_draw(cfg: EvalConfig, trial: int) -> KindDraw | None:
    """The truth kind's choices for a trial (None for the nominal truth)."""
    if cfg.truth_kind == "nominal":
        return None
    return draw_kind(cfg.scenario, cfg.truth_kind, _rng(cfg.seed, trial, 3), cfg.n_ticks - 1)


def run_method(cfg: EvalConfig, method: Method, trial: int, truth: np.ndarray, start: np.ndarray,
               gains: np.ndarray | None = None, path: np.ndarray | None = None) -> MethodTrace:
    """Closed loop of one method on one trial's truth (K, M, 6); with the truth's closed-loop
    gains (K-1, M, 3, 6), also the PCRB along the flown path. ``path`` (K, 2): the UAV's
    positions given in advance (``Method.follows``; its start first): no planning, no flight."""
    draw = trial_draw(cfg, trial)
    if cfg.told:
        cfg = replace(cfg, scenario=filter_scenario(cfg.scenario, cfg.truth_kind, draw, told=True))
    setup, df, limits = _setup_for(cfg, method)
    true_col = _true_columns(setup, cfg, draw)
    if path is not None:
        limits = None
    ss = np.random.SeedSequence(cfg.seed, spawn_key=(trial, 2, _method_key(method.name)))
    sensor_rng, filter_rng, policy_rng = (np.random.default_rng(s) for s in ss.spawn(3))
    K, M = truth.shape[0], truth.shape[1]
    state = initial_state(setup, filter_rng)
    ws = GuidanceWorkspace()  # per method and trial: OSQP warm starts never leak between runs
    uav = None if method.sensing == "fixed" else np.asarray(start, float).copy()
    uav_vel = np.zeros(2)  # planar UAV velocity at ``uav`` (vehicle motion); starts in hover
    uav_acc = np.zeros(2) if _ramps(setup) else None  # the plan's acceleration there (continuous acceleration)
    err, nees, est = np.zeros((K, M)), np.zeros((K, M)), np.zeros((K, M, 2))
    mode_p = None if true_col is None else np.full((K, M), np.nan)
    reseeds = None if true_col is None else np.zeros((K, M), dtype=bool)
    uav_track = None if uav is None else np.zeros((K, 3))
    degenerate, tick_time = 0, 0.0
    if limits is not None:  # flown: a copter hovering at the start, in GUIDED
        vehicle = VehicleState(pos=ned(uav))
        miss, plan_speed, speed = np.zeros(K - 1), np.zeros(K - 1), np.zeros(K)
    for k in range(K):
        if uav is None:
            scans = fixed_scans(truth[k], FIXED_SENSORS_M, setup.sensor.sigma_rad, sensor_rng)
        else:
            uav_track[k] = uav
            scans = [Scan(uav.copy(), df_scan(truth[k], uav, df, sensor_rng))]
        t0 = time.perf_counter()
        plan_from = None if path is not None or uav is None else UavState(uav, uav_vel, uav_acc)
        state, res = tick(setup, state, scans, filter_rng, plan_from=plan_from, workspace=ws, planner_rng=policy_rng)
        tick_time += time.perf_counter() - t0
        e = res.means[:, :2] - truth[k, :, :2]
        est[k] = res.means[:, :2]
        err[k] = np.linalg.norm(e, axis=1)
        P = res.covs[:, :2, :2]
        nees[k] = np.einsum("mi,mi->m", e, np.linalg.solve(P, e[..., None])[..., 0])
        degenerate += int(res.degenerate.sum())
        if mode_p is not None and res.mode_probabilities is not None:
            mode_p[k] = [p[c] if c >= 0 else np.nan for p, c in zip(res.mode_probabilities, true_col)]
            reseeds[k] = res.reseeded
        if path is not None and k < K - 1:
            uav = np.array([path[k + 1, 0], path[k + 1, 1], setup.grid.altitude_m])
        elif uav is not None and k < K - 1 and limits is not None:
            vehicle, uav, uav_vel, uav_acc, miss[k], plan_speed[k] = _fly_tick(setup, limits, res, vehicle, uav,
                                                                             uav_vel, uav_acc, k == 0)
            speed[k + 1] = float(np.linalg.norm(uav_vel))
        elif uav is not None and k < K - 1:
            uav, uav_vel = _jump_tick(res, uav)
    bound = None if gains is None else _path_bound(setup, truth, gains, uav_track)
    flown = {} if limits is None else dict(plan_miss_m=miss, plan_speed_mps=plan_speed, speed_mps=speed)
    return MethodTrace(err, nees, est, uav_track, degenerate, tick_time / K, bound, **flown, true_mode_prob=mode_p,
                       reseeds=reseeds)


def _ramps(setup: MonitorSetup) -> bool:
    """Whether plans carry their acceleration over (vehicle motion with a jerk limit)."""
    return setup.motion.kind == "vehicle" and setup.motion.jerk_max_mps3 > 0.0


def _fly_tick(setup: MonitorSetup, limits: VehicleLimits, res, vehicle: VehicleState, uav: np.ndarray,
              uav_vel: np.ndarray, uav_acc: np.ndarray | None, first: bool):
    """A flown method's move after a tick (``res``): the copter flies the plan's next velocity.
    Returns the vehicle, its ENU position and planar velocity, the next plan's starting
    acceleration, its distance from the planned point (m) and the plan's speed (m/s)."""
    p = res.planning
    ok = p is not None and p.index is not None
    v_next = np.asarray(p.velocities[p.index], float)[:2] if ok else None
    planned = p.position[:2] if ok else uav[:2]
    vehicle = fly_plan(vehicle, v_next, setup.grid.altitude_m, setup.model.dt_s, limits, first=first, a_k=uav_acc)
    if _ramps(setup):  # where the plan's acceleration ended: the next plan's starts there
        uav_acc = np.zeros(2) if v_next is None else 2.0 * (v_next - uav_vel) / setup.model.dt_s - uav_acc
    uav, uav_vel = enu(vehicle.pos), enu(vehicle.vel)[:2]
    return (vehicle, uav, uav_vel, uav_acc, float(np.linalg.norm(uav[:2] - planned)),
            0.0 if v_next is None else float(np.linalg.norm(v_next)))


def _jump_tick(res, uav: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A method's move after a tick when it flies no vehicle: to the tick's next position, at the
    plan's velocity there. Returns the position and the planar velocity."""
    nxt = res.next_position
    p = res.planning
    if p is not None and p.index is not None and p.velocities is not None:
        uav_vel = np.asarray(p.velocities[p.index], float)[:2].copy()
    else:
        uav_vel = np.zeros(2)  # no admissible move (or a baseline's): the vehicle stops where it is
    return (uav if nxt is None else np.asarray(nxt, float).copy()), uav_vel


def _path_bound(setup: MonitorSetup, truth: np.ndarray, gains: np.ndarray, uav_track: np.ndarray | None) -> np.ndarray:
    """The PCRB along the sensors' positions: the fixed DFs' (``uav_track`` None) or the UAV's."""
    K = truth.shape[0]
    if uav_track is None:
        sensors = np.broadcast_to(np.asarray(FIXED_SENSORS_M, float)[None, :, :2], (K, len(FIXED_SENSORS_M), 2))
        q = 1.0  # the fixed DFs: p_D = 1, no clutter
    else:
        sensors = uav_track[:, None, :2]
        q = information_reduction_factor(setup.sensor.p_detect, setup.sensor.clutter_rate, setup.sensor.sigma_rad)
    return pcrb_position(setup.model, setup.initial_cov, truth, gains, sensors, setup.sensor.sigma_rad, q)


def _ceiling_trace(cfg: EvalConfig, method: Method, truth: np.ndarray, gains: np.ndarray, path: np.ndarray,
                   cpu_s: float) -> MethodTrace:
    """A bound-only method's trace: its path (K, 2) and the PCRB along it; the error, NEES and
    estimates NaN (no filter runs); tick_s: the search's CPU time per tick."""
    setup, _, _ = _setup_for(cfg, method)
    K, M = truth.shape[:2]
    q = information_reduction_factor(setup.sensor.p_detect, setup.sensor.clutter_rate, setup.sensor.sigma_rad)
    bound = pcrb_position(setup.model, setup.initial_cov, truth, gains, path[:, None], setup.sensor.sigma_rad, q)
    nan = np.full((K, M), np.nan)
    uav = np.column_stack([path, np.full(K, setup.grid.altitude_m)])
    return MethodTrace(nan, nan.copy(), np.full((K, M, 2), np.nan), uav, 0, cpu_s / K, bound)


def run_trial(cfg: EvalConfig, trial: int) -> TrialResult:
    """One trial of every method: truth once, the same truth and UAV start for all. The
    clairvoyant ceiling's path (``sim.evaluation.ceiling_search.ceiling_path``), for a bound-only method
    or one that follows it, is searched once per vehicle limits after the other methods ran,
    with their flown paths at those limits as extra starts of its search."""
    from sim.evaluation.ceiling_search import ceiling_path

    t0 = time.perf_counter()
    truth, gains = simulate_kind(cfg.scenario, cfg.n_ticks - 1, _rng(cfg.seed, trial, 0), cfg.truth_kind,
                                 _rng(cfg.seed, trial, 3), with_gains=True)
    start = draw_start(cfg, _rng(cfg.seed, trial, 1))
    planned = [m for m in cfg.methods if not m.bound_only and m.follows is None]
    traces = {m.name: run_method(cfg, m, trial, truth, start, gains) for m in planned}
    ceilings: dict = {}  # UavMotion -> (path (K, 2), CPU s)
    for m in cfg.methods:
        if m in planned:
            continue
        setup = _setup_for(cfg, m)[0]
        if setup.motion not in ceilings:
            given = [traces[o.name].uav[:, :2] for o in planned
                     if o.sensing == "uav" and _setup_for(cfg, o)[0].motion == setup.motion]
            c0 = time.process_time()
            path = ceiling_path(setup, truth, gains, start, cfg.window_start, given)
            ceilings[setup.motion] = (path, time.process_time() - c0)
        path, cpu = ceilings[setup.motion]
        traces[m.name] = (_ceiling_trace(cfg, m, truth, gains, path, cpu) if m.bound_only else
                          run_method(cfg, m, trial, truth, start, gains, path=path))
    traces = {m.name: traces[m.name] for m in cfg.methods}
    return TrialResult(trial, start, truth, traces, time.perf_counter() - t0, gains)


# --------------------------------------------------------------------------- running many trials

def run_trials(cfg: EvalConfig, workers: int | None = None, scheduler: str | None = None,
               progress: bool = True, console=None, trials: Sequence[int] | None = None) -> list[TrialResult]:
    """All trials (or those numbered ``trials``: each exactly as in a run of them all), in trial
    order. workers: local processes (default os.cpu_count()), each with one BLAS thread;
    scheduler: a Dask distributed scheduler address instead of local processes."""
    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    console = console or Console(stderr=True)
    bar = Progress(TextColumn("[bold]eval[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                   TextColumn("trials"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                   console=console, disable=not progress, transient=False, refresh_per_second=2)
    results: list[TrialResult] = []
    ids = list(range(cfg.n_trials)) if trials is None else [int(i) for i in trials]
    n = len(ids)
    label = f"{len(cfg.methods)} methods x {cfg.n_ticks} ticks"
    if scheduler is not None:
        from dask.distributed import Client, as_completed

        with Client(scheduler, timeout="20s") as client, bar:
            task = bar.add_task(label + f" on {scheduler}", total=n)
            futures = client.map(run_trial, [cfg] * n, ids, pure=False)
            for fut in as_completed(futures):
                results.append(fut.result())
                bar.advance(task)
    else:
        workers = (os.cpu_count() or 1) if workers is None else int(workers)
        if workers < 1:
            raise ValueError(f"--workers must be >= 1, got {workers}")
        workers = min(workers, n)
        with bar:
            task = bar.add_task(label + f" on {workers} local worker(s)", total=n)
            import functools
            import multiprocessing as mp

            # even one worker is a spawned process: BLAS sums in another order with more threads
            # (this process's numpy may have them), and the plan-steering filter amplifies last-bit
            # differences, so only workers with one BLAS thread each give the same trials whatever K
            _one_blas_thread()  # inherited by the spawned workers' environment
            pin_kernels()  # the AVX2 kernels on every x86-64 that has them: the same figures there (sim/evaluation/numerics.py)
            ctx = mp.get_context("spawn")  # no fork of a process with threads (the progress bar)
            # stopped for any reason, the workers go at once: none computes trials nobody reads
            try:
                with _worker_pool(ctx, workers) as pool:
                    for res in pool.imap_unordered(functools.partial(run_trial, cfg), ids):
                        results.append(res)
                        bar.advance(task)
            except BaseException:
                console.print(f"eval: stopped after {len(results)} of {n} trials; workers terminated")
                raise
    return sorted(results, key=lambda r: r.trial)
