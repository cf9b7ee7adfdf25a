"""The tick's steps 1-4 (onboard/core/monitor.py) for beliefs whose particles carry motion modes
(``tracking.intent``; onboard/core/tracking/intent.py holds the modes' maths).

1. update, as the paper's filter, after an innovation check: a target whose last scans the belief
   did not explain (``intent.SURPRISE_COUNT`` of ``SURPRISE_WINDOW``) gets a wide share of its
   particles re-drawn along the bearings (stationary or free), so a belief that has lost its
   target widens instead of staying sure;
3. guidance: P1 once per goal mode present, from the weighted mean of that mode's particles (the
   particles of a mode share its plan: the guidance is the expensive part);
2. the posterior mixed and resampled by mode (``intent.mix_resample``): the Markov switch at the
   mode level, and every mode kept densely sampled however little the bearings favour it yet;
4. prediction: each mode's particles by their own motion: a goal mode's by
   the configured particle steering toward its goal (the most probable goal mode's with the full
   strategy, the others' with the free law and their plan's control), stationary ones stand, free
   ones coast with random acceleration, aimed ones head for their own destinations.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from onboard.core.tracking import intent as im
from onboard.core.tracking import filter as tracking
from onboard.core.dynamics import PLANAR
from onboard.core.guidance.predictor import Feedback, GuidanceWorkspace, Plan, PlanAsk, Solver, plan_guidance
from onboard.core.tracking.steering import AHEAD_STEPS, TargetTick

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
    probabilities: tuple[np.ndarray, ...]  # per target, (K + 3,) its modes' posterior probabilities
    reseeded: np.ndarray  # (M,) bool: re-seeded along the bearings this tick


def initial_beliefs(setup, rng: np.random.Generator) -> tuple[tracking.ParticleSet, ...]:
    """N(mu_0, Sigma_0) per target, each particle's mode drawn from the target's prior (a
    stationary one at rest)."""
    out = []
    for m, intent in zip(setup.initial_means, setup.intents):
        ps = tracking.initialise(m, setup.initial_cov, setup.n_particles, rng)
        out.append(with_modes(ps, intent, setup, rng))
    return tuple(out)


def with_modes(ps: tracking.ParticleSet, intent: im.Intent, setup, rng: np.random.Generator) -> tracking.ParticleSet:
    """``ps`` with a mode and a destination per particle (drawn from the prior where it has none:
    a belief the app rebuilt or re-seeded)."""
    if ps.modes is not None and len(ps.modes) == len(ps) and ps.aims is not None:
        return ps
    modes = im.draw(intent, len(ps), rng)
    particles = ps.particles.copy()
    particles[modes == im.STATIONARY, 3:] = 0.0
    aims = im.draw_aims(len(ps), setup.area_min, setup.area_max, rng)
    return tracking.ParticleSet(particles, ps.log_weights, ps.labels, modes, aims)


def _reseed_modes(rng: np.random.Generator) -> Callable[[int], np.ndarray]:
    return lambda k: np.array([im.STATIONARY, im.FREE, im.AIMED])[rng.integers(3, size=k)]


def _reseeded_velocities(ps: tracking.ParticleSet, n_old: int, setup_area, rng: np.random.Generator
                         ) -> tracking.ParticleSet:
    """The re-drawn particles (from index ``n_old``) at rest if stationary, else with a velocity
    N(0, RESEED_SPEED^2 I) and a new destination: the motion that lost the target is not theirs."""
    if len(ps) == n_old:
        return ps
    p, aims = ps.particles.copy(), ps.aims.copy()
    new = np.arange(n_old, len(ps))
    p[new, 3:] = 0.0
    moving = new[ps.modes[new] != im.STATIONARY]
    p[moving, 3:5] = im.RESEED_SPEED_MPS * rng.standard_normal((len(moving), 2))
    aims[new] = im.draw_aims(len(new), setup_area[0], setup_area[1], rng)
    return replace(ps, particles=p, aims=aims)


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
        prior = with_modes(beliefs[j], intent, setup, rng)
        n = len(prior)
        window = mem.unexplained
        if j_scans and sum(window) >= im.SURPRISE_COUNT:
            prior = tracking.recover(prior, j_scans[-1][0], j_scans[-1][1], reseed, setup.sensor.sigma_rad, rng,
                                     new_modes=_reseed_modes(rng))
            prior = _reseeded_velocities(prior, n, (setup.area_min, setup.area_max), rng)
            reseeded[j] = len(prior) > n
            window = () if reseeded[j] else window
        elif setup.recovery is not None and j_scans:
            rec = im.raised_recovery(setup.recovery, im.unpredicted_weight(prior), setup.intent)
            prior = tracking.recover(prior, j_scans[-1][0], j_scans[-1][1], rec, setup.sensor.sigma_rad, rng)
        upd = tracking.update(prior, j_scans, setup.sensor)
        degenerate[j] = upd.degenerate
        told = [e < im.EXPLAINED_MIN for e in upd.explained if np.isfinite(e) or e == np.inf]
        window = (window + tuple(told))[-im.SURPRISE_WINDOW:]
        post = tracking.trim(upd.particles, n)
        means[j], covs[j] = tracking.estimate(post)
        probs.append(im.probabilities(post.log_weights, post.modes, intent.n_goals))
        posts.append(mix(setup, intent, post, rng))
        out_mem.append(IntentMemory(mem.plans, mem.steering, window))
    return IntentUpdate(posts, means, covs, degenerate, tuple(out_mem), tuple(probs), reseeded)


def mix(setup, intent: im.Intent, post: tracking.ParticleSet, rng: np.random.Generator) -> tracking.ParticleSet:
    """The posterior mixed and resampled by mode (``intent.mix_resample``): a particle switching
    into AIMED takes a new destination and leaves its side label; each mode's copies regularised
    with the mode's own covariance when the set has degenerated (as ``tracking.resample_if_needed``)."""
    n = len(post)
    degenerate = tracking.effective_sample_size(post) < setup.resample_fraction * n
    mixed = im.mix_resample(post.log_weights, post.modes, intent, setup.intent.switch_prob, n, im.MIN_MODE_SHARE,
                            rng, setup.intent.goal_switch_share)
    particles = post.particles[mixed.source]
    aims = post.aims[mixed.source]
    s = setup.intent.start_speed_mps
    if s > 0.0:  # a standing target that moves off does so at some speed, not from the standing particles' zero
        off = mixed.switched & (post.modes[mixed.source] == im.STATIONARY) & (mixed.modes != im.STATIONARY)
        particles[off, 3:5] = s * rng.standard_normal((int(off.sum()), 2))
    # a particle switching into AIMED takes a new destination, and an aimed one changes its mind at
    # AIM_REDRAW a tick: a target that turns back is then covered by particles already heading there
    fresh = (mixed.modes == im.AIMED) & (mixed.switched | (rng.random(len(mixed.modes)) < im.AIM_REDRAW))
    aims[fresh] = im.draw_aims(int(fresh.sum()), setup.area_min, setup.area_max, rng)
    labels = None
    if post.labels is not None:
        labels = np.where(mixed.switched, -1, post.labels[mixed.source])
    h = setup.regularise_bandwidth
    if degenerate and h > 0.0:
        for m in np.unique(mixed.modes):
            sel = np.flatnonzero(mixed.modes == m)
            if len(sel) < 2:
                continue
            d = particles[sel][:, PLANAR] - particles[sel][:, PLANAR].mean(axis=0)
            C = d.T @ d / len(sel) + 1e-9 * np.eye(4)
            try:
                L = np.linalg.cholesky(C)
            except np.linalg.LinAlgError:
                continue
            particles[np.ix_(sel, PLANAR)] += h * rng.standard_normal((len(sel), 4)) @ L.T
    return tracking.ParticleSet(particles, mixed.log_weights, labels, mixed.modes, aims)


def _mode_moments(ps: tracking.ParticleSet, sel: np.ndarray):
    """(share of the weight, weighted mean (6,), covariance (6, 6), the sub-belief) of the particles ``sel``."""
    logw = ps.log_weights[sel]
    share = float(np.exp(tracking.logsumexp(logw)))
    sub = tracking.ParticleSet(ps.particles[sel], logw - tracking.logsumexp(logw), *tracking.carried(ps, sel))
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
            ask = PlanAsk(Feedback.CONSTRAINED if setup.plan_steering is not None else Feedback.NONE,
                          ahead=AHEAD_STEPS if sides else 0, nearby=tuple(m.plan.shifted() for m in steer_mem))
            plan = plan_guidance(setup.model, setup.guidance, setup.obstacles, mean, intent.goals[k],
                                 previous=mem.plans.get(k), ask=ask, solver=Solver(workspace, timer))
            found[k] = (plan, share, mean, cov, sub)
        per_target.append(found)
        if found:
            main.append(found[max(found, key=lambda k: found[k][1])][0])
        else:
            mean, _ = tracking.estimate(ps)
            main.append(motion_plan(setup, mean, dominant_motion(ps, intent)))
    return per_target, tuple(main)


def dominant_motion(ps: tracking.ParticleSet, intent: im.Intent) -> int:
    """STATIONARY, FREE or AIMED, whichever holds the most weight."""
    p = im.probabilities(ps.log_weights, ps.modes, intent.n_goals)
    return int(im.codes(intent.n_goals + int(np.argmax(p[intent.n_goals:])), intent.n_goals))


def motion_plan(setup, mean: np.ndarray, mode: int) -> Plan:
    """A Plan holding a stationary, free or aimed mode's path (no control, no guidance solved): what
    the planner and the app read of a target no goal mode describes."""
    T = setup.guidance.horizon
    K = len(setup.obstacles)
    status = {im.STATIONARY: "stationary", im.FREE: "free", im.AIMED: "aimed"}[mode]
    return Plan(status, float("nan"), 0.0, 0, np.zeros((T, 3)), im.motion_path(mean, mode, T, setup.model),
                np.full((T - 1, K), -1))


PLAN_MODES = 2  # the lookahead scores at most this many modes of a target ...
PLAN_MODE_P = 0.1  # ... each holding at least this probability (the most probable always)


def _mode_path(setup, ps: tracking.ParticleSet, intent: im.Intent, column: int, found, fallback: Plan,
               mean: np.ndarray) -> Plan:
    """The path a mode predicts: a goal mode's plan, or the standing / coasting path from its mean."""
    if column < intent.n_goals:
        return found[column][0] if column in found else fallback
    code = int(im.codes(column, intent.n_goals))
    sel = ps.modes == code
    return motion_plan(setup, _mode_moments(ps, sel)[1] if sel.any() else mean, code)


def planner_inputs(setup, beliefs: Sequence[tracking.ParticleSet], posts: Sequence[tracking.ParticleSet],
                   per_target, main: Sequence[Plan], means: np.ndarray, mixture: bool):
    """What the UAV planner scores: per target its most probable mode's path and its predicted
    belief (``mixture`` False); or (the lookahead) its likely modes (``PLAN_MODES``, ``PLAN_MODE_P``)
    each as a belief of its own, its particles of that mode and that mode's path, weighted by the
    mode's share of the target's probability, so routes are scored over what the target may do.
    Returns (beliefs, plans, weights or None)."""
    out_b, out_p, out_w = [], [], []
    for j, ps in enumerate(posts):
        intent = setup.intents[j]
        p = im.probabilities(ps.log_weights, ps.modes, intent.n_goals)
        order = np.argsort(-p, kind="stable")
        cols = [c for k, c in enumerate(order[:PLAN_MODES if mixture else 1]) if k == 0 or p[c] >= PLAN_MODE_P]
        b = beliefs[j]
        for c in cols:
            out_p.append(_mode_path(setup, ps, intent, int(c), per_target[j], main[j], means[j]))
            if mixture and len(cols) > 1:
                own = b.modes == im.codes(int(c), intent.n_goals)
                out_b.append(replace(b, log_weights=np.where(own, b.log_weights, -np.inf)))
            else:
                out_b.append(b)
            out_w.append(p[c] / p[cols].sum())
    return tuple(out_b), tuple(out_p), (np.array(out_w) if mixture else None)


def predict(setup, steering, posts: Sequence[tracking.ParticleSet], per_target, main: Sequence[Plan],
            memory: Sequence[IntentMemory], replanner: Callable, rng: np.random.Generator):
    """Step 4: each mode's particles by their own motion. Returns the
    predicted beliefs and each target's memory (its goal modes' plans and steering)."""
    beliefs, out_mem = [], []
    budgets = steering.budgets(main)
    for j, ps in enumerate(posts):
        intent = setup.intents[j]
        modes, aims = ps.modes, ps.aims  # switched and mixed already (``mix``)
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
        sel = modes == im.AIMED
        ground = im.Ground(setup.ground_obstacles, setup.area_min, setup.area_max)
        particles[sel] = im.predict_aimed(ps.particles[sel], aims[sel], setup.model, setup.free_steering.gain,
                                          setup.guidance.u_max_n, setup.intent, ground, rng)
        beliefs.append(tracking.ParticleSet(particles, ps.log_weights, labels if lead is not None else None, modes,
                                            aims))
        out_mem.append(IntentMemory(plans, steer_mem, memory[j].unexplained))
    return tuple(beliefs), tuple(out_mem)


def most_likely(setup, probabilities: Sequence[np.ndarray]) -> tuple[tuple[str, str | None, float], ...]:
    """Per target, what it most likely does: (``goal``, the goal's name, p) or (one of
    ``intent.MOTION_MODES``, None, p): what the operator is shown."""
    out = []
    for intent, p in zip(setup.intents, probabilities):
        c = int(np.argmax(p))
        if c < intent.n_goals:
            out.append(("goal", intent.names[c], float(p[c])))
        else:
            out.append((intent.label(c), None, float(p[c])))
    return tuple(out)


__all__ = ["IntentMemory", "IntentUpdate", "initial_beliefs", "update", "guidance", "predict", "planner_inputs",
           "most_likely", "with_modes"]
