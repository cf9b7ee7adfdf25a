"""Particle steering: the control each particle of a target is predicted with (eq. (9a)).

One abstract class for the role (``ParticleSteering``), chosen once from the configuration
(``monitor.particle_steering``), three strategies (docs/TRACKING.md says why; the measurements are in docs/LOG.md):

- ``FreeSteering`` (the default): the plan's first control for every particle, except a particle
  whose own P1 optimum is the free one (``FreeLaw.is_optimal``), which gets that optimum's control;
  a share ``control_mix`` of the rest a random control.
- ``ReferenceSteering`` (``tracking.plan_steering``): while the mean's plan is constrained, a share
  of the particles steers by the affine law of the nearest of several reference plans.
- ``SideSteering`` (``plan_steering`` + ``plan_sides``): each particle carries the side of each
  obstacle its target takes, and each side present has its own plan and reference plans.

``particle_controls`` is the one place the controls are formed from the laws a strategy found.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from typing import Any, Callable, Sequence

import numpy as np

from onboard.core.dynamics import PLANAR
from onboard.core.guidance.predictor import LocalLaw, Plan, in_class, winding
from onboard.core.tracking.steering_setup import PlanSteering, SteeringSetup
from onboard.core.tracking.filter import ParticleSet


@dataclass(frozen=True, eq=False)
class SideMode:
    """One hypothesis of the side on which a target rounds its obstacles (``PlanSteering.sides``):
    the plan from the weighted mean of the particles labelled with it, held to ``sides`` (K,)
    (``guidance.in_class``: +1 counterclockwise, -1 clockwise, 0 not yet chosen)."""

    plan: Plan
    sides: np.ndarray
    references: tuple[Plan | None, ...] = ()  # its spread reference plans (next tick's warm starts)


MAX_SIDE_MODES = 4  # per target
MIN_SIDE_SHARE = 0.01  # a side mode holding less of the posterior weight is dropped
SIDE_LEAD_STEPS = 3  # an obstacle first met this many steps ahead or later gets two sides
# the side-aware steering's QP solves per target and tick (``Budget``) and what one plan may take of
# them: a side mode's re-plan (a search from scratch when its warm starts fail), a side's birth, a
# reference plan (warm starts only); a plan's law counts as LAW_COST solves
TICK_QP_BUDGET = 40  # per target, when side_modes is given no budget
STEER_QPS = 40  # per tick, less what the mean plans searched this tick (SideSteering.budgets) ...
STEER_MIN_QPS = 12  # ... but at least this many
MODE_QPS = 8
BIRTH_QPS = 12
REFERENCE_QPS = 3
# a law (a KKT solve on the active rows and the next controls' gains) costs more than one
# assignment's QP; counted as 2 the tick stays in budget at the same accuracy (docs/LOG.md)
LAW_COST = 2
AHEAD_STEPS = 2  # a side-aware plan keeps the laws of this many next controls (Plan.ahead): it can be shifted

# P1 from a state, warm-started by a plan, with its law (Feedback.ALWAYS), held to sides (strict:
# rounding each obstacle of a side that way): the guidance as the strategies call it
Replan = Callable[..., Plan]


@dataclass(frozen=True, eq=False)
class TargetTick:
    """One target at tick t, as its prediction sees it."""

    post: ParticleSet  # the posterior, resampled
    mean: np.ndarray  # (6,) posterior mean
    cov: np.ndarray  # (6, 6)
    goal: np.ndarray  # (3,)
    plan: Plan  # P1 from the mean, this tick
    previous_plan: Plan | None  # last tick's
    replan: Replan  # ``replan(x, previous, sides=None, strict=False)``: P1 from x, with its law
    budget: int | None = None  # QP solves its steering may spend this tick (``ParticleSteering.budgets``)


@dataclass(frozen=True, eq=False)
class Steered:
    controls: np.ndarray  # (n, 3) N, one per particle
    labels: np.ndarray | None  # (n,) each particle's side mode (SideSteering), else None
    memory: Any  # what the strategy keeps for this target until the next tick


class ParticleSteering(ABC):
    """How a target's particles are moved in the prediction; ``memory`` is what the strategy
    kept for this target at the last tick (() at the start)."""

    def __init__(self, setup: SteeringSetup):
        self.setup = setup

    @abstractmethod
    def steer(self, target: TargetTick, memory: Any, rng: np.random.Generator) -> Steered:
        ...

    def budgets(self, plans: Sequence[Plan]) -> list[int | None]:
        """Per target, the QP solves its steering may spend this tick (None: no limit), given the
        mean's plans of the tick (made before the steering)."""
        return [None] * len(plans)

    def free(self, target: TargetTick, rng: np.random.Generator) -> Steered:
        """The free law and the plan's control, nothing kept."""
        return Steered(particle_controls(target.plan, target.post.particles, target.goal, self.setup, rng), None, ())

    @staticmethod
    def constrained(plan: Plan) -> bool:
        """The plan has a law and an active row: the free law does not describe it."""
        return plan.law is not None and not plan.unconstrained


class FreeSteering(ParticleSteering):
    """The default: the free law where it is exact, the plan's control (or the mixture's) elsewhere."""

    def steer(self, target: TargetTick, memory: Any, rng: np.random.Generator) -> Steered:
        return self.free(target, rng)


class ReferenceSteering(ParticleSteering):
    """``tracking.plan_steering``: while the mean's plan is constrained, the laws of the mean's
    plan and of ``references`` spread plans (``reference_laws``); kept: the spread plans, next
    tick's warm starts."""

    def steer(self, target: TargetTick, memory: Any, rng: np.random.Generator) -> Steered:
        if not self.constrained(target.plan):
            return self.free(target, rng)
        laws, metric, refs = reference_laws(self.setup.plan_steering, target, memory)
        u = particle_controls(target.plan, target.post.particles, target.goal, self.setup, rng, laws, metric)
        return Steered(u, None, refs)


class SideSteering(ParticleSteering):
    """``tracking.plan_sides``: side modes (``side_modes``); kept: the modes. Its plans are made
    within a budget of QP solves per tick (a count, never wall time: the same inputs give the same
    plans on any machine): ``STEER_QPS`` less what the mean's plans spent beyond a warm start, at
    least ``STEER_MIN_QPS``, shared by the targets whose plan is constrained."""

    def budgets(self, plans: Sequence[Plan]) -> list[int | None]:
        searched = sum(max(0, p.qp_solves - 1) for p in plans)  # the mean plans' searches this tick
        total = max(STEER_MIN_QPS, STEER_QPS - searched)
        steered = [self.constrained(p) for p in plans]
        share = total // max(1, sum(steered))
        return [share if c else None for c in steered]

    def steer(self, target: TargetTick, memory: Any, rng: np.random.Generator) -> Steered:
        if not self.constrained(target.plan):
            return self.free(target, rng)  # a particle's side is dropped while the mean's plan is free
        side_laws, modes = side_modes(self.setup, target, memory, rng)
        u = particle_controls(target.plan, target.post.particles, target.goal, self.setup, rng, sides=side_laws)
        return Steered(u, side_laws.labels, modes)


# --------------------------------------------------------------------------- the controls


def particle_controls(plan: Plan, particles: np.ndarray, goal: np.ndarray, setup: SteeringSetup,
                      rng: np.random.Generator, laws: Sequence[LocalLaw] = (),
                      metric: np.ndarray | None = None, sides: SideLaws | None = None) -> np.ndarray:
    """(n, 3) controls for the prediction: the plan's u_(t|t) for every particle (eq. (9a)),
    except:

    * ``free_steering``: a particle from which P1's optimum has no active row (checked on its
      whole free path: input box, speed, obstacles; ``FreeLaw.is_optimal``) gets that optimum's
      control, which is exactly what the guidance commands a target there. A target in open
      ground steers back toward its goal from wherever it is; a target already past an obstacle
      no longer follows a plan that still rounds it.
    * ``plan_steering`` (``laws``: reference plans of a target whose plan is constrained,
      ``reference_laws``): a share of the other particles, those within ``trust_sigma`` of a
      reference (``metric``: position Mahalanobis), steers by the affine law of the nearest one,
      clipped to the input box: a target pressed against a face or cruising at its speed limit
      is pulled back onto its plan as the true one is. With ``sides`` (plan_sides: the laws and
      metric of ``side_modes``) a particle uses the nearest law of its own side mode, and outside
      the trust radius or the steered share that mode's plan's control, not the mean plan's.
    * a fraction ``control_mix`` of the particles not on the free law gets a control uniform in
      the input box (u_z = 0): the target may take another way around an obstacle.
    docs/TRACKING.md says why; the measurements are in docs/LOG.md."""
    n = len(particles)
    out = np.broadcast_to(np.asarray(plan.next_control, float), (n, 3)).copy()
    free = np.zeros(n, dtype=bool)
    if setup.free_steering is not None:
        u_free = setup.free_steering.controls(particles, goal)
        free = setup.free_steering.is_optimal(particles, goal, setup.obstacles, u_free)
        out[free] = u_free[free]
    if sides is not None:
        laws, metric = sides.laws, sides.metric
    if laws and setup.plan_steering is not None:
        _steer_by_laws(out, free, particles, setup, rng, laws, metric, sides)
    if setup.control_mix > 0.0:
        u_max = setup.guidance.u_max_n
        other = (rng.random(n) < setup.control_mix) & ~free
        out[other, :2] = rng.uniform(-u_max, u_max, (int(other.sum()), 2))
        out[other, 2] = 0.0
    return out


def _steer_by_laws(out: np.ndarray, free: np.ndarray, particles: np.ndarray, setup: SteeringSetup,
                   rng: np.random.Generator, laws: Sequence[LocalLaw], metric: np.ndarray,
                   sides: SideLaws | None) -> None:
    """``particle_controls``' reference steering, in place on ``out``."""
    rest = np.flatnonzero(~free)
    if sides is not None:  # a mode's first law is its own plan's
        first = np.searchsorted(sides.group, np.arange(sides.group.max() + 1))
        out[rest] = np.array([laws[i].u_ref for i in first])[sides.labels[rest]]
    rest = rest[rng.random(len(rest)) < setup.plan_steering.steered_share]
    x = particles[rest]
    m2 = mahalanobis2(x, np.array([lw.x_ref[:2] for lw in laws]), metric)
    if sides is not None:
        m2 = np.where(sides.group[None, :] == sides.labels[rest][:, None], m2, np.inf)
    which = np.argmin(m2, axis=1)
    # a linearisation holds near its reference only: a particle far from every reference
    # (the target may round the obstacle on another side) is not pulled onto their plans
    near = m2[np.arange(len(x)), which] <= setup.plan_steering.trust_sigma ** 2
    rest, x, which = rest[near], x[near], which[near]
    for r, lw in enumerate(laws):
        sel = which == r
        u = lw.controls(x[sel])
        u[:, :2] = np.clip(u[:, :2], -setup.guidance.u_max_n, setup.guidance.u_max_n)
        u[:, 2] = 0.0
        out[rest[sel]] = u


def mahalanobis2(points: np.ndarray, centres: np.ndarray, metric: np.ndarray) -> np.ndarray:
    """(n, r) squared Mahalanobis distances of the positions of points (n, >=2) to centres (r, >=2)."""
    d = points[:, None, :2] - centres[None, :, :2]
    return np.einsum("nri,ij,nrj->nr", d, metric, d)


# --------------------------------------------------------------------------- reference plans


def reference_laws(ps: PlanSteering, target: TargetTick, previous_refs: Sequence[Plan | None],
                   sides: np.ndarray | None = None, budget: Budget | None = None
                   ) -> tuple[list[LocalLaw], np.ndarray, tuple[Plan | None, ...]]:
    """The laws of the mean's plan (``target``'s; its particles are not read) and of plans from
    ``references`` points, pairs evenly spaced out to +-``spread_sigma`` standard deviations
    along the cloud's major position axis (velocity regressed on position, as the cloud
    correlates them), each planned as the mean is (warm-started by last tick's plan from the same
    offset, else the mean's, so each may round an obstacle on its own side; with ``sides``, never
    against them: ``guidance.in_class``); the position metric (inverse covariance) that picks a
    particle's nearest reference; and the reference plans (next tick's warm starts). A reference with no feasible plan is left out. With a ``budget`` (the
    side modes'): each reference is warm-started by its own last plan, else by ``plan`` as it is,
    with at most ``REFERENCE_QPS`` of the budget and no search from scratch."""
    mean, plan, previous, replan = target.mean, target.plan, target.previous_plan, target.replan
    C = target.cov[np.ix_(PLANAR, PLANAR)]
    Cpp = C[:2, :2] + 1e-6 * np.eye(2)
    metric = np.linalg.inv(Cpp)
    laws, refs = [plan.law], []
    if ps.references >= 2:
        lam, vec = np.linalg.eigh(Cpp)
        axis = vec[:, -1] * np.sqrt(lam[-1])
        half = ps.spread_sigma * np.arange(1, ps.references // 2 + 1) / (ps.references // 2)
        for i, o in enumerate(np.concatenate([-half, half])):
            x = np.asarray(mean, float).copy()
            x[PLANAR] += C[:, :2] @ np.linalg.solve(Cpp, o * axis)
            own = previous_refs[i] if i < len(previous_refs) else None
            if budget is None:
                p = replan(x, own if own is not None else previous, sides)
            else:
                p = _budgeted_reference(x, own, previous, plan, sides, replan, budget, first=i >= len(previous_refs))
            refs.append(p if p is not None and p.feasible else None)
            if p is not None and p.feasible and p.law is not None:
                laws.append(p.law)
    return laws, metric, tuple(refs)


def _budgeted_reference(x: np.ndarray, own: Plan | None, previous: Plan | None, plan: Plan, sides: np.ndarray | None,
                        replan: Replan, budget: Budget, first: bool) -> Plan | None:
    """A reference plan within the side modes' budget: its own last plan shifted by a tick
    (``Plan.shifted``) while that has a next law, so each is made afresh every ``AHEAD_STEPS`` + 1
    ticks; else P1 from x warm-started by its own last plan (else the mode's last), then by the
    mode's plan of this tick, no search from scratch (``first``: the reference's first plan, with
    ``MODE_QPS``, else ``REFERENCE_QPS``); where the budget does not reach or that fails, shifted
    while it can be."""
    if own is not None and own.ahead:
        return own.shifted()
    p = None
    most = REFERENCE_QPS if own is not None else MODE_QPS  # a reference's first plan: its faces re-picked more
    if budget.cap(most) > 0:
        p = replan(x, own if own is not None else previous, sides, nearby=plan, explore=False, budget=budget.cap(most))
        budget.spend(p)
    if (p is None or not p.feasible or p.law is None) and own is not None and own.ahead:
        p = own.shifted()
    return p


# --------------------------------------------------------------------------- side modes


@dataclass(frozen=True, eq=False)
class SideLaws:
    """What ``side_modes`` gives the prediction: each particle's mode (``labels``, (n,)), the
    reference laws of every mode (``laws``; ``group``: the mode of each), and the metric."""

    labels: np.ndarray
    laws: list[LocalLaw]
    group: np.ndarray
    metric: np.ndarray


class Budget:
    """The QP solves one target's side-aware steering may spend in a tick: a count, never wall
    time, so the same inputs give the same plans on any machine. A plan's law (its sensitivity
    solve) costs ``LAW_COST``. Spent in order of priority: the heaviest side modes first."""

    def __init__(self, total: int):
        self.left = total

    def cap(self, most: int) -> int:
        """What the next plan may spend: at most ``most``, within what is left."""
        return max(0, min(most, self.left - LAW_COST))

    def spend(self, plan: Plan | None) -> None:
        if plan is not None:
            self.left -= plan.qp_solves + (LAW_COST if plan.law is not None else 0)


def side_modes(setup: SteeringSetup, target: TargetTick, previous: Sequence[SideMode],
               rng: np.random.Generator) -> tuple[SideLaws, tuple[SideMode, ...]]:
    """Side modes of a target whose mean's plan is constrained (``PlanSteering.sides``); ``previous``:
    its modes of the last tick.

    A true target keeps the side of an obstacle its plan took when the obstacle first bound it
    (its guidance is warm-started by its own last plan), and where both sides cost P1 about the
    same that choice is a knife edge no estimate resolves in advance. So each particle carries a
    side, kept through resampling, and each side present has its own reference plans:

    1. last tick's modes, each re-planned from the weighted mean of its particles, warm-started by
       its own plan (then by the mean's plan of this tick, when on its sides) and never rounding
       an obstacle the other way than its side; a mode with under ``MIN_SIDE_SHARE`` of the
       weight, or no feasible plan, is dropped (with none left the mean's plan is the one mode); a
       particle without a mode joins the nearest (Mahalanobis, position) (``_carry_modes``);
    2. a mode whose plan has an active row on an obstacle it has no side for yet, not within
       ``SIDE_LEAD_STEPS`` of now, takes its plan's side there and plans the best path round the
       other side from the same point; that side takes each of the mode's particles with
       probability 1 / (1 + exp(d / side_temperature)), d the relative extra cost of its plan (a
       coin toss at the knife edge), up to ``MAX_SIDE_MODES`` modes (``_birth_sides``);
    3. each mode's reference plans, as ``reference_laws`` spreads them over its own particles,
       held to its sides and warm-started by their own plans of the last tick, then by the mode's
       plan of this tick, never searched from scratch (a mode born this tick has its own plan only).

    All of it within ``target.budget`` QP solves (None: ``TICK_QP_BUDGET``), spent on the modes holding the
    most weight first: the modes' re-plans (a mode whose plan cannot be shifted again is re-planned
    past the budget: a mode is never lost for want of QPs), then the births, then the references.
    A mode or reference the budget does not reach (or whose warm starts fail) keeps its plan of the
    last tick shifted by a tick (``Plan.shifted``: its law the next control's) for up to
    ``AHEAD_STEPS`` ticks.
    """
    metric = np.linalg.inv(target.cov[:2, :2] + 1e-6 * np.eye(2))
    budget = Budget(TICK_QP_BUDGET if target.budget is None else target.budget)
    planned = _planner_within(budget, target.replan)
    labels, modes, stats, old = _carry_modes(target, previous, planned, metric, len(setup.obstacles))
    n_old = len(modes)
    _birth_sides(setup.plan_steering, labels, modes, stats, planned, rng)
    weight = np.bincount(labels, weights=target.post.weights, minlength=len(modes))
    refs_of: dict[int, tuple] = {}
    for m in sorted(range(n_old), key=lambda m: -weight[m]):  # the heaviest modes' references first
        centre, c = stats[m]  # the mode's particles, planned as a target of their own
        mode_target = replace(target, mean=centre, cov=c, plan=modes[m].plan, previous_plan=old[m][0])
        refs_of[m] = reference_laws(setup.plan_steering, mode_target, old[m][1], sides=modes[m].sides, budget=budget)
    laws, group, out = [], [], []
    for m, mode in enumerate(modes):
        mode_laws, _, refs = refs_of[m] if m < n_old else ([mode.plan.law], None, ())
        laws += mode_laws
        group += [m] * len(mode_laws)
        out.append(SideMode(mode.plan, mode.sides, refs))
    return SideLaws(labels, laws, np.array(group), metric), tuple(out)


def _planner_within(budget: Budget, replan: Replan) -> Callable:
    """``replan`` within ``budget``: a plan of at most ``most`` QP solves (with ``force``, past the
    budget when it is spent), None when not planned or without a feasible plan and law."""

    def planned(x, previous_plan, sides, strict=False, nearby=None, most=MODE_QPS, force=False):
        cap = budget.cap(most)
        if cap <= 0:
            if not force:
                return None
            cap = most  # past the budget: a mode that would otherwise be lost
        p = replan(x, previous_plan, sides, strict, nearby=nearby, budget=cap)
        budget.spend(p)
        return p if p.feasible and p.law is not None else None
    return planned


def _carry_modes(target: TargetTick, previous: Sequence[SideMode], planned: Callable, metric: np.ndarray, K: int):
    """``side_modes``' step 1: the labels (n,), the modes kept (re-planned, the heaviest first),
    each one's particles' (weighted mean, covariance), and its last plan and references (the
    warm starts)."""
    ps, mean, cov, plan = target.post, target.mean, target.cov, target.plan
    w, x_all = ps.weights, ps.particles

    def moments(sel):
        share = float(w[sel].sum())
        m = w[sel] @ x_all[sel] / share
        d = x_all[sel] - m
        return share, m, (d * w[sel, None]).T @ d / share

    labels = np.full(len(ps), -1) if ps.labels is None else np.asarray(ps.labels).copy()
    labels[labels >= len(previous)] = -1
    kept = {}  # previous index -> (share, centre, covariance)
    for m in range(len(previous)):
        sel = labels == m
        if sel.any():
            share, centre, c = moments(sel)
            if share >= MIN_SIDE_SHARE:
                kept[m] = (share, centre, c)
    planned_for = {}
    for m in sorted(kept, key=lambda m: -kept[m][0]):  # the heaviest first: the budget runs out on the lightest
        share, centre, _ = kept[m]
        mode = previous[m]
        on_side = in_class(plan.faces, mode.sides)
        if share > 1.0 - 1e-12 and on_side:
            planned_for[m] = plan  # the mean's plan is this mode's: no second solve
        else:
            # a mode whose plan cannot be shifted again is re-planned whatever the budget: a side
            # mode is a hypothesis the bearings may still be weighing, never dropped for want of QPs
            planned_for[m] = planned(centre, mode.plan, mode.sides, nearby=plan if on_side else None,
                                     force=not mode.plan.ahead)
            if planned_for[m] is None and mode.plan.ahead:
                planned_for[m] = mode.plan.shifted()  # not re-planned this tick: its last plan, a tick on
    modes, stats, old = [], [], []  # old: the mode's last plan and references (warm starts)
    renumber = np.full(len(previous) + 1, -1)  # index -1 (no mode) stays -1
    for m, mode in enumerate(previous):
        p = planned_for.get(m)
        if p is None:
            continue
        renumber[m] = len(modes)
        modes.append(SideMode(p, mode.sides))
        stats.append(kept[m][1:])
        old.append((mode.plan, mode.references))
    labels = renumber[labels]
    if not modes:
        modes, stats = [SideMode(plan, np.zeros(K, dtype=int))], [(np.asarray(mean, float), cov)]
        old = [(target.previous_plan, ())]
    lost = np.flatnonzero(labels < 0)
    if len(lost):
        labels[lost] = np.argmin(mahalanobis2(x_all[lost], np.array([c[:2] for c, _ in stats]), metric), axis=1)
    return labels, modes, stats, old


def _birth_sides(st: PlanSteering, labels: np.ndarray, modes: list[SideMode], stats: list, planned: Callable,
                 rng: np.random.Generator) -> None:
    """``side_modes``' step 2, in place on ``labels``, ``modes`` and ``stats``."""
    n_old = len(modes)
    for m in range(n_old):
        mode = modes[m]
        p = mode.plan
        if p.active is None:
            continue
        wind = winding(p.faces)
        rows = p.active.obstacles.any(axis=2)  # (K, T-1)
        # a side is chosen ahead of the obstacle: a plan already against it has made its choice
        ahead = rows.any(axis=1) & ~rows[:, :SIDE_LEAD_STEPS].any(axis=1)
        for k in np.flatnonzero(ahead & (wind != 0) & (mode.sides == 0)):
            held = mode.sides.copy()
            held[k] = np.sign(wind[k])
            modes[m] = mode = SideMode(p, held, mode.references)
            if len(modes) >= MAX_SIDE_MODES:
                continue
            other = held.copy()
            other[k] = -held[k]
            alt = planned(stats[m][0], None, other, strict=True, most=BIRTH_QPS)
            if alt is None:
                continue
            d = (alt.cost - p.cost) / max(abs(p.cost), 1e-9)
            share = 1.0 / (1.0 + np.exp(min(d / st.side_temperature, 700.0)))
            members = np.flatnonzero(labels == m)
            move = members[rng.random(len(members)) < share]
            if share < MIN_SIDE_SHARE or not len(move):
                continue
            labels[move] = len(modes)
            modes.append(SideMode(alt, other))
            stats.append(stats[m])
