"""Monte Carlo evaluation of the monitor (Sec. V of the paper): truth, sensors, methods, metrics.

The closed loop runs the flight code itself (``onboard.core.monitor.tick``); nothing of the
algorithm is copied here. One *trial* is one draw of the world:

* the true target trajectories (``sim.truth``: each target's own guidance from its true state,
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

Methods are registered by name in ``METHODS`` (name -> ``Method``; both in sim/methods.py); a method is a sensing mode
and, for a UAV, the planner the monitor's tick runs (``onboard.core.planners``: the paper's
greedy rule, the lookahead, and the baselines hover, orbit, random). A new method registers
itself with ``register_method``.

Metrics (``summarise``), all on the horizontal position (x, y) in metres:

* eps_t (the paper's RMSE at step t): sqrt of the mean over trials of |x^_t - x_t|^2, per target;
  "averaged over targets" is the mean over the M targets of the per-target eps_t;
* ``rmse_mean_m``: the time average of the target-averaged eps_t over the convergence window
  t in [window_start, K) (default: from 10 s on; the second half if the mission is shorter);
* per-trial RMSE r_n = sqrt(mean over window steps and targets of |error|^2): the paired
  differences r_n(method) - r_n(greedy_l1) over the same trials, with a 95 % t-interval;
* ``uav_vs_fixed_ratio`` = rmse_mean_m(greedy_l1) / rmse_mean_m(fixed3), 95 % CI by a paired
  percentile bootstrap over trials (trials resampled with replacement, both methods together);
* NEES on the 2-D position: e^T P^-1 e with P the filter's (x, y) covariance; a consistent
  filter has E = 2. The average over N trials, per step and target (ANEES), has the 95 % band
  [chi2_(0.025)(2N), chi2_(0.975)(2N)] / N. ``nees_mean`` is ANEES averaged over targets and the
  window; ``nees_in_band`` is the fraction of (step, target) cells whose ANEES is in the band.
  (The full 6-D state is not used: z and v_z have variances of 1e-10 by construction and their
  NEES would measure round-off.)
"""
from __future__ import annotations

import math
import os
import time
import zlib
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np

from onboard.config import ConfigError, override
from onboard.core.guidance import GuidanceWorkspace
from onboard.core.information import information_reduction_factor
from onboard.core.monitor import MonitorSetup, Scan, initial_state, tick
from onboard.core.planners import ORBIT_RADIUS_M, orbit_centre
from onboard.policy import vehicle_motion
from sim.guided import enu, fly_plan, ned
from sim.methods import AUTOPILOTS, DEFAULT_METHODS, METHODS, Method, method_scenario, register_method
from sim.multicopter import VehicleLimits, VehicleState, limits_from_params
from sim.metrics import (BOOTSTRAP_RESAMPLES, FIXED, REFERENCE, MethodSummary, MethodTrace, Summary, TrialResult,
                         bound_summary, is_flight, motion_stats, nees_band, paired_bound_ratio, paired_ratio, pcrb_position, seeded_rng, t_interval,
                         truth_stats)
from sim.numerics import pin_kernels
from sim.report import headline, machine_description, results_markdown, write_csv, write_outputs, write_per_trial_csv
from sim.sensors import FIXED_SENSORS_M, DirectionFinder, df_scan, fixed_scans
from sim.truth_kinds import KindDraw, check_kind, draw_kind, filter_scenario, simulate_kind
from sim.workers import one_blas_thread as _one_blas_thread, worker_pool as _worker_pool

# the evaluation's interface, wherever its parts are held (sim.methods: the methods; sim.metrics: the
# statistics; sim.report: the outputs)
__all__ = ["AUTOPILOTS", "DEFAULT_METHODS", "DEFAULT_WINDOW_S", "METHODS", "Method", "register_method", "EvalConfig",
           "make_config", "method_named", "MethodTrace", "TrialResult", "draw_start", "run_method", "run_trial",
           "run_trials", "summarise", "REFERENCE", "FIXED", "BOOTSTRAP_RESAMPLES", "MethodSummary", "Summary",
           "nees_band", "t_interval", "pcrb_position", "is_flight", "headline", "write_csv", "write_per_trial_csv",
           "machine_description", "results_markdown", "write_outputs"]

DEFAULT_WINDOW_S = 10.0  # convergence window: metrics are time-averaged from this time on


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True, eq=False)
class EvalConfig:
    scenario: Any  # onboard.config.Scenario
    n_trials: int
    seed: int
    methods: tuple[Method, ...]
    n_ticks: int
    window_start: int  # first tick of the convergence window
    truth_kind: str = "nominal"  # how the true targets move (sim/truth_kinds.py)
    told: bool = False  # the filter is told each trial what its targets really do (truth_kinds.filter_scenario)

    @property
    def method_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.methods)

    @property
    def orbit_radius_m(self) -> float:
        """The orbit baseline's radius (``onboard.core.planners.OrbitPlanner``), m."""
        return ORBIT_RADIUS_M

    @property
    def orbit_center(self) -> np.ndarray:
        """The orbit baseline's centre, the targets' initial centroid (ENU m, planar)."""
        return orbit_centre(MonitorSetup.from_scenario(self.scenario))

    @property
    def dt_s(self) -> float:
        return self.scenario.dynamics.dt_s


def make_config(sc, n_trials: int, seed: int, methods: Sequence[str] = DEFAULT_METHODS,
                duration_s: float | None = None, particles: int | None = None,
                window_s: float = DEFAULT_WINDOW_S, truth: str = "nominal", told: bool = False) -> EvalConfig:
    """Validated configuration. Raises ValueError with a one-line reason."""
    check_kind(sc, truth)
    if told and truth not in ("candidate_goal", "stationary"):
        raise ValueError(f"--told applies to --truth candidate_goal or stationary, not {truth}")
    sc = filter_scenario(sc, truth)
    if n_trials < 1:
        raise ValueError(f"--trials must be >= 1, got {n_trials}")
    if seed < 0:
        raise ValueError(f"--seed must be >= 0, got {seed}")
    names = list(methods)
    if not names:
        raise ValueError("--methods is empty")
    unknown = [m for m in names if m.partition("@")[0] not in METHODS]
    if unknown:
        raise ValueError(f"unknown method {unknown[0]!r} (known: {', '.join(METHODS)}; a vehicle method "
                         f"takes @{'|@'.join(AUTOPILOTS)})")
    if len(set(names)) != len(names):
        raise ValueError("--methods names a method twice")
    chosen = tuple(method_named(m, sc) for m in names)
    for option, key, value in (("--duration", "mission.duration_s", duration_s),
                               ("--particles", "tracking.particles", particles)):
        if value is not None:  # a setting of every method's scenario, checked as a file is
            try:
                sc = override(sc, {key: value})
            except ConfigError as exc:
                raise ValueError(f"{option} {value}: {exc}") from None
    for m in chosen:
        try:
            method_scenario(sc, m)
        except ConfigError as exc:
            raise ValueError(f"method {m.name}: {exc}") from None
    dt = sc.dynamics.dt_s
    duration = sc.mission.duration_s
    if not duration >= 2 * dt:
        raise ValueError(f"--duration must be at least 2 time steps ({2 * dt:g} s), got {duration_s}")
    n_ticks = int(round(duration / dt))
    # the window starts at window_s, or halfway when the mission is too short for that
    window_start = min(int(round(window_s / dt)), n_ticks // 2)
    return EvalConfig(sc, int(n_trials), int(seed), chosen, n_ticks, window_start, truth, told)


def method_named(name: str, sc=None) -> Method:
    """A registered method by name; ``NAME@LABEL`` is that method flown with the autopilot
    parameters ``AUTOPILOTS[LABEL]`` (a method of its own name, seeds and all). ValueError for
    a label on a method that flies no vehicle (under the scenario ``sc``, when given)."""
    base, at, label = name.partition("@")
    m = METHODS[base]
    if not at:
        return m
    if label not in AUTOPILOTS:
        raise ValueError(f"method {name!r}: unknown autopilot parameters {label!r} (one of {', '.join(AUTOPILOTS)})")
    try:  # its motion under its policy (a paper method's: the paper's jump)
        motion = m.motion or (None if sc is None else method_scenario(sc, m).planning.motion)
    except ConfigError as exc:
        raise ValueError(f"method {base}: {exc}") from None
    if m.sensing != "uav" or motion == "jump":
        raise ValueError(f"method {name!r}: {base} flies no vehicle (only vehicle-motion methods take @{label})")
    return replace(m, name=name, autopilot=label, description=f"{m.description}; autopilot: {label}")


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


def _setup_for(cfg: EvalConfig, method: Method) -> tuple[MonitorSetup, DirectionFinder | None, VehicleLimits | None]:
    """The method's monitor, its DF (None: fixed sensors) and, for a flown method, the vehicle's
    limits from its autopilot's parameters."""
    sc = method_scenario(cfg.scenario, method)
    flown = method.sensing != "fixed" and sc.planning.motion == "vehicle"  # the ceiling: its vehicle's limits
    limits = limits_from_params(AUTOPILOTS[method.autopilot or "stock"]) if flown else None
    if limits is not None and method.autopilot_limits:
        # PX4's OFFBOARD shapes no jerk (onboard/app/autopilot_profiles.py Px4): the scenario's stays
        jerk = limits.jerk_xy_max() if limits.shaping else math.inf
        m = vehicle_motion(sc.planning, limits.speed_xy, limits.accel_xy, jerk)
        sc = override(sc, {"planning.speed_max_mps": m.speed_max_mps, "planning.accel_max_mps2": m.accel_max_mps2,
                           "planning.jerk_max_mps3": m.jerk_max_mps3})
    df = None if method.sensing != "uav" else DirectionFinder.from_config(sc.sensor)
    setup = MonitorSetup.from_scenario(sc)
    if method.planner is not None and method.planner != setup.planner:
        # a planner a bench registered in PLANNERS (not one the flight app may be configured with)
        setup = replace(setup, planner=method.planner)
    return setup, df, limits


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
    ramps = setup.motion.kind == "vehicle" and setup.motion.jerk_max_mps3 > 0.0
    uav_acc = np.zeros(2) if ramps else None  # the plan's acceleration there (continuous acceleration)
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
        state, res = tick(setup, state, scans, filter_rng, plan_from=None if path is not None else uav,
                          workspace=ws, uav_velocity=uav_vel, planner_rng=policy_rng, uav_acceleration=uav_acc)
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
            p = res.planning
            ok = p is not None and p.index is not None
            v_next = np.asarray(p.velocities[p.index], float)[:2] if ok else None
            planned = p.position[:2] if ok else uav[:2]
            vehicle = fly_plan(vehicle, v_next, setup.grid.altitude_m, setup.model.dt_s, limits, first=k == 0,
                               a_k=uav_acc)
            if ramps:  # where the plan's acceleration ended: the next plan's starts there
                uav_acc = np.zeros(2) if v_next is None else 2.0 * (v_next - uav_vel) / setup.model.dt_s - uav_acc
            uav, uav_vel = enu(vehicle.pos), enu(vehicle.vel)[:2]
            miss[k] = float(np.linalg.norm(uav[:2] - planned))
            plan_speed[k] = 0.0 if v_next is None else float(np.linalg.norm(v_next))
            speed[k + 1] = float(np.linalg.norm(uav_vel))
        elif uav is not None and k < K - 1:
            nxt = res.next_position
            p = res.planning
            if p is not None and p.index is not None and p.velocities is not None:
                uav_vel = np.asarray(p.velocities[p.index], float)[:2].copy()
            else:
                uav_vel = np.zeros(2)  # no admissible move (or a baseline's): the vehicle stops where it is
            uav = uav if nxt is None else np.asarray(nxt, float).copy()
    bound = None
    if gains is not None:
        if uav_track is None:
            sensors = np.broadcast_to(np.asarray(FIXED_SENSORS_M, float)[None, :, :2], (K, len(FIXED_SENSORS_M), 2))
            q = 1.0  # the fixed DFs: p_D = 1, no clutter
        else:
            sensors = uav_track[:, None, :2]
            q = information_reduction_factor(setup.sensor.p_detect, setup.sensor.clutter_rate, setup.sensor.sigma_rad)
        bound = pcrb_position(setup.model, setup.initial_cov, truth, gains, sensors, setup.sensor.sigma_rad, q)
    flown = {} if limits is None else dict(plan_miss_m=miss, plan_speed_mps=plan_speed, speed_mps=speed)
    return MethodTrace(err, nees, est, uav_track, degenerate, tick_time / K, bound, **flown, true_mode_prob=mode_p,
                       reseeds=reseeds)


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
    clairvoyant ceiling's path (``sim.ceiling_search.ceiling_path``), for a bound-only method
    or one that follows it, is searched once per vehicle limits after the other methods ran,
    with their flown paths at those limits as extra starts of its search."""
    from sim.ceiling_search import ceiling_path

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
            pin_kernels()  # the AVX2 kernels on every x86-64 that has them: the same figures there (sim/numerics.py)
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


# --------------------------------------------------------------------------- the summary


def _flown_stats(cfg: EvalConfig, method: Method, traces: Sequence[MethodTrace]) -> dict:
    """How a flown method's vehicle followed its plans: the flown position's distance from the
    planned one at the next tick (median, p95, max over all ticks and trials), the plan's and
    the vehicle's speeds (mean over ticks, max), and the limits it planned and flew with."""
    if traces[0].plan_miss_m is None:
        return {}
    miss = np.concatenate([t.plan_miss_m for t in traces])
    plan_v = np.concatenate([t.plan_speed_mps for t in traces])
    v = np.concatenate([t.speed_mps for t in traces])
    setup, _, limits = _setup_for(cfg, method)
    return dict(autopilot=method.autopilot or "stock", wpnav_speed_mps=limits.speed_xy,
                wpnav_accel_mps2=limits.accel_xy, plan_speed_max_mps=setup.motion.speed_max_mps,
                plan_accel_max_mps2=setup.motion.accel_max_mps2,
                miss_median_m=float(np.median(miss)), miss_p95_m=float(np.percentile(miss, 95)),
                miss_max_m=float(miss.max()), planned_speed_mean_mps=float(plan_v.mean()),
                planned_speed_peak_mps=float(plan_v.max()), speed_mean_mps=float(v.mean()),
                speed_peak_mps=float(v.max()))


def summarise(cfg: EvalConfig, trials: Sequence[TrialResult], wall_s: float = float("nan")) -> Summary:
    N, w0 = len(trials), cfg.window_start
    band = nees_band(N)
    out: dict[str, MethodSummary] = {}
    errs = {m.name: np.stack([t.traces[m.name].error_m for t in trials]) for m in cfg.methods}  # (N, K, M)
    ref_r = None
    if REFERENCE in errs:
        ref_err = errs[REFERENCE]
        ref_r = np.sqrt(np.mean(ref_err[:, w0:] ** 2, axis=(1, 2)))
    full_step = cfg.scenario.uav.n_radial * cfg.scenario.uav.step_m
    for m in cfg.methods:
        err = errs[m.name]
        nees = np.stack([t.traces[m.name].nees for t in trials])
        eps = np.sqrt(np.mean(err ** 2, axis=0))
        anees = nees.mean(axis=0)
        per_trial = np.sqrt(np.mean(err[:, w0:] ** 2, axis=(1, 2)))
        filtered = ref_r is not None and not m.bound_only
        diff = t_interval(per_trial - ref_r) if filtered else None
        ratio_ref = paired_ratio(ref_err, err, w0, cfg.seed) if filtered else None
        motion: dict = {}
        if m.sensing != "fixed":
            st = [motion_stats(t.traces[m.name], t.truth) for t in trials]
            steps = np.concatenate([s["step_m"] for s in st])
            motion = dict(
                mean_step_m=float(steps.mean()),
                full_step_fraction=float(np.mean(steps > full_step - 1e-3)),
                stay_fraction=float(np.mean(steps < 1e-3)),
                mean_away_m=float(np.mean(np.concatenate([s["away_m"] for s in st]))),
                mean_across_m=float(np.mean(np.concatenate([s["across_m"] for s in st]))),
                mean_range_m=float(np.mean([s["range_m"][w0:].mean() for s in st])),
            )
        out[m.name] = MethodSummary(
            m.name, m.description, eps, eps.mean(axis=1), float(eps.mean(axis=1)[w0:].mean()),
            eps[w0:].mean(axis=0), per_trial, anees, float(anees[w0:].mean()),
            float(np.mean((anees[w0:] >= band[0]) & (anees[w0:] <= band[1]))), diff, ratio_ref, motion,
            1e3 * float(np.mean([t.traces[m.name].tick_s for t in trials])),
            int(sum(t.traces[m.name].degenerate for t in trials)),
            *bound_summary([t.traces[m.name].bound_m2 for t in trials], w0),
            vs_jump=None if m.jump_twin not in errs else (m.jump_twin, paired_ratio(err, errs[m.jump_twin], w0,
                                                                                       cfg.seed)),
            flown=_flown_stats(cfg, m, [t.traces[m.name] for t in trials]),
            truth={} if m.bound_only else truth_stats([t.traces[m.name] for t in trials], w0, cfg.dt_s))
    ratio = ratio_ci = None
    if REFERENCE in out and FIXED in out:
        # the headline is the table's fixed3 row, so the two print one CI
        ratio, lo, hi = out[FIXED].ratio_vs_ref
        ratio_ci = (lo, hi) if N > 1 else None
    speed = np.linalg.norm(np.stack([t.truth[:, :, 3:5] for t in trials]), axis=-1).mean(axis=(0, 2))  # (K,)
    per10 = int(round(10.0 / cfg.dt_s))
    speed_10s = tuple(float(speed[k:k + per10].mean()) for k in range(0, len(speed), per10))
    filtered = [m.name for m in cfg.methods if not m.bound_only]
    pairs = {(a, b): (paired_ratio(errs[a], errs[b], w0, cfg.seed),
                      t_interval(out[a].per_trial_rmse - out[b].per_trial_rmse))
             for a in filtered if is_flight(a) for b in filtered if b != a}
    return Summary(cfg, out, band, ratio, ratio_ci, wall_s, N, speed_10s, pairs, _over_ceiling(cfg, trials))


def _over_ceiling(cfg: EvalConfig, trials: Sequence[TrialResult]) -> dict:
    """Each UAV method's PCRB over the (first) bound-only method's, paired over the trials
    (``Summary.ceiling``)."""
    ceil = next((m for m in cfg.methods if m.bound_only), None)
    if ceil is None:
        return {}
    w0 = cfg.window_start
    ref = np.stack([t.traces[ceil.name].bound_m2 for t in trials])
    ratios, limits = {}, {}
    for m in cfg.methods:
        if m.sensing == "fixed":
            continue
        mo = _setup_for(cfg, m)[0].motion
        limits[m.name] = (f"{mo.speed_max_mps:g} m/s, {mo.accel_max_mps2:g} m/s²" if mo.kind == "vehicle" else
                          f"jumps of {cfg.scenario.uav.n_radial * cfg.scenario.uav.step_m:g} m")
        if m.sensing == "uav":
            b = np.stack([t.traces[m.name].bound_m2 for t in trials])
            per_trial = np.sqrt(b[:, w0:].mean(axis=(1, 2)) / ref[:, w0:].mean(axis=(1, 2)))
            ratios[m.name] = (paired_bound_ratio(b, ref, w0, cfg.seed), per_trial)
    return {"name": ceil.name, "limits": limits, "ratios": ratios}
