"""One tick of the monitor: scans in; estimates, target plans and the next UAV position out.

A tick t runs the paper's filter and planner in their order, from the beliefs held between ticks
(the predictions for the scan at t):

  1. update each target's predicted belief bel(x_t) with the scans taken at t, through the
     clutter-aware set likelihood (eqs. (9b), (10); ``tracking.update``);
  2. estimate: posterior mean and covariance; resample when the effective sample size is low;
  3. guidance: P1 from each posterior mean, warm-started by the target's previous plan;
  4. predict each belief to t+1 with its guidance (eq. (9a)): the particles' controls come
     from the configured particle steering (``steering``: the plan's first control, the free law
     where it is exact, reference plans when configured), noise Q;
  5. plan the next UAV position s_(t+1) from ``plan_from`` (a ``planning_inputs.UavState``) with the
     configured planner (``planners``: the paper's greedy rule by pseudo-updating those
     predictions, or the lookahead; ``planner_choice`` builds the one the setup names).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import numpy as np

from onboard.core.tracking import intent_tick
from onboard.core.tracking import filter as tracking
from onboard.core.guidance.predictor import Feedback, GuidanceWorkspace, Plan, PlanAsk, Solver, plan_guidance
from onboard.core.monitor_setup import MonitorSetup
from onboard.core.planner_choice import make_planner
from onboard.core.planning.planners import Planner, PlanningInputs
from onboard.core.planning.next_position import PlanningResult
from onboard.core.planning.inputs import UavState
from onboard.core.tracking.steering import (AHEAD_STEPS, FreeSteering, ParticleSteering, ReferenceSteering, Replan,
                                            SideMode, SideSteering, TargetTick)
from onboard.core.tracking.steering_setup import PlanSteering

__all__ = ["PlanSteering", "MonitorSetup", "MonitorState", "Scan", "TickResult", "SideMode", "UavState",
           "initial_state", "tick", "replanner", "uav_planner", "particle_steering"]


def uav_planner(setup: MonitorSetup) -> Planner:
    """The UAV planner ``setup.planner`` names (onboard/core/planner_choice.py), built once per setup."""
    if "planner" not in setup.parts:
        setup.parts["planner"] = make_planner(setup)
    return setup.parts["planner"]


def particle_steering(setup: MonitorSetup) -> ParticleSteering:
    """The particle steering ``setup.plan_steering`` chooses (onboard/core/tracking/steering.py): free,
    by reference plans, or side-aware; built once per setup."""
    if "steering" not in setup.parts:
        ps = setup.plan_steering
        setup.parts["steering"] = (FreeSteering(setup) if ps is None
                                   else SideSteering(setup) if ps.sides else ReferenceSteering(setup))
    return setup.parts["steering"]


@dataclass(frozen=True, eq=False)
class MonitorState:
    beliefs: tuple[tracking.ParticleSet, ...]  # predicted beliefs for the next scan time
    plans: tuple[Plan | None, ...]
    step: int = 0
    # per target, what the particle steering kept from last tick (``Steered.memory``: the
    # reference plans, or the side modes; () for the free steering)
    steering: tuple[Any, ...] = ()
    # per target, what its motion modes kept (``tracking.intent``: onboard/core/tracking/intent_tick.py); ()
    # without modes, or when the app rebuilt the state (the modes start again)
    intent: tuple[intent_tick.IntentMemory, ...] = ()


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
    # with motion modes (``tracking.intent``): per target, the posterior probability of each mode
    # (its goals', stationary, free: ``Intent.label``), and whether it was re-seeded this tick
    # because its bearings stopped agreeing with every mode
    mode_probabilities: tuple[np.ndarray, ...] | None = None
    reseeded: np.ndarray | None = None

    @property
    def next_position(self) -> np.ndarray | None:
        return None if self.planning is None else self.planning.position


def initial_state(setup: MonitorSetup, rng: np.random.Generator) -> MonitorState:
    if setup.intents is not None:
        return MonitorState(intent_tick.initial_beliefs(setup, rng), (None,) * setup.n_targets, 0)
    beliefs = tuple(tracking.initialise(m, setup.initial_cov, setup.n_particles, rng)
                    for m in setup.initial_means)
    return MonitorState(beliefs, (None,) * setup.n_targets, 0)


def tick(setup: MonitorSetup, state: MonitorState, scans: Sequence[Scan], rng: np.random.Generator,
         plan_from: UavState | None = None, workspace: GuidanceWorkspace | None = None,
         timer: Callable[[], float] = time.perf_counter, planner_rng: np.random.Generator | None = None
         ) -> tuple[MonitorState, TickResult]:
    """Run one tick (the module's steps 1-5). ``plan_from``: where the planner starts from, the
    UAV where it is or will be at the next tick (``planning_inputs.UavState``: its position, ENU m; its
    planar velocity, for the vehicle motion; the plan's planar acceleration, for a continuous one,
    ``planning.jerk_max_mps3`` > 0); None skips the UAV planning (e.g. fixed sensors).
    ``planner_rng``: the planner's own random stream (the random baseline draws from it; default
    ``rng``), so a planner's draws never shift the filter's."""
    if setup.intents is not None:
        return _tick_with_modes(setup, state, scans, rng, plan_from, workspace, timer, planner_rng)
    t0 = timer()
    posts, means, covs, degenerate = _update_and_estimate(setup, state.beliefs, scans, rng)  # 1, 2
    t1 = timer()
    plans = _guidance(setup, state, means, workspace, timer)  # 3
    t2 = timer()
    beliefs, memory = _predict(setup, state, posts, means, covs, plans,
                               lambda goal: replanner(setup, goal, workspace, timer), rng)  # 4
    t3 = timer()
    planning = _plan_uav(setup, beliefs, plans, plan_from, rng, planner_rng)  # 5
    t4 = timer()
    timings = {"tracking": (t1 - t0) + (t3 - t2), "guidance": t2 - t1, "planning": t4 - t3, "tick": t4 - t0}
    return (MonitorState(beliefs, plans, state.step + 1, memory),
            TickResult(means, covs, plans, planning, degenerate, timings))


def _plan_uav(setup: MonitorSetup, beliefs, plans, plan_from: UavState | None, rng, planner_rng,
              weights: np.ndarray | None = None):
    """Step 5: the next UAV position from ``plan_from`` (None: no planning)."""
    if plan_from is None:
        return None
    vel = np.zeros(2) if plan_from.velocity is None else np.asarray(plan_from.velocity, float)[:2]
    acc = None if plan_from.acceleration is None else np.asarray(plan_from.acceleration, float)[:2]
    inputs = PlanningInputs(beliefs, plans, np.asarray(plan_from.position, float), vel, acc, weights)
    return uav_planner(setup).plan(inputs, rng if planner_rng is None else planner_rng)


def _tick_with_modes(setup: MonitorSetup, state: MonitorState, scans, rng, plan_from, workspace, timer, planner_rng):
    """``tick`` for beliefs whose particles carry motion modes (onboard/core/tracking/intent_tick.py)."""
    M = setup.n_targets
    memory = state.intent if len(state.intent) == M else tuple(intent_tick.IntentMemory() for _ in range(M))
    sides = setup.plan_steering is not None and setup.plan_steering.sides
    t0 = timer()
    upd = intent_tick.update(setup, state.beliefs, memory, scans, rng)  # 1, 2
    t1 = timer()
    per_target, plans = intent_tick.guidance(setup, upd.posts, upd.memory, workspace, timer, sides)  # 3
    t2 = timer()
    beliefs, memory = intent_tick.predict(setup, particle_steering(setup), upd.posts, per_target, plans, upd.memory,
                                          lambda goal: replanner(setup, goal, workspace, timer), rng)  # 4
    t3 = timer()
    planning = None
    if plan_from is not None:  # 5: the lookahead scores the modes' mixture, the others the likeliest
        pb, paths, weights = intent_tick.planner_inputs(setup, beliefs, upd.posts, per_target, plans, upd.means,
                                                        mixture=setup.planner == "lookahead")
        planning = _plan_uav(setup, pb, paths, plan_from, rng, planner_rng, weights)
    t4 = timer()
    timings = {"tracking": (t1 - t0) + (t3 - t2), "guidance": t2 - t1, "planning": t4 - t3, "tick": t4 - t0}
    return (MonitorState(beliefs, plans, state.step + 1, (), memory),
            TickResult(upd.means, upd.covs, plans, planning, upd.degenerate, timings, upd.probabilities,
                       upd.reseeded))


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
    feedback = Feedback.CONSTRAINED if setup.plan_steering is not None else Feedback.NONE
    solver = Solver(workspace, timer)
    out = []
    for j in range(setup.n_targets):
        modes = state.steering[j] if sides and state.steering else ()
        ask = PlanAsk(feedback, ahead=AHEAD_STEPS if sides else 0, nearby=tuple(m.plan.shifted() for m in modes))
        out.append(plan_guidance(setup.model, setup.guidance, setup.obstacles, means[j], setup.goals[j],
                                 previous=state.plans[j], ask=ask, solver=solver))
    return tuple(out)


def _predict(setup: MonitorSetup, state: MonitorState, posts: Sequence[tracking.ParticleSet], means: np.ndarray,
             covs: np.ndarray, plans: Sequence[Plan], replan_to: Callable[[np.ndarray], Replan],
             rng: np.random.Generator):
    """Step 4: each posterior predicted to t+1 with the particle steering's controls (its
    reference plans count as tracking time); the beliefs and what the steering keeps.
    ``replan_to(goal)``: the steering's P1 toward a goal (``replanner``)."""
    beliefs, memory = [], []
    budgets = particle_steering(setup).budgets(plans)
    for j in range(setup.n_targets):
        target = TargetTick(posts[j], means[j], covs[j], setup.goals[j], plans[j], state.plans[j],
                            replan_to(setup.goals[j]), budgets[j])
        steered = particle_steering(setup).steer(target, state.steering[j] if state.steering else (), rng)
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
    solver = Solver(workspace, timer)

    def replan(x: np.ndarray, previous: Plan | None, sides: np.ndarray | None = None, strict: bool = False,
               nearby: Plan | None = None, explore: bool = True, budget: int | None = None) -> Plan:
        p = params if budget is None else replace(params, max_qp_solves=min(budget, params.max_qp_solves))
        ask = PlanAsk(Feedback.ALWAYS, ahead, sides, strict_sides=strict, nearby=nearby, explore=explore)
        return plan_guidance(setup.model, p, setup.obstacles, x, goal, previous=previous, ask=ask, solver=solver)
    return replan
