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

Methods are registered by name in ``METHODS`` (name -> ``Method``); a method is a sensing mode
and a policy function ``policy(ctx) -> next UAV position``. A new planner registers itself with
``register_method``.

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

import contextlib
import math
import os
import platform
import signal
import time
import zlib
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import numpy as np
from scipy import stats

from onboard.config import with_overrides
from onboard.core import tracking
from onboard.core.guidance import GuidanceWorkspace
from onboard.core.information import PLANAR, bearing_information, information_reduction_factor, pcrb, planar_model
from onboard.core.monitor import MonitorSetup, MonitorState, Scan, TickResult, initial_state, tick
from onboard.core.planning import UavMotion, admissible, candidate_positions
from onboard.demo import DEMO_VEHICLE_PARAMS
from onboard.policy import POLICIES, vehicle_motion
from sim.guided import enu, fly_plan, ned
from sim.numerics import numerics_description, pin_kernels
from sim.sensors import FIXED_SENSORS_M, DirectionFinder, df_scan, fixed_scans
from sim.truth import simulate_truth
from sim.vehicle import PX4_DEFAULTS, VehicleLimits, VehicleState, limits_from_params

DEFAULT_WINDOW_S = 10.0  # convergence window: metrics are time-averaged from this time on
ORBIT_RADIUS_M = 150.0  # radius of the "orbit" baseline around the targets' initial centroid
REFERENCE = "greedy_l1"  # paired differences are taken against this method
FIXED = "fixed3"
BOOTSTRAP_RESAMPLES = 2000
# the ArduCopter parameters a vehicle method's copter flies with (sim.vehicle.limits_from_params):
# ``NAME@LABEL`` in --methods picks one (default stock: 10 m/s, 2.5 m/s^2; demo: onboard/demo.py's;
# px4: PX4 v1.16's stock MPC_* parameters, its controller and SIH airframe)
AUTOPILOTS: dict[str, dict[str, float]] = {"stock": {}, "demo": dict(DEMO_VEHICLE_PARAMS), "px4": dict(PX4_DEFAULTS)}


# --------------------------------------------------------------------------- methods


@dataclass(frozen=True, eq=False)
class PolicyContext:
    """What a UAV policy may look at after tick k to choose the UAV position for tick k+1."""

    step: int
    uav: np.ndarray  # (3,) ENU m, where the scan of tick k was taken
    setup: MonitorSetup
    state: MonitorState  # predicted beliefs for tick k+1 and the targets' plans
    result: TickResult  # tick k's estimates, plans and (greedy) planning result
    rng: np.random.Generator  # the method's own policy stream
    config: "EvalConfig"


Policy = Callable[[PolicyContext], np.ndarray]


@dataclass(frozen=True, eq=False)
class Method:
    """A sensing mode and, for a UAV, how it moves.

    sensing: ``uav`` (the UAV's DF: p_D, Poisson clutter) or ``fixed`` (the paper's three
    ground DFs, no clutter, p_D = 1). clutter_rate: Lambda for both the simulated DF and the
    filter's likelihood (None: the scenario's). greedy: let the monitor's tick run the paper's
    one-step rule (eq:optimization) from the UAV position; ``policy`` is then not called.
    (With ``setup`` overrides such as ``planner="lookahead"`` the tick runs that planner
    instead: ``greedy`` means "the monitor's tick plans the UAV".)
    setup: MonitorSetup field overrides for this method only (applied after the config's).
    motion: the UAV's motion model for this method, ``jump`` or ``vehicle``, with the scenario's
    ``planning.speed_max_mps`` / ``accel_max_mps2``; None: the scenario's ``planning.motion``.
    A UAV that the monitor's tick plans on the vehicle motion is *flown*: at each tick the app's
    setpoint (the plan's position, velocity and acceleration) is given to the vehicle model
    fitted to ArduCopter (sim.guided.fly_plan), and the next scan is taken where it is a tick
    later, with the velocity it has then (not at the planned point).
    jump_twin: for a vehicle method, the method with the same planner and the jump model; when
    both run, the summary reports this method's RMSE over the twin's, paired, with its CI.
    scenario_overrides: scenario settings of this method only (``onboard.policy.POLICIES``), under
    the run's own ``--set`` (``onboard.config.with_overrides``).
    autopilot: the ArduCopter parameter set (``AUTOPILOTS``) a flown method's copter flies with
    (None: stock). autopilot_limits: the planner plans with the autopilot's WPNAV_SPEED and
    WPNAV_ACCEL capped by the scenario's planning.speed_max_mps / accel_max_mps2 (what the
    airframe flies; ``onboard.policy.vehicle_motion``), as the app does; else with the
    scenario's values.
    """

    name: str
    description: str
    sensing: str = "uav"
    clutter_rate: float | None = None
    greedy: bool = False
    policy: Policy | None = None
    setup: tuple[tuple[str, Any], ...] = ()
    motion: str | None = None
    jump_twin: str | None = None
    scenario_overrides: tuple[tuple[str, Any], ...] = ()
    autopilot: str | None = None
    autopilot_limits: bool = False

    def __post_init__(self):
        if self.sensing not in ("uav", "fixed"):
            raise ValueError(f"method {self.name}: sensing must be 'uav' or 'fixed'")
        if self.sensing == "uav" and not self.greedy and self.policy is None:
            raise ValueError(f"method {self.name}: a UAV method needs greedy=True or a policy")
        if self.motion not in (None, "jump", "vehicle"):
            raise ValueError(f"method {self.name}: motion must be 'jump', 'vehicle' or None")
        if self.autopilot is not None and self.autopilot not in AUTOPILOTS:
            raise ValueError(f"method {self.name}: autopilot must be one of {', '.join(AUTOPILOTS)}")


def hover_policy(ctx: PolicyContext) -> np.ndarray:
    """Stay at the start position."""
    return ctx.uav


def random_policy(ctx: PolicyContext) -> np.ndarray:
    """A uniformly random admissible candidate of S_(t+1) ("stay" included)."""
    s = ctx.setup
    cand = candidate_positions(ctx.uav, s.grid)
    ok = np.flatnonzero(admissible(cand, ctx.uav, s.area_min, s.area_max, s.uav_obstacles))
    return ctx.uav if ok.size == 0 else cand[ctx.rng.choice(ok)]


def orbit_policy(ctx: PolicyContext) -> np.ndarray:
    """Counter-clockwise circle of radius ``config.orbit_radius_m`` around the targets' initial
    centroid, at the UAV's speed limit N_r Delta_r per tick.

    Far from the circle the UAV flies straight to its nearest point; on it, it advances by one
    step of arc. The move goes where it should when that is admissible (area, obstacles), else
    to the admissible grid candidate nearest to that point: the same limits as every method.
    """
    s, cfg = ctx.setup, ctx.config
    c = cfg.orbit_center
    r = cfg.orbit_radius_m
    step = s.grid.n_radial * s.grid.step_m
    p = ctx.uav[:2]
    d = p - c
    dist = float(np.hypot(*d))
    if dist < 1e-9:
        d, dist = np.array([1.0, 0.0]), 1.0
    if abs(dist - r) > step:
        target = c + r * d / dist
    else:
        ang = math.atan2(d[1], d[0]) + step / r
        target = c + r * np.array([math.cos(ang), math.sin(ang)])
    move = target - p
    n = float(np.hypot(*move))
    want = p + (move if n <= step else move * (step / n))
    want3 = np.array([want[0], want[1], s.grid.altitude_m])
    if admissible(want3[None], ctx.uav, s.area_min, s.area_max, s.uav_obstacles)[0]:
        return want3
    cand = candidate_positions(ctx.uav, s.grid)
    ok = admissible(cand, ctx.uav, s.area_min, s.area_max, s.uav_obstacles)
    if not ok.any():
        return ctx.uav
    dist_c = np.where(ok, np.linalg.norm(cand[:, :2] - want, axis=1), np.inf)
    return cand[int(np.argmin(dist_c))]


METHODS: dict[str, Method] = {}


def register_method(method: Method) -> Method:
    """Add (or replace) a method by name; ``pmon eval --methods`` can then name it."""
    METHODS[method.name] = method
    return method


for _m in (
    Method("greedy_l1", "single UAV, the paper's one-step greedy rule, Lambda = 1", greedy=True, clutter_rate=1.0),
    Method("lookahead", "single UAV, the non-myopic planner (docs/PLANNING.md), jump moves, Lambda = 1",
           greedy=True, clutter_rate=1.0, setup=(("planner", "lookahead"),), motion="jump"),
    Method("lookahead_vehicle", "single UAV, the non-myopic planner with vehicle limits (planning.speed_max_mps, "
           "accel_max_mps2: ArduCopter's 10 m/s, 2.5 m/s^2 in the paper scenario), Lambda = 1", greedy=True,
           clutter_rate=1.0, setup=(("planner", "lookahead"),), motion="vehicle", jump_twin="lookahead"),
    Method("greedy_vehicle", "single UAV, the paper's greedy rule with vehicle limits (as lookahead_vehicle), "
           "Lambda = 1", greedy=True, clutter_rate=1.0, setup=(("planner", "greedy"),), motion="vehicle",
           jump_twin="greedy_l1"),
    Method("flight", "single UAV, the flight default (onboard/policy.py POLICIES['flight']: docs/PLANNING.md "
           "section 9), planning with the autopilot's WPNAV_SPEED / WPNAV_ACCEL capped by what the airframe "
           "flies, Lambda = 1", greedy=True, clutter_rate=1.0, motion="vehicle",
           scenario_overrides=tuple(POLICIES["flight"].items()), autopilot_limits=True),
    Method("greedy_l8", "single UAV, greedy rule, Lambda = 8 (DF and filter)", greedy=True, clutter_rate=8.0),
    Method("fixed3", "three fixed DFs (150,200), (800,200), (500,900) m; no clutter, p_D = 1", sensing="fixed"),
    Method("hover", "single UAV hovering at its start, Lambda = 1", policy=hover_policy, clutter_rate=1.0),
    Method("orbit", "single UAV on a circle around the targets' initial centroid, Lambda = 1",
           policy=orbit_policy, clutter_rate=1.0),
    Method("random", "single UAV, uniformly random admissible move, Lambda = 1", policy=random_policy,
           clutter_rate=1.0),
):
    register_method(_m)
DEFAULT_METHODS = ("greedy_l1", "greedy_l8", "fixed3", "hover", "orbit", "random")  # the paper's set


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True, eq=False)
class EvalConfig:
    scenario: Any  # onboard.config.Scenario
    n_trials: int
    seed: int
    methods: tuple[Method, ...]
    n_ticks: int
    window_start: int  # first tick of the convergence window
    orbit_radius_m: float = ORBIT_RADIUS_M
    overrides: tuple[tuple[str, Any], ...] = ()  # MonitorSetup overrides for every method

    @property
    def method_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.methods)

    @property
    def orbit_center(self) -> np.ndarray:
        return np.mean([t.position_m[:2] for t in self.scenario.targets], axis=0)

    @property
    def dt_s(self) -> float:
        return self.scenario.dynamics.dt_s


def make_config(sc, n_trials: int, seed: int, methods: Sequence[str] = DEFAULT_METHODS,
                duration_s: float | None = None, particles: int | None = None,
                window_s: float = DEFAULT_WINDOW_S) -> EvalConfig:
    """Validated configuration. Raises ValueError with a one-line reason."""
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
    dt = sc.dynamics.dt_s
    duration = sc.mission.duration_s if duration_s is None else float(duration_s)
    if not (math.isfinite(duration) and duration >= 2 * dt):
        raise ValueError(f"--duration must be at least 2 time steps ({2 * dt:g} s), got {duration_s}")
    n_ticks = int(round(duration / dt))
    # the window starts at window_s, or halfway when the mission is too short for that
    window_start = min(int(round(window_s / dt)), n_ticks // 2)
    overrides: tuple = ()
    if particles is not None:
        if particles < 10:
            raise ValueError(f"--particles must be >= 10, got {particles}")
        overrides = (("n_particles", int(particles)),)
    return EvalConfig(sc, int(n_trials), int(seed), chosen, n_ticks, window_start, overrides=overrides)


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
    motion = m.motion or (None if sc is None else sc.planning.motion)
    if m.sensing != "uav" or not m.greedy or motion == "jump":
        raise ValueError(f"method {name!r}: {base} flies no vehicle (only vehicle-motion methods take @{label})")
    return replace(m, name=name, autopilot=label, description=f"{m.description}; autopilot: {label}")


# --------------------------------------------------------------------------- one trial


@dataclass(frozen=True, eq=False)
class MethodTrace:
    """One method on one trial: (K, M) arrays over ticks and targets unless stated."""

    error_m: np.ndarray  # horizontal position error |x^ - x|
    nees: np.ndarray  # 2-D position NEES
    estimate_xy: np.ndarray  # (K, M, 2) posterior mean positions
    uav: np.ndarray | None  # (K, 3) where each scan was taken (None: fixed sensors)
    degenerate: int  # updates that left no finite weight (prior kept)
    tick_s: float  # mean wall time of a tick
    bound_m2: np.ndarray | None = None  # (K, M) PCRB of the position (trace, m^2) along this path
    # a flown method (Method's docstring): per tick k < K-1, the flown position at k+1 from the
    # planned one (m), the plan's speed at k+1 (m/s); per tick, the vehicle's speed (m/s)
    plan_miss_m: np.ndarray | None = None
    plan_speed_mps: np.ndarray | None = None
    speed_mps: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class TrialResult:
    trial: int
    start: np.ndarray  # (3,) the UAV start of this trial
    truth: np.ndarray  # (K, M, 6) true states at the ticks
    traces: dict[str, MethodTrace]
    wall_s: float
    gains: np.ndarray | None = None  # (K-1, M, 3, 6) closed-loop guidance gains at the true states


def _rng(seed: int, *key: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=tuple(int(k) for k in key)))


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
    sc = cfg.scenario
    if method.scenario_overrides:
        sc = with_overrides(sc, dict(method.scenario_overrides))
    sigma = sc.sensor.sigma_rad
    if method.sensing == "fixed":
        # the baseline's sensors: no clutter, every target seen; the filter must know it
        sensor, df = tracking.SensorModel(sigma, 1.0, 0.0), None
    else:
        lam = sc.sensor.clutter_rate if method.clutter_rate is None else method.clutter_rate
        sensor = tracking.SensorModel(sigma, sc.sensor.p_detect, lam)
        df = DirectionFinder(sigma, sc.sensor.p_detect, lam)
    fields = {**dict(cfg.overrides), **dict(method.setup)}
    motion = method.motion or sc.planning.motion
    flown = method.sensing == "uav" and method.greedy and motion == "vehicle"
    limits = limits_from_params(AUTOPILOTS[method.autopilot or "stock"]) if flown else None
    if limits is not None and method.autopilot_limits:
        fields["motion"] = vehicle_motion(sc.planning, limits.speed_xy, limits.accel_xy)
    elif method.motion is not None:
        fields["motion"] = replace(UavMotion.from_config(sc.planning), kind=method.motion)
    return MonitorSetup.from_scenario(sc, **fields, sensor=sensor), df, limits


def run_method(cfg: EvalConfig, method: Method, trial: int, truth: np.ndarray, start: np.ndarray,
               gains: np.ndarray | None = None) -> MethodTrace:
    """Closed loop of one method on one trial's truth (K, M, 6); with the truth's closed-loop
    gains (K-1, M, 3, 6), also the PCRB along the flown path."""
    setup, df, limits = _setup_for(cfg, method)
    ss = np.random.SeedSequence(cfg.seed, spawn_key=(trial, 2, _method_key(method.name)))
    sensor_rng, filter_rng, policy_rng = (np.random.default_rng(s) for s in ss.spawn(3))
    K, M = truth.shape[0], truth.shape[1]
    state = initial_state(setup, filter_rng)
    ws = GuidanceWorkspace()  # per method and trial: OSQP warm starts never leak between runs
    uav = None if method.sensing == "fixed" else np.asarray(start, float).copy()
    uav_vel = np.zeros(2)  # planar UAV velocity at ``uav`` (vehicle motion); starts in hover
    err, nees, est = np.zeros((K, M)), np.zeros((K, M)), np.zeros((K, M, 2))
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
        state, res = tick(setup, state, scans, filter_rng, plan_from=uav if method.greedy else None, workspace=ws,
                          uav_velocity=uav_vel)
        tick_time += time.perf_counter() - t0
        e = res.means[:, :2] - truth[k, :, :2]
        est[k] = res.means[:, :2]
        err[k] = np.linalg.norm(e, axis=1)
        P = res.covs[:, :2, :2]
        nees[k] = np.einsum("mi,mi->m", e, np.linalg.solve(P, e[..., None])[..., 0])
        degenerate += int(res.degenerate.sum())
        if uav is not None and k < K - 1 and limits is not None:
            p = res.planning
            ok = p is not None and p.index is not None
            v_next = np.asarray(p.velocities[p.index], float)[:2] if ok else None
            planned = p.position[:2] if ok else uav[:2]
            vehicle = fly_plan(vehicle, v_next, setup.grid.altitude_m, setup.model.dt_s, limits, first=k == 0)
            uav, uav_vel = enu(vehicle.pos), enu(vehicle.vel)[:2]
            miss[k] = float(np.linalg.norm(uav[:2] - planned))
            plan_speed[k] = 0.0 if v_next is None else float(np.linalg.norm(v_next))
            speed[k + 1] = float(np.linalg.norm(uav_vel))
        elif uav is not None and k < K - 1:
            if method.greedy:
                nxt = res.next_position
                p = res.planning
                if p is not None and p.index is not None and p.velocities is not None:
                    uav_vel = np.asarray(p.velocities[p.index], float)[:2].copy()
                else:
                    uav_vel = np.zeros(2)  # no admissible move: the vehicle stops where it is
            else:
                nxt = method.policy(PolicyContext(k, uav, setup, state, res, policy_rng, cfg))
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
    return MethodTrace(err, nees, est, uav_track, degenerate, tick_time / K, bound, **flown)


def run_trial(cfg: EvalConfig, trial: int) -> TrialResult:
    """One trial of every method: truth once, the same truth and UAV start for all."""
    t0 = time.perf_counter()
    truth, gains = simulate_truth(cfg.scenario, cfg.n_ticks - 1, _rng(cfg.seed, trial, 0), with_gains=True)
    start = draw_start(cfg, _rng(cfg.seed, trial, 1))
    traces = {m.name: run_method(cfg, m, trial, truth, start, gains) for m in cfg.methods}
    return TrialResult(trial, start, truth, traces, time.perf_counter() - t0, gains)


# --------------------------------------------------------------------------- running many trials

def _one_blas_thread() -> None:
    # one BLAS thread per worker: the workers already fill the cores
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def _worker_init() -> None:
    _one_blas_thread()
    # Ctrl-C reaches the whole process group: the parent stops the pool, the workers stay quiet
    # (they already start with SIGINT ignored, _worker_pool; this covers a replaced worker)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def _worker_pool(ctx, workers: int):
    """A pool of spawned workers that never outlives the block: terminated on leaving it for any
    reason (a worker's error, Ctrl-C, or SIGTERM, which raises SystemExit(143) meanwhile).

    While the pool starts (milliseconds: the workers import on their own afterwards):
    - SIGINT is ignored, a disposition the workers inherit across exec (a signal mask is not:
      spawned children start unblocked), so a Ctrl-C to the process group never kills one
      mid-import; one pressed in that window is lost.
    - SIGTERM is only recorded, and raised once the pool exists, so the pool is terminated rather
      than left half-built with workers orphaned. Recorded by the handler, not held back by a
      mask: this process has other threads (the progress bar's, BLAS's) that a signal sent to
      the process may land on, whatever the main thread blocks.
    Signal handling only from the main thread, where Python allows it."""
    import threading

    main = threading.current_thread() is threading.main_thread()

    def _raise(signum, frame):
        raise SystemExit(128 + signum)

    held: list[int] = []
    old_term = signal.signal(signal.SIGTERM, _raise) if main else None
    pool = None
    try:
        if main:
            old_int = signal.signal(signal.SIGINT, signal.SIG_IGN)
            signal.signal(signal.SIGTERM, lambda signum, frame: held.append(signum))
        try:
            pool = ctx.Pool(workers, initializer=_worker_init)
        finally:
            if main:
                signal.signal(signal.SIGINT, old_int)
                signal.signal(signal.SIGTERM, _raise)
        if held:
            _raise(held[0], None)
        yield pool
    finally:
        if pool is not None:
            pool.terminate()
        if main:
            signal.signal(signal.SIGTERM, old_term)


def run_trials(cfg: EvalConfig, workers: int | None = None, scheduler: str | None = None,
               progress: bool = True, console=None) -> list[TrialResult]:
    """All trials, in trial order. workers: local processes (default os.cpu_count()), each with
    one BLAS thread; scheduler: a Dask distributed scheduler address instead of local processes."""
    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    console = console or Console(stderr=True)
    bar = Progress(TextColumn("[bold]eval[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                   TextColumn("trials"), TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                   console=console, disable=not progress, transient=False, refresh_per_second=2)
    results: list[TrialResult] = []
    n = cfg.n_trials
    label = f"{len(cfg.methods)} methods x {cfg.n_ticks} ticks"
    if scheduler is not None:
        from dask.distributed import Client, as_completed

        with Client(scheduler, timeout="20s") as client, bar:
            task = bar.add_task(label + f" on {scheduler}", total=n)
            futures = client.map(run_trial, [cfg] * n, list(range(n)), pure=False)
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
                    for res in pool.imap_unordered(functools.partial(run_trial, cfg), range(n)):
                        results.append(res)
                        bar.advance(task)
            except BaseException:
                console.print(f"eval: stopped after {len(results)} of {n} trials; workers terminated")
                raise
    return sorted(results, key=lambda r: r.trial)


# --------------------------------------------------------------------------- metrics


def nees_band(n_trials: int, dof: int = 2, level: float = 0.95) -> tuple[float, float]:
    """95 % band of the average of n_trials NEES values of a consistent filter (dof each)."""
    a = (1.0 - level) / 2.0
    return (float(stats.chi2.ppf(a, dof * n_trials) / n_trials), float(stats.chi2.ppf(1 - a, dof * n_trials) / n_trials))


def t_interval(x: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """Mean and its two-sided t confidence interval (nan for fewer than two values)."""
    x = np.asarray(x, float)
    m = float(x.mean()) if x.size else float("nan")
    if x.size < 2:
        return m, float("nan"), float("nan")
    half = float(stats.t.ppf(0.5 + level / 2, x.size - 1) * x.std(ddof=1) / math.sqrt(x.size))
    return m, m - half, m + half


def pcrb_position(model, initial_cov: np.ndarray, truth: np.ndarray, gains: np.ndarray, sensors: np.ndarray,
                  sigma_rad: float, reduction: float = 1.0) -> np.ndarray:
    """Posterior Cramer-Rao bound of each target's horizontal position along a trial: (K, M),
    the trace of the (x, y) block of the bound, m^2.

    ``onboard.core.information.pcrb`` on the planar state [px, py, vx, vy] with, per step, the
    closed-loop transition Jacobian F_k = A + B du/dx of the target's guidance at its true state
    (``gains`` (K-1, M, 3, 6) from ``sim.truth``: the targets steer by feedback toward a known
    goal, so treating the control as a known input would give a bound above what a filter that
    knows the policy achieves), process noise Q, prior Sigma_0, and the measurement information
    of one bearing per sensor and tick, q h h^T / sigma^2 at the true position (``reduction`` q:
    p_D and clutter, ``information_reduction_factor``). truth (K, M, 6); sensors (K, S, 2) the
    sensor positions at each tick (the flown UAV path, or the fixed DFs repeated).
    """
    A, B, Q = planar_model(model)
    P0 = np.asarray(initial_cov, float)[np.ix_(PLANAR, PLANAR)]
    K, M = truth.shape[:2]
    out = np.zeros((K, M))
    for j in range(M):
        info = bearing_information(truth[:, None, j, :2], sensors[:, :, :2], sigma_rad, reduction).sum(axis=1)
        F = A[None] + B[None] @ np.asarray(gains, float)[:K - 1, j, :2][:, :, PLANAR]  # (K-1, 4, 4)
        bound = pcrb(np.linalg.inv(P0), F, Q, info)
        out[:, j] = bound[:, 0, 0] + bound[:, 1, 1]
    return out


@dataclass(frozen=True, eq=False)
class MethodSummary:
    name: str
    description: str
    rmse_t: np.ndarray  # (K, M) eps_t per target
    rmse_t_mean: np.ndarray  # (K,) averaged over targets
    rmse_mean_m: float  # time average of rmse_t_mean over the window
    rmse_target_m: np.ndarray  # (M,) time average per target over the window
    per_trial_rmse: np.ndarray  # (N,) r_n over the window
    anees_t: np.ndarray  # (K, M)
    nees_mean: float
    nees_in_band: float  # fraction of (step, target) cells in the N-trial band
    diff_vs_ref: tuple[float, float, float] | None  # mean, lo, hi of r_n - r_n(ref)
    ratio_vs_ref: tuple[float, float, float] | None  # rmse_mean_m(ref) / rmse_mean_m, 95 % bootstrap CI
    motion: dict  # UAV motion statistics (empty for fixed sensors)
    tick_ms: float
    degenerate: int
    bound_mean_m: float = float("nan")  # the PCRB, averaged like rmse_mean_m (sqrt of the trial mean)
    bound_t_mean: np.ndarray | None = None  # (K,) the bound per step, averaged over targets
    # vehicle method whose jump twin ran: (twin, rmse_mean_m / twin's with its 95 % paired CI)
    vs_jump: tuple[str, tuple[float, float, float]] | None = None
    flown: dict = field(default_factory=dict)  # a flown method: how the vehicle flew its plans (_flown_stats)

    @property
    def rmse_over_bound(self) -> float:
        return self.rmse_mean_m / self.bound_mean_m


@dataclass(frozen=True, eq=False)
class Summary:
    config: EvalConfig
    methods: dict[str, MethodSummary]
    nees_band: tuple[float, float]
    ratio: float | None  # greedy_l1 / fixed3
    ratio_ci: tuple[float, float] | None
    wall_s: float
    n_trials: int
    target_speed_10s: tuple[float, ...] = ()  # the true targets' mean speed per 10 s of mission, m/s
    # the flight default (a method named flight, flight@..., flight~...) against every other method
    # of the run: {(flight method, other): ((ratio, lo, hi) of RMSEs, (mean, lo, hi) of per-trial
    # differences)}, paired over the trials
    pairs: dict = field(default_factory=dict)


def is_flight(name: str) -> bool:
    """The flight default, with its autopilot (``@``) or a variant of it (``~``)."""
    return name.partition("@")[0].partition("~")[0] == "flight"


def _paired_ratio(a: np.ndarray, b: np.ndarray, w0: int, seed: int) -> tuple[float, float, float]:
    """rmse_mean_m(a) / rmse_mean_m(b) for error arrays (N, K, M) of the same trials, with a 95 %
    paired percentile bootstrap CI (trials resampled with replacement, both methods together)."""
    ratio = _window_mean_rmse(a, w0) / _window_mean_rmse(b, w0)
    N = len(a)
    if N < 2:
        return ratio, float("nan"), float("nan")
    boot_rng = _rng(seed, 2**31 - 2)  # its own stream: does not touch any trial's
    rs = [_window_mean_rmse(a[idx], w0) / _window_mean_rmse(b[idx], w0)
          for idx in (boot_rng.integers(0, N, N) for _ in range(BOOTSTRAP_RESAMPLES))]
    return ratio, float(np.percentile(rs, 2.5)), float(np.percentile(rs, 97.5))


def _bound_summary(bounds: list, w0: int) -> tuple[float, np.ndarray | None]:
    if any(b is None for b in bounds):
        return float("nan"), None
    b = np.sqrt(np.mean(np.stack(bounds), axis=0)).mean(axis=1)  # (K,): like eps_t, over targets
    return float(b[w0:].mean()), b


def _window_mean_rmse(err: np.ndarray, w0: int) -> float:
    """err (N, K, M) -> time average over the window of the target-averaged eps_t."""
    eps = np.sqrt(np.mean(err ** 2, axis=0))  # (K, M)
    return float(eps[w0:].mean())


def _motion_stats(trace: MethodTrace, truth: np.ndarray) -> dict:
    """How a UAV moved: step lengths, and the step's component toward/away from and across the
    lines of sight to the true targets (averaged over targets)."""
    u = trace.uav[:, :2]
    move = np.diff(u, axis=0)  # (K-1, 2)
    length = np.linalg.norm(move, axis=1)
    los = truth[:-1, :, :2] - u[:-1, None, :]  # (K-1, M, 2) UAV -> target
    rng_m = np.linalg.norm(los, axis=2)
    unit = los / np.maximum(rng_m, 1e-9)[..., None]
    along = np.einsum("kd,kmd->km", move, unit)  # + toward the target
    across = np.abs(unit[..., 0] * move[:, None, 1] - unit[..., 1] * move[:, None, 0])
    return dict(step_m=length, away_m=-along.mean(axis=1), across_m=across.mean(axis=1),
                range_m=np.linalg.norm(truth[:, :, :2] - u[:, None, :], axis=2).mean(axis=1))


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
        diff = None if ref_r is None else t_interval(per_trial - ref_r)
        ratio_ref = None if ref_r is None else _paired_ratio(ref_err, err, w0, cfg.seed)
        motion: dict = {}
        if m.sensing == "uav":
            st = [_motion_stats(t.traces[m.name], t.truth) for t in trials]
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
            *_bound_summary([t.traces[m.name].bound_m2 for t in trials], w0),
            vs_jump=None if m.jump_twin not in errs else (m.jump_twin, _paired_ratio(err, errs[m.jump_twin], w0,
                                                                                       cfg.seed)),
            flown=_flown_stats(cfg, m, [t.traces[m.name] for t in trials]))
    ratio = ratio_ci = None
    if REFERENCE in out and FIXED in out:
        # the headline is the table's fixed3 row, so the two print one CI
        ratio, lo, hi = out[FIXED].ratio_vs_ref
        ratio_ci = (lo, hi) if N > 1 else None
    speed = np.linalg.norm(np.stack([t.truth[:, :, 3:5] for t in trials]), axis=-1).mean(axis=(0, 2))  # (K,)
    per10 = int(round(10.0 / cfg.dt_s))
    speed_10s = tuple(float(speed[k:k + per10].mean()) for k in range(0, len(speed), per10))
    pairs = {(a, b): (_paired_ratio(errs[a], errs[b], w0, cfg.seed),
                      t_interval(out[a].per_trial_rmse - out[b].per_trial_rmse))
             for a in cfg.method_names if is_flight(a) for b in cfg.method_names if b != a}
    return Summary(cfg, out, band, ratio, ratio_ci, wall_s, N, speed_10s, pairs)


def headline(summary: Summary) -> dict:
    """The JSON line ``pmon eval`` ends with."""
    def r(x):
        return None if x is None or not math.isfinite(x) else round(float(x), 4)
    return {
        "methods": {n: {"rmse_mean_m": r(s.rmse_mean_m), "nees_mean": r(s.nees_mean),
                        "bound_m": r(s.bound_mean_m), "rmse_over_bound": r(s.rmse_over_bound),
                        "ratio_vs_ref": None if s.ratio_vs_ref is None else [r(v) for v in s.ratio_vs_ref],
                        **({} if s.vs_jump is None else {"ratio_vs_jump": [r(v) for v in s.vs_jump[1]]}),
                        **({} if not s.flown else {"from_plan_median_m": r(s.flown["miss_median_m"]),
                                                   "speed_peak_mps": r(s.flown["speed_peak_mps"])})}
                    for n, s in summary.methods.items()},
        "uav_vs_fixed_ratio": r(summary.ratio),
        "uav_vs_fixed_ratio_ci95": None if summary.ratio_ci is None else [r(v) for v in summary.ratio_ci],
        **({} if not summary.pairs else {"flight_over": {f"{a} / {b}": [r(v) for v in ratio]
                                                          for (a, b), (ratio, _) in summary.pairs.items()}}),
    }


# --------------------------------------------------------------------------- outputs


def write_csv(summary: Summary, path) -> None:
    """step, method, target, rmse_m: per target (names from the scenario) and ``mean``."""
    names = [t.name for t in summary.config.scenario.targets]
    dt = summary.config.dt_s
    lines = ["step,time_s,method,target,rmse_m"]
    for mname, s in summary.methods.items():
        for k in range(s.rmse_t.shape[0]):
            for j, tn in enumerate(names):
                lines.append(f"{k},{k * dt:g},{mname},{tn},{s.rmse_t[k, j]:.4f}")
            lines.append(f"{k},{k * dt:g},{mname},mean,{s.rmse_t_mean[k]:.4f}")
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


def write_per_trial_csv(summary: Summary, path) -> None:
    """trial, method, rmse_window_m (r_n): the numbers the paired differences are made of."""
    lines = ["trial,method,rmse_window_m"]
    for mname, s in summary.methods.items():
        lines += [f"{n},{mname},{v:.4f}" for n, v in enumerate(s.per_trial_rmse)]
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


def machine_description() -> str:
    return f"{platform.node() or 'host'}: {platform.machine()}, {os.cpu_count()} cores, {platform.system()} " \
           f"{platform.release()}, Python {platform.python_version()}"


def results_markdown(summary: Summary, command: str) -> str:
    cfg = summary.config
    dt = cfg.dt_s
    lo, hi = summary.nees_band
    names = [t.name for t in cfg.scenario.targets]
    L = [f"# Evaluation results: scenario `{cfg.scenario.name}`", "",
         f"- Command: `{command}`",
         f"- Trials: {summary.n_trials}, seed {cfg.seed}, {cfg.n_ticks} ticks of {dt:g} s "
         f"({cfg.n_ticks * dt:g} s missions); particles per target: "
         f"{dict(cfg.overrides).get('n_particles', cfg.scenario.tracking.particles)}",
         f"- Convergence window: ticks {cfg.window_start}..{cfg.n_ticks - 1} "
         f"(t = {cfg.window_start * dt:g} s to the end)",
         f"- Machine: {machine_description()}; wall time {summary.wall_s:.0f} s",
         f"- Numerics: {numerics_description()} (figures reproduce exactly where these match)", "",
         "## Time-averaged RMSE and consistency", "",
         f"RMSE: the paper's eps_t (root mean square over trials of the horizontal position error), "
         f"averaged over the {len(names)} targets and over the window. Paired difference: per-trial "
         f"window RMSE minus {REFERENCE}'s on the same trial, mean and 95 % t-interval. ANEES: 2-D "
         f"position NEES averaged over trials (consistent: 2; 95 % band for N = {summary.n_trials}: "
         f"[{lo:.2f}, {hi:.2f}]), then over targets and the window; 'in band' is the share of "
         f"(step, target) cells inside the band. Ratio: {REFERENCE}'s time-averaged RMSE over the "
         f"method's, 95 % paired percentile bootstrap CI ({BOOTSTRAP_RESAMPLES} resamples). PCRB: the posterior "
         f"Cramér-Rao bound of the position along each trial's truth and flown path (closed-loop guidance "
         f"Jacobian in the transition, information reduced by q for p_D and clutter), averaged like the RMSE; "
         f"RMSE / bound >= 1 for any estimator.", "",
         "| method | RMSE [m] | " + " | ".join(f"{n} [m]" for n in names)
         + f" | minus {REFERENCE} [m] (95 % CI) | {REFERENCE} / method (95 % CI) | PCRB [m] | RMSE / bound "
           f"| ANEES | in band | ms/tick |",
         "|---|---:|" + "---:|" * len(names) + "---|---|---:|---:|---:|---:|---:|"]
    for n, s in summary.methods.items():
        if s.diff_vs_ref is None or n == REFERENCE:
            d = "—"
        else:
            d = f"{s.diff_vs_ref[0]:+.1f} ({s.diff_vs_ref[1]:+.1f}, {s.diff_vs_ref[2]:+.1f})"
        if s.ratio_vs_ref is None or n == REFERENCE:
            rr = "—"
        else:
            rr = f"{s.ratio_vs_ref[0]:.2f} ({s.ratio_vs_ref[1]:.2f}, {s.ratio_vs_ref[2]:.2f})"
        L.append(f"| {n} | {s.rmse_mean_m:.1f} | " + " | ".join(f"{v:.1f}" for v in s.rmse_target_m)
                 + f" | {d} | {rr} | {s.bound_mean_m:.1f} | {s.rmse_over_bound:.2f} | {s.nees_mean:.2f} "
                   f"| {100 * s.nees_in_band:.0f} % | {s.tick_ms:.0f} |")
    L.append("")
    if summary.ratio is not None:
        ci = "" if summary.ratio_ci is None else f", 95 % CI [{summary.ratio_ci[0]:.2f}, {summary.ratio_ci[1]:.2f}] " \
                                                  f"(paired percentile bootstrap over trials, {BOOTSTRAP_RESAMPLES} resamples)"
        L += [f"**Single UAV (Lambda = 1) over fixed sensors:** RMSE ratio {REFERENCE} / {FIXED} = "
              f"{summary.ratio:.2f}{ci}.", ""]
    pl, u = cfg.scenario.planning, cfg.scenario.uav
    jump_m = u.n_radial * u.step_m
    equal_step = pl.speed_max_mps * dt / u.n_radial  # the grid step that makes the jump as fast
    for n, s in summary.methods.items():
        if s.vs_jump is not None:
            twin, (v, a, b) = s.vs_jump
            tb = summary.methods[twin].bound_mean_m
            L += [f"**Vehicle limits:** {n} / {twin} (the same planner, jump model): RMSE ratio {v:.2f}, "
                  f"95 % CI [{a:.2f}, {b:.2f}] (paired bootstrap); PCRB ratio {s.bound_mean_m / tb:.2f}. "
                  f"The jump model moves up to {jump_m:g} m per tick, the vehicle at most {pl.speed_max_mps:g} m/s "
                  f"({pl.accel_max_mps2:g} m/s^2); the same comparison at equal speed: "
                  f"`--set uav.step_m={equal_step:g}`.", ""]
    uav = {n: s for n, s in summary.methods.items() if s.motion}
    if uav:
        L += ["## How the UAV moved", "",
              "Per step (tick to tick), averaged over trials: step length; share of steps at the full "
              f"N_r Delta_r = {cfg.scenario.uav.n_radial * cfg.scenario.uav.step_m:g} m and of 'stay'; "
              "the component of the step away from the targets (+: away) and across the lines of sight "
              "(both averaged over targets); mean UAV-target range over the window.", "",
              "| method | step [m] | full steps | stays | away [m/step] | across [m/step] | range [m] |",
              "|---|---:|---:|---:|---:|---:|---:|"]
        for n, s in uav.items():
            mo = s.motion
            L.append(f"| {n} | {mo['mean_step_m']:.1f} | {100 * mo['full_step_fraction']:.0f} % | "
                     f"{100 * mo['stay_fraction']:.0f} % | {mo['mean_away_m']:+.2f} | {mo['mean_across_m']:.2f} | "
                     f"{mo['mean_range_m']:.0f} |")
        L.append("")
        if summary.target_speed_10s:
            L += ["The targets' mean true speed per 10 s of the mission [m/s]: "
                  + ", ".join(f"{v:.1f}" for v in summary.target_speed_10s) + ".", ""]
    if summary.pairs:
        L += ["## The flight default against each method", "",
              "Paired over the same trials: the ratio of time-averaged RMSEs (flight / other; 95 % paired "
              f"percentile bootstrap CI, {BOOTSTRAP_RESAMPLES} resamples) and the mean per-trial difference of "
              "window RMSE (flight minus other; 95 % t-interval).", "",
              "| flight method | other | flight / other (95 % CI) | other / flight | flight minus other [m] (95 % CI) |",
              "|---|---|---|---:|---|"]
        for (a, b), ((v, lo, hi), (d, dlo, dhi)) in summary.pairs.items():
            L.append(f"| {a} | {b} | {v:.2f} ({lo:.2f}, {hi:.2f}) | {1 / v:.2f} | {d:+.1f} ({dlo:+.1f}, {dhi:+.1f}) |")
        L.append("")
    flown = {n: s.flown for n, s in summary.methods.items() if s.flown}
    if flown:
        L += ["## How the vehicle flew its plans", "",
              "Flown methods: at each tick the plan's position, velocity and acceleration are sent to the "
              "vehicle model fitted to ArduCopter SITL (sim/guided.py), which flies with its autopilot's "
              "parameters; the next scan is where it is a tick later. Autopilot: WPNAV_SPEED, WPNAV_ACCEL "
              "of its parameter set; planned with: the planner's speed and acceleration limits; from the plan: "
              "the flown position's distance from the planned one at the next tick (median, p95, max over "
              "ticks and trials); speeds: mean over ticks / peak.", "",
              "| method | autopilot | planned with | from the plan [m] | planned speed [m/s] | flown speed [m/s] |",
              "|---|---|---|---|---|---|"]
        for n, f in flown.items():
            L.append(f"| {n} | {f['autopilot']}: {f['wpnav_speed_mps']:g} m/s, {f['wpnav_accel_mps2']:g} m/s² | "
                     f"{f['plan_speed_max_mps']:g} m/s, {f['plan_accel_max_mps2']:g} m/s² | "
                     f"{f['miss_median_m']:.2f} / {f['miss_p95_m']:.2f} / {f['miss_max_m']:.2f} | "
                     f"{f['planned_speed_mean_mps']:.1f} / {f['planned_speed_peak_mps']:.1f} | "
                     f"{f['speed_mean_mps']:.1f} / {f['speed_peak_mps']:.1f} |")
        L.append("")
    L += ["## Methods", ""] + [f"- `{m.name}`: {m.description}" for m in cfg.methods]
    L += ["", f"Orbit: radius {cfg.orbit_radius_m:g} m around the targets' initial centroid "
              f"({cfg.orbit_center[0]:.0f}, {cfg.orbit_center[1]:.0f}) m, counter-clockwise.",
          "", "Files: rmse.csv (step, method, target, rmse_m), per_trial.csv, rmse_vs_time.png, "
              "nees_vs_time.png, scenario_3d.png, scenario_top.png, flight.png, "
              "flown_paths.png (the UAV methods' paths side by side on the first trials).", ""]
    deg = {n: s.degenerate for n, s in summary.methods.items() if s.degenerate}
    if deg:
        L += [f"Degenerate updates (no finite weight; prior kept): {deg}", ""]
    return "\n".join(L)


def write_outputs(summary: Summary, trials: Sequence[TrialResult], out_dir, command: str,
                  figures: bool = True) -> dict:
    """rmse.csv, per_trial.csv, results.md and the figures in out_dir; returns the headline dict."""
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_csv(summary, out / "rmse.csv")
    write_per_trial_csv(summary, out / "per_trial.csv")
    (out / "results.md").write_text(results_markdown(summary, command), encoding="utf-8")
    if figures:
        from sim import figures as figs

        figs.rmse_vs_time(summary, out / "rmse_vs_time.png")
        figs.nees_vs_time(summary, out / "nees_vs_time.png")
        figs.scenario(summary.config.scenario, out / "scenario_3d.png", out / "scenario_top.png")
        figs.flight(summary.config, trials[0], out / "flight.png")
        figs.flown_paths(summary.config, trials, out / "flown_paths.png")
    return headline(summary)
