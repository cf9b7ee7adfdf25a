"""One tick of the monitor: scans in; estimates, target plans and the next UAV position out.

A tick t runs the paper's filter and planner in their order, from the beliefs held between ticks
(the predictions for the scan at t):

  1. update each target's predicted belief bel(x_t) with the scans taken at t, through the
     clutter-aware set likelihood (eq:update, eq:rfs_like; ``tracking.update``);
  2. estimate: posterior mean and covariance; resample when the effective sample size is low;
  3. guidance: P1 from each posterior mean, warm-started by the target's previous plan;
  4. predict each belief to t+1 with its guidance (eq:prediction): the particles' controls come
     from the configured particle steering (``steering``: the plan's first control, the free law
     where it is exact, reference plans when configured), noise Q;
  5. plan the next UAV position s_(t+1) from ``plan_from`` with the configured planner
     (``planners``: the paper's greedy rule by pseudo-updating those predictions, the lookahead,
     or a baseline).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, Callable, Sequence

import numpy as np

from onboard.core import tracking
from onboard.core.dynamics import MotionModel
from onboard.core.guidance import FreeLaw, GuidanceParams, GuidanceWorkspace, Plan, free_law, plan_guidance
from onboard.core.obstacles import Obstacles
from onboard.core.planners import Planner, PlanningInputs, make_planner
from onboard.core.planning import CandidateGrid, LookaheadParams, PlanningResult, UavMotion
from onboard.core.steering import (AHEAD_STEPS, FreeSteering, ParticleSteering, ReferenceSteering, Replan,
                                   SideMode, SideSteering, TargetTick)

__all__ = ["PlanSteering", "MonitorSetup", "MonitorState", "Scan", "TickResult", "SideMode", "initial_state",
           "tick", "replanner"]


@dataclass(frozen=True)
class PlanSteering:
    """How the particles of a target whose plan is constrained are steered (docs/TRACKING.md):
    by the affine law (``LocalLaw``) of the nearest reference plan, the posterior mean's or one
    of ``references`` more (an even number: pairs out to ``spread_sigma`` standard deviations
    either side along the cloud's major axis), if it lies within ``trust_sigma`` standard
    deviations (Mahalanobis, position) of one. A share ``1 - steered_share``, and every particle
    farther out, keeps the mean plan's control (robustness where the target's plan differs from
    all of them). Used while the mean's plan has an active row (rounding an obstacle, or at an
    input or speed limit): elsewhere the free law is exact."""

    references: int
    spread_sigma: float
    steered_share: float
    trust_sigma: float
    max_qp_solves: int  # per reference plan (capped by the guidance's budget, which the mean's has)
    # each particle carries the side of each obstacle its target takes, and each side present has
    # its own mean's plan and spread pairs (``_side_modes``); a side costing P1 d more (relative)
    # than its parent's gets a share 1 / (1 + exp(d / side_temperature)) of its particles at birth
    sides: bool
    side_temperature: float

    @classmethod
    def from_config(cls, tr) -> "PlanSteering | None":
        """From the scenario's ``tracking.plan_*`` (onboard/settings.py declares the defaults)."""
        if not tr.plan_steering:
            return None
        return cls(tr.plan_references, tr.plan_spread_sigma, tr.plan_steered_share, tr.plan_trust_sigma,
                   tr.plan_max_qp_solves, tr.plan_sides, tr.plan_side_temperature)


MAX_SIDE_MODES = 4  # per target
MIN_SIDE_SHARE = 0.01  # a side mode holding less of the posterior weight is dropped
SIDE_LEAD_STEPS = 3  # an obstacle first met this many steps ahead or later gets two sides


@dataclass(frozen=True, eq=False)
class MonitorSetup:
    """Everything static about a mission, built once from a scenario (``from_scenario``: every
    value from it; onboard/settings.py declares the defaults, so none here)."""

    model: MotionModel
    sensor: tracking.SensorModel
    guidance: GuidanceParams
    obstacles: Obstacles  # as built; the guidance inflates by its own margin
    uav_obstacles: Obstacles  # inflated by the UAV's clearance margin
    goals: np.ndarray  # (M, 3) goal centroid per target
    initial_means: np.ndarray  # (M, 6)
    initial_cov: np.ndarray  # (6, 6)
    grid: CandidateGrid
    area_min: np.ndarray
    area_max: np.ndarray
    n_particles: int
    resample_fraction: float
    objective: str
    control_mix: float  # fraction of particles predicted with a random control
    regularise_bandwidth: float  # h of the regularised resampling (tracking.resample_if_needed)
    free_steering: FreeLaw | None  # particles whose own plan is the free optimum steer by it
    plan_steering: PlanSteering | None  # the others, while the plan is constrained, by reference plans
    recovery: tracking.Recovery | None  # a lost target found again along the bearings (tracking.recover)
    planner: str  # greedy | lookahead
    lookahead_steps: int
    motion: UavMotion
    lookahead: LookaheadParams

    @classmethod
    def from_scenario(cls, sc) -> "MonitorSetup":
        """From a scenario; to change a setting, change the scenario (``onboard.config.override``)."""
        obstacles = Obstacles.from_boxes(sc.obstacles)
        d = sc.dynamics
        model = MotionModel.create(d.dt_s, d.friction, d.mass_kg, d.process_noise_diag)
        return cls(
            model=model,
            sensor=tracking.SensorModel.from_config(sc.sensor),
            guidance=GuidanceParams.from_config(sc.guidance),
            obstacles=obstacles,
            uav_obstacles=obstacles.inflate(sc.uav.obstacle_margin_m),
            goals=np.array([sc.goal_of(t).center_m for t in sc.targets], dtype=float),
            initial_means=np.array([t.mean for t in sc.targets]),
            initial_cov=sc.initial_cov,
            grid=CandidateGrid.from_config(sc.uav),
            area_min=np.array(sc.area.min_m), area_max=np.array(sc.area.max_m),
            n_particles=sc.tracking.particles,
            resample_fraction=sc.tracking.resample_ess_fraction,
            control_mix=sc.tracking.control_mix,
            regularise_bandwidth=sc.tracking.regularise_bandwidth,
            free_steering=free_law(model, GuidanceParams.from_config(sc.guidance)),
            plan_steering=PlanSteering.from_config(sc.tracking),
            recovery=tracking.Recovery.from_config(sc.tracking),
            objective=sc.planning.objective,
            planner=sc.planning.planner,
            lookahead_steps=sc.planning.lookahead_steps,
            motion=UavMotion.from_config(sc.planning),
            lookahead=LookaheadParams.from_config(sc.planning.lookahead),
        )

    @property
    def n_targets(self) -> int:
        return len(self.goals)

    # what the configuration chooses once: the planner and the particle steering (derived, not
    # settings: ``planner`` and ``plan_steering`` above name them)
    @cached_property
    def uav_planner(self) -> Planner:
        return make_planner(self)

    @cached_property
    def steering(self) -> ParticleSteering:
        if self.plan_steering is None:
            return FreeSteering(self)
        return SideSteering(self) if self.plan_steering.sides else ReferenceSteering(self)


@dataclass(frozen=True, eq=False)
class MonitorState:
    beliefs: tuple[tracking.ParticleSet, ...]  # predicted beliefs for the next scan time
    plans: tuple[Plan | None, ...]
    step: int = 0
    # per target, what the particle steering kept from last tick (``Steered.memory``: the
    # reference plans, or the side modes; () for the free steering)
    steering: tuple[Any, ...] = ()


@dataclass(frozen=True, eq=False)
class Scan:
    """Bearings (rad, per target channel) taken from one sensor position (ENU, m).

    ``clutter_rates``: per channel, the clutter rate Lambda of this scan's likelihood (a DF that
    measures its clutter, onboard/core/doa.py), None (or an entry None) for the setup's."""

    sensor_position: np.ndarray
    bearings: tuple[np.ndarray, ...]
    clutter_rates: tuple[float | None, ...] | None = None


@dataclass(frozen=True, eq=False)
class TickResult:
    means: np.ndarray  # (M, 6) posterior means at this tick
    covs: np.ndarray  # (M, 6, 6)
    plans: tuple[Plan, ...]
    planning: PlanningResult | None
    degenerate: np.ndarray  # (M,) bool: the update left no finite weight; the prior was kept
    timings_s: dict = field(default_factory=dict)

    @property
    def next_position(self) -> np.ndarray | None:
        return None if self.planning is None else self.planning.position


def initial_state(setup: MonitorSetup, rng: np.random.Generator) -> MonitorState:
    beliefs = tuple(tracking.initialise(m, setup.initial_cov, setup.n_particles, rng)
                    for m in setup.initial_means)
    return MonitorState(beliefs, (None,) * setup.n_targets, 0)


def tick(setup: MonitorSetup, state: MonitorState, scans: Sequence[Scan], rng: np.random.Generator,
         plan_from: np.ndarray | None = None, workspace: GuidanceWorkspace | None = None,
         timer: Callable[[], float] = time.perf_counter, uav_velocity: np.ndarray | None = None,
         planner_rng: np.random.Generator | None = None, uav_acceleration: np.ndarray | None = None
         ) -> tuple[MonitorState, TickResult]:
    """Run one tick (the module's steps 1-5). ``plan_from`` (ENU, m): where the UAV is or will be
    at the next tick, where the planner starts from; None skips the UAV planning (e.g. fixed
    sensors). ``uav_velocity`` (ENU, m/s, planar): the UAV's velocity there, for the vehicle
    motion; ``uav_acceleration`` (ENU, m/s^2, planar): the plan's acceleration there, for a
    continuous one (``planning.jerk_max_mps3`` > 0; None: 0). ``planner_rng``: the planner's own random stream (the random baseline draws from it;
    default ``rng``), so a planner's draws never shift the filter's."""
    t0 = timer()
    posts, means, covs, degenerate = _update_and_estimate(setup, state.beliefs, scans, rng)  # 1, 2
    t1 = timer()
    plans = _guidance(setup, state, means, workspace, timer)  # 3
    t2 = timer()
    beliefs, memory = _predict(setup, state, posts, means, covs, plans, workspace, timer, rng)  # 4
    t3 = timer()
    planning = None
    if plan_from is not None:  # 5
        vel = np.zeros(2) if uav_velocity is None else np.asarray(uav_velocity, float)[:2]
        acc = None if uav_acceleration is None else np.asarray(uav_acceleration, float)[:2]
        planning = setup.uav_planner.plan(PlanningInputs(beliefs, plans, np.asarray(plan_from, float), vel, acc),
                                          rng if planner_rng is None else planner_rng)
    t4 = timer()
    timings = {"tracking": (t1 - t0) + (t3 - t2), "guidance": t2 - t1, "planning": t4 - t3, "tick": t4 - t0}
    return (MonitorState(beliefs, plans, state.step + 1, memory),
            TickResult(means, covs, plans, planning, degenerate, timings))


def _update_and_estimate(setup: MonitorSetup, beliefs: Sequence[tracking.ParticleSet], scans: Sequence[Scan],
                         rng: np.random.Generator):
    """Steps 1-2 per target: the posteriors (resampled when due), means (M, 6), covariances
    (M, 6, 6), and which updates left no finite weight (the prior was kept)."""
    M = setup.n_targets
    posts, degenerate = [], np.zeros(M, dtype=bool)
    means, covs = np.zeros((M, 6)), np.zeros((M, 6, 6))
    for j in range(M):
        j_scans = [(np.asarray(s.sensor_position, float)[:2], s.bearings[j],
                    None if s.clutter_rates is None else s.clutter_rates[j]) for s in scans]
        prior = beliefs[j]
        if setup.recovery is not None and j_scans:  # the last scan's bearings propose where a lost target is
            prior = tracking.recover(prior, j_scans[-1][0], j_scans[-1][1], setup.recovery, setup.sensor.sigma_rad,
                                     rng)
        upd = tracking.update(prior, j_scans, setup.sensor)
        degenerate[j] = upd.degenerate
        post = tracking.trim(upd.particles, len(beliefs[j]))
        means[j], covs[j] = tracking.estimate(post)
        posts.append(tracking.resample_if_needed(post, setup.resample_fraction, rng,
                                                 setup.regularise_bandwidth, covs[j]))
    return posts, means, covs, degenerate


def _guidance(setup: MonitorSetup, state: MonitorState, means: np.ndarray, workspace: GuidanceWorkspace | None,
              timer: Callable[[], float]) -> tuple[Plan, ...]:
    """Step 3: P1 from each posterior mean, warm-started by the target's previous plan (with its
    law when the particle steering uses it: a plan with an active row). With side modes, their
    plans of the last tick are the next warm starts: the mean of a cloud split between two sides
    of an obstacle often has no plan near its own last one."""
    sides = setup.plan_steering is not None and setup.plan_steering.sides
    out = []
    for j in range(setup.n_targets):
        modes = state.steering[j] if sides and state.steering else ()
        out.append(plan_guidance(setup.model, setup.guidance, setup.obstacles, means[j], setup.goals[j],
                                 previous=state.plans[j], workspace=workspace, timer=timer,
                                 with_feedback="constrained" if setup.plan_steering is not None else False,
                                 nearby=tuple(m.plan.shifted() for m in modes), ahead=AHEAD_STEPS if sides else 0))
    return tuple(out)


def _predict(setup: MonitorSetup, state: MonitorState, posts: Sequence[tracking.ParticleSet], means: np.ndarray,
             covs: np.ndarray, plans: Sequence[Plan], workspace: GuidanceWorkspace | None,
             timer: Callable[[], float], rng: np.random.Generator):
    """Step 4: each posterior predicted to t+1 with the particle steering's controls (its
    reference plans count as tracking time); the beliefs and what the steering keeps."""
    beliefs, memory = [], []
    budgets = setup.steering.budgets(plans)
    for j in range(setup.n_targets):
        target = TargetTick(posts[j], means[j], covs[j], setup.goals[j], plans[j], state.plans[j],
                            replanner(setup, setup.goals[j], workspace, timer), budgets[j])
        steered = setup.steering.steer(target, state.steering[j] if state.steering else (), rng)
        post = replace(posts[j], labels=steered.labels)
        beliefs.append(tracking.predict(post, setup.model, steered.controls, rng))
        memory.append(steered.memory)
    return tuple(beliefs), tuple(memory)


def replanner(setup: MonitorSetup, goal: np.ndarray, workspace: GuidanceWorkspace | None = None,
              timer: Callable[[], float] = time.perf_counter) -> Replan:
    """P1 toward ``goal`` as the particle steering calls it (``steering.Replan``): from a state,
    warm-started by a plan (and a ``nearby`` plan of this tick), with its law, held to sides;
    with a reference plan's QP budget (``plan_max_qp_solves``, capped by the guidance's own, and
    by ``budget`` when given)."""
    params = setup.guidance
    ahead = AHEAD_STEPS if setup.plan_steering is not None and setup.plan_steering.sides else 0
    if setup.plan_steering is not None:
        params = replace(params, max_qp_solves=min(setup.plan_steering.max_qp_solves, params.max_qp_solves))

    def replan(x: np.ndarray, previous: Plan | None, sides: np.ndarray | None = None, strict: bool = False,
               nearby: Plan | None = None, explore: bool = True, budget: int | None = None) -> Plan:
        p = params if budget is None else replace(params, max_qp_solves=min(budget, params.max_qp_solves))
        return plan_guidance(setup.model, p, setup.obstacles, x, goal, previous=previous, workspace=workspace,
                             timer=timer, with_feedback=True, sides=sides, strict_sides=strict, nearby=nearby,
                             explore=explore, ahead=ahead)
    return replan
