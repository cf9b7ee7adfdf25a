"""The tick's steps 1-4 (onboard/core/monitor.py) for beliefs whose particles carry motion modes
(``tracking.intent``; onboard/core/intent.py holds the modes' maths).

1. update, as the paper's filter, after an innovation check: a target whose last scans the belief
   did not explain (``intent.SURPRISE_COUNT`` of ``SURPRISE_WINDOW``) gets a wide share of its
   particles re-drawn along the bearings (stationary or free), so a belief that has lost its
   target widens instead of staying sure;
3. guidance: P1 once per goal mode present, from the weighted mean of that mode's particles (the
   particles of a mode share its plan: the guidance is the expensive part);
4. prediction: the Markov switch, then each mode's particles by their own motion: a goal mode's by
   the configured particle steering toward its goal (the most probable goal mode's with the full
   strategy, the others' with the free law and their plan's control), stationary ones stand, free
   ones coast with random acceleration.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from onboard.core import intent as im
from onboard.core import tracking
from onboard.core.guidance import GuidanceWorkspace, Plan, plan_guidance
from onboard.core.steering import AHEAD_STEPS, TargetTick

MIN_MODE_SHARE = 1e-3  # a goal mode holding less of a target's weight gets no plan of its own this tick


@dataclass(frozen=True, eq=False)
class IntentMemory:
    """What a target's modes keep between ticks."""

    plans: dict = field(default_factory=dict)  # goal mode -> its last P1 plan (the next warm start)
    steering: dict = field(default_factory=dict)  # goal mode -> its particle steering's memory
    unexplained: tuple[bool, ...] = ()  # the last scans with bearings: did the belief miss them


@dataclass(frozen=True, eq=False)
class IntentUpdate:
    posts: list  # resampled posteriors
    means: np.ndarray
    covs: np.ndarray
    degenerate: np.ndarray
    memory: tuple[IntentMemory, ...]
    probabilities: tuple[np.ndarray, ...]  # per target, (K + 2,) its modes' posterior probabilities
    reseeded: np.ndarray  # (M,) bool: re-seeded along the bearings this tick


def initial_beliefs(setup, rng: np.random.Generator) -> tuple[tracking.ParticleSet, ...]:
    """N(mu_0, Sigma_0) per target, each particle's mode drawn from the target's prior (a
    stationary one at rest)."""
    out = []
    for m, intent in zip(setup.initial_means, setup.intents):
        ps = tracking.initialise(m, setup.initial_cov, setup.n_particles, rng)
        out.append(with_modes(ps, intent, rng))
    return tuple(out)


def with_modes(ps: tracking.ParticleSet, intent: im.Intent, rng: np.random.Generator) -> tracking.ParticleSet:
    """``ps`` with a mode per particle (drawn from the prior where it has none: a belief the app
    rebuilt or re-seeded)."""
    if ps.modes is not None and len(ps.modes) == len(ps):
        return ps
    modes = im.draw(intent, len(ps), rng)
    particles = ps.particles.copy()
    particles[modes == im.STATIONARY, 3:] = 0.0
    return tracking.ParticleSet(particles, ps.log_weights, ps.labels, modes)


def _reseed_modes(rng: np.random.Generator) -> Callable[[int], np.ndarray]:
    return lambda k: np.where(rng.random(k) < 0.5, im.STATIONARY, im.FREE)


def _reseeded_velocities(ps: tracking.ParticleSet, n_old: int, rng: np.random.Generator) -> tracking.ParticleSet:
    """The re-drawn particles (from index ``n_old``) at rest if stationary, else with a velocity
    N(0, RESEED_SPEED^2 I): the motion that lost the target is not theirs."""
    if len(ps) == n_old:
        return ps
    p = ps.particles.copy()
    new = np.arange(n_old, len(ps))
    p[new, 3:] = 0.0
    free = new[ps.modes[new] == im.FREE]
    p[free, 3:5] = im.RESEED_SPEED_MPS * rng.standard_normal((len(free), 2))
    return replace(ps, particles=p)


def update(setup, beliefs: Sequence[tracking.ParticleSet], memory: Sequence[IntentMemory], scans,
           rng: np.random.Generator) -> IntentUpdate:
    """Steps 1-2 for every target (``monitor._update_and_estimate`` with modes and the innovation
    check)."""
    M = setup.n_targets
    posts, out_mem, probs = [], [], []
    degenerate, reseeded = np.zeros(M, dtype=bool), np.zeros(M, dtype=bool)
    means, covs = np.zeros((M, 6)), np.zeros((M, 6, 6))
    reseed = tracking.Recovery(im.RESEED_PRIOR, im.RESEED_SHARE, im.RESEED_SIGMA_M)
    for j in range(M):
        mem = memory[j] if j < len(memory) else IntentMemory()
        intent = setup.intents[j]
        j_scans = [(np.asarray(s.sensor_position, float)[:2], s.bearings[j],
                    None if s.clutter_rates is None else s.clutter_rates[j]) for s in scans]
        prior = with_modes(beliefs[j], intent, rng)
        n = len(prior)
        window = mem.unexplained
        if j_scans and sum(window) >= im.SURPRISE_COUNT:
            prior = tracking.recover(prior, j_scans[-1][0], j_scans[-1][1], reseed, setup.sensor.sigma_rad, rng,
                                     new_modes=_reseed_modes(rng))
            prior = _reseeded_velocities(prior, n, rng)
            reseeded[j] = len(prior) > n
            window = () if reseeded[j] else window
        elif setup.recovery is not None and j_scans:
            prior = tracking.recover(prior, j_scans[-1][0], j_scans[-1][1], setup.recovery, setup.sensor.sigma_rad,
                                     rng)
        upd = tracking.update(prior, j_scans, setup.sensor)
        degenerate[j] = upd.degenerate
        told = [e < im.EXPLAINED_MIN for e in upd.explained if np.isfinite(e) or e == np.inf]
        window = (window + tuple(told))[-im.SURPRISE_WINDOW:]
        post = tracking.trim(upd.particles, n)
        means[j], covs[j] = tracking.estimate(post)
        probs.append(im.probabilities(post.log_weights, post.modes, intent.n_goals))
        posts.append(tracking.resample_if_needed(post, setup.resample_fraction, rng, setup.regularise_bandwidth,
                                                 covs[j]))
        out_mem.append(IntentMemory(mem.plans, mem.steering, window))
    return IntentUpdate(posts, means, covs, degenerate, tuple(out_mem), tuple(probs), reseeded)


def _mode_moments(ps: tracking.ParticleSet, sel: np.ndarray):
    """(share of the weight, weighted mean (6,), covariance (6, 6), the sub-belief) of the particles ``sel``."""
    logw = ps.log_weights[sel]
    share = float(np.exp(tracking.logsumexp(logw)))
    sub = tracking.ParticleSet(ps.particles[sel], logw - tracking.logsumexp(logw),
                               None if ps.labels is None else ps.labels[sel], ps.modes[sel])
    mean, cov = tracking.estimate(sub)
    return share, mean, cov, sub


def guidance(setup, posts: Sequence[tracking.ParticleSet], memory: Sequence[IntentMemory],
             workspace: GuidanceWorkspace | None, timer: Callable[[], float], sides: bool):
    """Step 3: per target, P1 for each goal mode holding weight, from its particles' mean, warm-started
    by its own last plan. Returns per target {goal mode: (plan, share, mean, cov)} and the target's
    main plan (its most probable goal mode's, or its standing / coasting path without one)."""
    per_target, main = [], []
    for j, ps in enumerate(posts):
        intent = setup.intents[j]
        mem = memory[j]
        found = {}
        for k in range(intent.n_goals):
            sel = ps.modes == k
            if not sel.any():
                continue
            share, mean, cov, sub = _mode_moments(ps, sel)
            if share < MIN_MODE_SHARE:
                continue
            steer_mem = mem.steering.get(k, ()) if sides else ()
            plan = plan_guidance(setup.model, setup.guidance, setup.obstacles, mean, intent.goals[k],
                                 previous=mem.plans.get(k), workspace=workspace, timer=timer,
                                 with_feedback="constrained" if setup.plan_steering is not None else False,
                                 nearby=tuple(m.plan.shifted() for m in steer_mem),
                                 ahead=AHEAD_STEPS if sides else 0)
            found[k] = (plan, share, mean, cov, sub)
        per_target.append(found)
        if found:
            main.append(found[max(found, key=lambda k: found[k][1])][0])
        else:
            mean, _ = tracking.estimate(ps)
            main.append(motion_plan(setup, mean, dominant_motion(ps, intent)))
    return per_target, tuple(main)


def dominant_motion(ps: tracking.ParticleSet, intent: im.Intent) -> int:
    """STATIONARY or FREE, whichever holds more weight."""
    p = im.probabilities(ps.log_weights, ps.modes, intent.n_goals)
    return im.STATIONARY if p[-2] >= p[-1] else im.FREE


def motion_plan(setup, mean: np.ndarray, mode: int) -> Plan:
    """A Plan holding a stationary or free mode's path (no control, no guidance solved): what the
    planner and the app read of a target no goal mode describes."""
    T = setup.guidance.horizon
    K = len(setup.obstacles)
    status = "stationary" if mode == im.STATIONARY else "free"
    return Plan(status, float("nan"), 0.0, 0, np.zeros((T, 3)), im.motion_path(mean, mode, T, setup.model),
                np.full((T - 1, K), -1))


def planner_plans(setup, posts: Sequence[tracking.ParticleSet], per_target, main: Sequence[Plan],
                  means: np.ndarray) -> tuple[Plan, ...]:
    """Per target, the path the UAV planner scores: its most probable mode's (a goal mode's plan,
    or the standing / coasting path)."""
    out = []
    for j, ps in enumerate(posts):
        intent = setup.intents[j]
        p = im.probabilities(ps.log_weights, ps.modes, intent.n_goals)
        best = int(np.argmax(p))
        if best < intent.n_goals and best in per_target[j]:
            out.append(per_target[j][best][0])
        elif best >= intent.n_goals:
            sel = ps.modes == im.codes(best, intent.n_goals)
            mean = _mode_moments(ps, sel)[1] if sel.any() else means[j]
            out.append(motion_plan(setup, mean, int(im.codes(best, intent.n_goals))))
        else:
            out.append(main[j])
    return tuple(out)


def predict(setup, steering, posts: Sequence[tracking.ParticleSet], per_target, main: Sequence[Plan],
            memory: Sequence[IntentMemory], replanner: Callable, rng: np.random.Generator):
    """Step 4: the Markov switch, then each mode's particles by their own motion. Returns the
    predicted beliefs and each target's memory (its goal modes' plans and steering)."""
    beliefs, out_mem = [], []
    budgets = steering.budgets(main)
    for j, ps in enumerate(posts):
        intent = setup.intents[j]
        modes = im.switch(ps.modes, intent, setup.intent.switch_prob, rng)
        particles = ps.particles.copy()
        labels = np.full(len(ps), -1)
        found = per_target[j]
        lead = max(found, key=lambda k: found[k][1]) if found else None
        plans, steer_mem = {}, {}
        for k, (plan, share, mean, cov, _) in found.items():
            sel = modes == k
            if not sel.any():
                plans[k] = plan
                continue
            sub = tracking.ParticleSet(ps.particles[sel], ps.log_weights[sel] - tracking.logsumexp(ps.log_weights[sel]),
                                       None if ps.labels is None or k != lead else ps.labels[sel], modes[sel])
            target = TargetTick(sub, mean, cov, intent.goals[k], plan, memory[j].plans.get(k),
                                replanner(intent.goals[k]), budgets[j] if k == lead else None)
            if k == lead:
                steered = steering.steer(target, memory[j].steering.get(k, ()), rng)
                steer_mem[k] = steered.memory
                if steered.labels is not None:
                    labels[sel] = steered.labels
            else:
                steered = steering.free(target, rng)
            moved = tracking.predict(replace(sub, labels=None), setup.model, steered.controls, rng)
            particles[sel] = moved.particles
            plans[k] = plan
        for k in set(np.unique(modes[modes >= 0]).tolist()) - set(found):
            # a goal mode with too little weight for a plan of its own: its particles coast this tick
            sel = modes == k
            particles[sel] = im.predict_free(ps.particles[sel], setup.model, setup.intent, setup.ground_obstacles,
                                             setup.area_min, setup.area_max, rng)
        sel = modes == im.STATIONARY
        particles[sel] = im.predict_stationary(ps.particles[sel], setup.intent, rng)
        sel = modes == im.FREE
        particles[sel] = im.predict_free(ps.particles[sel], setup.model, setup.intent, setup.ground_obstacles,
                                         setup.area_min, setup.area_max, rng)
        beliefs.append(tracking.ParticleSet(particles, ps.log_weights, labels if lead is not None else None, modes))
        out_mem.append(IntentMemory(plans, steer_mem, memory[j].unexplained))
    return tuple(beliefs), tuple(out_mem)


def mode_summary(setup, probabilities: Sequence[np.ndarray]) -> tuple[tuple[str, float], ...]:
    """Per target, its most probable mode's name and probability (what the operator is shown)."""
    out = []
    for intent, p in zip(setup.intents, probabilities):
        c = int(np.argmax(p))
        out.append((intent.label(c), float(p[c])))
    return tuple(out)


__all__ = ["IntentMemory", "IntentUpdate", "initial_beliefs", "update", "guidance", "predict", "planner_plans",
           "mode_summary", "with_modes"]
