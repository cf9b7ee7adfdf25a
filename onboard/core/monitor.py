"""One tick of the monitor: scans in; estimates, target plans and the next UAV position out.

Order within a tick t (the beliefs held between ticks are the predictions for the next scan):
  1. update each target's predicted belief bel(x_t) with the scans taken at time t;
  2. posterior mean and covariance; resample when the effective sample size is low;
  3. guidance (P1) from each posterior mean, warm-started by the previous plan;
  4. predict each belief to t+1 with the plan's first control u_(t|t) and noise Q;
  5. choose s_(t+1) around ``plan_from`` by pseudo-updating those predictions.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np

from onboard.core import tracking
from onboard.core.dynamics import PLANAR, MotionModel
from onboard.core.guidance import (FreeLaw, GuidanceParams, GuidanceWorkspace, LocalLaw, Plan, free_law,
                                   in_class, plan_guidance, winding)
from onboard.core.obstacles import Obstacles
from onboard.core.information import information_reduction_factor
from onboard.core.planning import (LOOKAHEAD_DEFAULT, CandidateGrid, LookaheadParams, PlanningResult, UavMotion,
                                   choose_lookahead, choose_next_position)
from onboard.core.steering import SideMode


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

    references: int = 2
    spread_sigma: float = 1.5
    steered_share: float = 0.7
    trust_sigma: float = 2.0
    max_qp_solves: int = 80  # per reference plan (capped by the guidance's budget, which the mean's has)
    # each particle carries the side of each obstacle its target takes, and each side present has
    # its own mean's plan and spread pairs (``_side_modes``); a side costing P1 d more (relative)
    # than its parent's gets a share 1 / (1 + exp(d / side_temperature)) of its particles at birth
    sides: bool = False
    side_temperature: float = 0.05

    @classmethod
    def from_config(cls, tr) -> "PlanSteering | None":
        if not tr.plan_steering:
            return None
        return cls(tr.plan_references, tr.plan_spread_sigma, tr.plan_steered_share, tr.plan_trust_sigma,
                   tr.plan_max_qp_solves, tr.plan_sides, tr.plan_side_temperature)


MAX_SIDE_MODES = 4  # per target
MIN_SIDE_SHARE = 0.01  # a side mode holding less of the posterior weight is dropped
SIDE_LEAD_STEPS = 3  # an obstacle first met this many steps ahead or later gets two sides


@dataclass(frozen=True, eq=False)
class MonitorSetup:
    """Everything static about a mission, built once from a scenario."""

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
    control_mix: float = 0.0  # fraction of particles predicted with a random control
    regularise_bandwidth: float = 0.0  # h of the regularised resampling (tracking.resample_if_needed)
    free_steering: FreeLaw | None = None  # particles whose own plan is the free optimum steer by it
    plan_steering: PlanSteering | None = None  # the others, while the plan is constrained, by reference plans
    planner: str = "greedy"  # greedy | lookahead
    lookahead_steps: int = 10
    motion: UavMotion = UavMotion()
    lookahead: LookaheadParams = LOOKAHEAD_DEFAULT

    @classmethod
    def from_scenario(cls, sc, **overrides) -> "MonitorSetup":
        obstacles = Obstacles.from_boxes(sc.obstacles)
        d = sc.dynamics
        model = MotionModel.create(d.dt_s, d.friction, d.mass_kg, d.process_noise_diag)
        fields = dict(
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
            objective=sc.planning.objective,
            planner=sc.planning.planner,
            lookahead_steps=sc.planning.lookahead_steps,
            motion=UavMotion.from_config(sc.planning),
            lookahead=LookaheadParams.from_config(sc.planning.lookahead),
        )
        fields.update(overrides)
        return cls(**fields)

    @property
    def n_targets(self) -> int:
        return len(self.goals)


@dataclass(frozen=True, eq=False)
class MonitorState:
    beliefs: tuple[tracking.ParticleSet, ...]  # predicted beliefs for the next scan time
    plans: tuple[Plan | None, ...]
    step: int = 0
    # per target, last tick's reference plans (plan_steering; empty while the plan was free): the
    # warm start of this tick's plan from the same offset
    references: tuple[tuple[Plan | None, ...], ...] = ()
    modes: tuple[tuple[SideMode, ...], ...] = ()  # per target, last tick's side modes (plan_sides)


@dataclass(frozen=True, eq=False)
class Scan:
    """Bearings (rad, per target channel) taken from one sensor position (ENU, m)."""

    sensor_position: np.ndarray
    bearings: tuple[np.ndarray, ...]


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


def _particle_controls(plan: Plan, particles: np.ndarray, goal: np.ndarray, setup: MonitorSetup,
                       rng: np.random.Generator, laws: Sequence[LocalLaw] = (),
                       metric: np.ndarray | None = None, sides: "SideLaws | None" = None) -> np.ndarray:
    """(n, 3) controls for the prediction: the plan's u_(t|t) for every particle (eq:prediction),
    except:

    * ``free_steering``: a particle from which P1's optimum has no active row (checked on its
      whole free path: input box, speed, obstacles; ``FreeLaw.is_optimal``) gets that optimum's
      control, which is exactly what the guidance commands a target there. A target in open
      ground steers back toward its goal from wherever it is; a target already past an obstacle
      no longer follows a plan that still rounds it.
    * ``plan_steering`` (``laws``: reference plans of a target whose plan is constrained,
      ``_reference_laws``): a share of the other particles, those within ``trust_sigma`` of a
      reference (``metric``: position Mahalanobis), steers by the affine law of the nearest one,
      clipped to the input box: a target pressed against a face or cruising at its speed limit
      is pulled back onto its plan as the true one is. With ``sides`` (plan_sides: the laws and
      metric of ``_side_modes``) a particle uses the nearest law of its own side mode, and outside
      the trust radius or the steered share that mode's plan's control, not the mean plan's.
    * a fraction ``control_mix`` of the particles not on the free law gets a control uniform in
      the input box (u_z = 0): the target may take another way around an obstacle.
    docs/TRACKING.md has the measurements."""
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
        rest = np.flatnonzero(~free)
        if sides is not None:  # a mode's first law is its own plan's
            first = np.searchsorted(sides.group, np.arange(sides.group.max() + 1))
            out[rest] = np.array([laws[i].u_ref for i in first])[sides.labels[rest]]
        rest = rest[rng.random(len(rest)) < setup.plan_steering.steered_share]
        x = particles[rest]
        m2 = _mahalanobis2(x, np.array([lw.x_ref[:2] for lw in laws]), metric)
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
    if setup.control_mix > 0.0:
        u_max = setup.guidance.u_max_n
        other = (rng.random(n) < setup.control_mix) & ~free
        out[other, :2] = rng.uniform(-u_max, u_max, (int(other.sum()), 2))
        out[other, 2] = 0.0
    return out


def _mahalanobis2(points: np.ndarray, centres: np.ndarray, metric: np.ndarray) -> np.ndarray:
    """(n, r) squared Mahalanobis distances of the positions of points (n, >=2) to centres (r, >=2)."""
    d = points[:, None, :2] - centres[None, :, :2]
    return np.einsum("nri,ij,nrj->nr", d, metric, d)


def _reference_params(setup: MonitorSetup) -> GuidanceParams:
    """The guidance settings of a reference plan: its own QP budget, capped by the mean's."""
    ps = setup.plan_steering
    return replace(setup.guidance, max_qp_solves=min(ps.max_qp_solves, setup.guidance.max_qp_solves))


def _reference_laws(setup: MonitorSetup, mean: np.ndarray, cov: np.ndarray, goal: np.ndarray, plan: Plan,
                    previous: Plan | None, previous_refs: Sequence[Plan | None], workspace: GuidanceWorkspace | None,
                    timer: Callable[[], float], sides: np.ndarray | None = None
                    ) -> tuple[list[LocalLaw], np.ndarray, tuple[Plan | None, ...]]:
    """The laws of the mean's plan and of plans from ``references`` points, pairs evenly spaced
    out to +-``spread_sigma`` standard deviations along the cloud's major position axis (velocity
    regressed on position, as the cloud correlates them), each planned as the mean is (warm-started
    by last tick's plan from the same offset, else the mean's, so each may round an obstacle on its
    own side; with ``sides``, never against them: ``guidance.in_class``); the position metric
    (inverse covariance) that picks a particle's nearest reference; and the reference plans (next
    tick's warm starts). A reference with no feasible plan is left out."""
    ps = setup.plan_steering
    C = cov[np.ix_(PLANAR, PLANAR)]
    Cpp = C[:2, :2] + 1e-6 * np.eye(2)
    metric = np.linalg.inv(Cpp)
    laws, refs = [plan.law], []
    params = _reference_params(setup)
    if ps.references >= 2:
        lam, vec = np.linalg.eigh(Cpp)
        axis = vec[:, -1] * np.sqrt(lam[-1])
        half = ps.spread_sigma * np.arange(1, ps.references // 2 + 1) / (ps.references // 2)
        for i, o in enumerate(np.concatenate([-half, half])):
            x = np.asarray(mean, float).copy()
            x[PLANAR] += C[:, :2] @ np.linalg.solve(Cpp, o * axis)
            own = previous_refs[i] if i < len(previous_refs) else None
            p = plan_guidance(setup.model, params, setup.obstacles, x, goal,
                              previous=own if own is not None else previous,
                              workspace=workspace, timer=timer, with_feedback=True, sides=sides)
            refs.append(p if p.feasible else None)
            if p.feasible and p.law is not None:
                laws.append(p.law)
    return laws, metric, tuple(refs)


@dataclass(frozen=True, eq=False)
class SideLaws:
    """What ``_side_modes`` gives the prediction: each particle's mode (``labels``, (n,)), the
    reference laws of every mode (``laws``; ``group``: the mode of each), and the metric."""

    labels: np.ndarray
    laws: list[LocalLaw]
    group: np.ndarray
    metric: np.ndarray


def _side_modes(setup: MonitorSetup, ps: tracking.ParticleSet, mean: np.ndarray, cov: np.ndarray,
                goal: np.ndarray, plan: Plan, previous: Sequence[SideMode], previous_plan: Plan | None,
                workspace: GuidanceWorkspace | None, timer: Callable[[], float], rng: np.random.Generator
                ) -> tuple[SideLaws, tuple[SideMode, ...]]:
    """Side modes of a target whose mean's plan is constrained (``PlanSteering.sides``).

    A true target keeps the side of an obstacle its plan took when the obstacle first bound it
    (its guidance is warm-started by its own last plan), and where both sides cost P1 about the
    same that choice is a knife edge no estimate resolves in advance. So each particle carries a
    side, kept through resampling, and each side present has its own reference plans:

    1. last tick's modes, each re-planned from the weighted mean of its particles, warm-started by
       its own plan and never rounding an obstacle the other way than its side; a mode with
       under ``MIN_SIDE_SHARE`` of the weight, or no feasible plan, is dropped (with none left
       the mean's plan is the one mode);
    2. a particle without a mode joins the nearest (Mahalanobis, position);
    3. a mode whose plan has an active row on an obstacle it has no side for yet, not within
       ``SIDE_LEAD_STEPS`` of now, takes its plan's side there and plans the best path round the
       other side from the same point; that side takes each of the mode's particles with
       probability 1 / (1 + exp(d / side_temperature)), d the relative extra cost of its plan (a
       coin toss at the knife edge), up to ``MAX_SIDE_MODES`` modes;
    4. each mode's reference plans, as ``_reference_laws`` spreads them over its own particles
       and held to its sides (a mode born this tick has its own plan only).
    """
    st = setup.plan_steering
    K = len(setup.obstacles)
    w, x_all = ps.weights, ps.particles
    metric = np.linalg.inv(cov[:2, :2] + 1e-6 * np.eye(2))
    params = _reference_params(setup)

    def planned(x, previous_plan, sides, strict=False):
        p = plan_guidance(setup.model, params, setup.obstacles, x, goal, previous=previous_plan,
                          workspace=workspace, timer=timer, with_feedback=True, sides=sides, strict_sides=strict)
        return p if p.feasible and p.law is not None else None

    def moments(sel):
        share = float(w[sel].sum())
        m = w[sel] @ x_all[sel] / share
        d = x_all[sel] - m
        return share, m, (d * w[sel, None]).T @ d / share

    labels = np.full(len(ps), -1) if ps.labels is None else np.asarray(ps.labels).copy()
    labels[labels >= len(previous)] = -1
    modes, stats, old = [], [], []  # old: the mode's last plan and references (warm starts)
    renumber = np.full(len(previous) + 1, -1)  # index -1 (no mode) stays -1
    for m, mode in enumerate(previous):
        sel = labels == m
        if not sel.any():
            continue
        share, centre, c = moments(sel)
        if share < MIN_SIDE_SHARE:
            continue
        if share > 1.0 - 1e-12 and in_class(plan.faces, mode.sides):
            p = plan  # the mean's plan is this mode's: no second solve
        else:
            p = planned(centre, mode.plan, mode.sides)
        if p is None:
            continue
        renumber[m] = len(modes)
        modes.append(SideMode(p, mode.sides))
        stats.append((centre, c))
        old.append((mode.plan, mode.references))
    labels = renumber[labels]
    if not modes:
        modes, stats = [SideMode(plan, np.zeros(K, dtype=int))], [(np.asarray(mean, float), cov)]
        old = [(previous_plan, ())]
    lost = np.flatnonzero(labels < 0)
    if len(lost):
        labels[lost] = np.argmin(_mahalanobis2(x_all[lost], np.array([c[:2] for c, _ in stats]), metric), axis=1)

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
            alt = planned(stats[m][0], None, other, strict=True)
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

    laws, group, out = [], [], []
    for m, mode in enumerate(modes):
        if m < n_old:
            centre, c = stats[m]
            mode_laws, _, refs = _reference_laws(setup, centre, c, goal, mode.plan, old[m][0], old[m][1],
                                                 workspace, timer, sides=mode.sides)
        else:
            mode_laws, refs = [mode.plan.law], ()
        laws += mode_laws
        group += [m] * len(mode_laws)
        out.append(SideMode(mode.plan, mode.sides, refs))
    return SideLaws(labels, laws, np.array(group), metric), tuple(out)


def initial_state(setup: MonitorSetup, rng: np.random.Generator) -> MonitorState:
    beliefs = tuple(tracking.initialise(m, setup.initial_cov, setup.n_particles, rng)
                    for m in setup.initial_means)
    return MonitorState(beliefs, (None,) * setup.n_targets, 0)


def tick(setup: MonitorSetup, state: MonitorState, scans: Sequence[Scan], rng: np.random.Generator,
         plan_from: np.ndarray | None = None, workspace: GuidanceWorkspace | None = None,
         timer: Callable[[], float] = time.perf_counter,
         uav_velocity: np.ndarray | None = None) -> tuple[MonitorState, TickResult]:
    """Run one tick. ``plan_from`` (ENU, m): where the candidate set is centred (where the UAV
    is or will be at the next tick); None skips the UAV planning (e.g. fixed sensors).
    ``uav_velocity`` (ENU, m/s, planar): the UAV's velocity there, for the vehicle motion."""
    t0 = timer()
    M = setup.n_targets
    posts, degenerate = [], np.zeros(M, dtype=bool)
    means, covs = np.zeros((M, 6)), np.zeros((M, 6, 6))
    for j in range(M):
        j_scans = [(np.asarray(s.sensor_position, float)[:2], s.bearings[j]) for s in scans]
        upd = tracking.update(state.beliefs[j], j_scans, setup.sensor)
        degenerate[j] = upd.degenerate
        means[j], covs[j] = tracking.estimate(upd.particles)
        posts.append(tracking.resample_if_needed(upd.particles, setup.resample_fraction, rng,
                                                     setup.regularise_bandwidth, covs[j]))
    t1 = timer()

    plans = tuple(
        plan_guidance(setup.model, setup.guidance, setup.obstacles, means[j], setup.goals[j],
                      previous=state.plans[j], workspace=workspace, timer=timer,
                      with_feedback=setup.plan_steering is not None)
        for j in range(M))
    t2 = timer()

    # the plan's one control for every particle (eq:prediction), except where a particle's own
    # plan is known in closed form, and (opt-in plan_steering) near a reference plan's
    # linearisation (_particle_controls; the reference plans count as tracking time). The mean
    # plan's law for every particle is worse: where constraints are active it is dead-beat, the
    # cloud collapses onto the mean's plan and is lost when the truth takes another active set
    # or side of an obstacle (docs/TRACKING.md).
    beliefs, references, modes = [], [], []
    for j in range(M):
        laws, metric, refs, sides, side_laws, post = (), None, (), (), None, posts[j]
        if setup.plan_steering is not None and plans[j].law is not None and not plans[j].unconstrained:
            if setup.plan_steering.sides:
                side_laws, sides = _side_modes(setup, post, means[j], covs[j], setup.goals[j], plans[j],
                                               state.modes[j] if state.modes else (), state.plans[j], workspace,
                                               timer, rng)
            else:
                laws, metric, refs = _reference_laws(setup, means[j], covs[j], setup.goals[j], plans[j],
                                                     state.plans[j], state.references[j] if state.references
                                                     else (), workspace, timer)
        references.append(refs)
        modes.append(sides)
        # a particle's side is dropped while the mean's plan is free
        post = replace(post, labels=None if side_laws is None else side_laws.labels)
        beliefs.append(tracking.predict(post, setup.model,
                                        _particle_controls(plans[j], post.particles, setup.goals[j],
                                                           setup, rng, laws, metric, side_laws), rng))
    beliefs = tuple(beliefs)
    t3 = timer()

    planning = None
    if plan_from is not None:
        particles = np.stack([b.particles for b in beliefs])
        log_w = np.stack([b.log_weights for b in beliefs])
        here = np.asarray(plan_from, float)
        vel = np.zeros(2) if uav_velocity is None else np.asarray(uav_velocity, float)[:2]
        if setup.planner == "lookahead":
            paths = np.stack([p.means[:setup.lookahead_steps] for p in plans])
            q = information_reduction_factor(setup.sensor.p_detect, setup.sensor.clutter_rate,
                                             setup.sensor.sigma_rad)
            planning = choose_lookahead(particles, log_w, paths, here, vel, setup.grid, setup.motion,
                                        setup.model, setup.sensor.sigma_rad, q, setup.area_min,
                                        setup.area_max, setup.uav_obstacles, setup.objective,
                                        params=setup.lookahead)
        else:
            planning = choose_next_position(particles, log_w, here, setup.grid, setup.sensor.sigma_rad,
                                            setup.area_min, setup.area_max, setup.uav_obstacles,
                                            setup.objective, setup.motion, vel, setup.model.dt_s)
    t4 = timer()
    timings = {"tracking": (t1 - t0) + (t3 - t2), "guidance": t2 - t1, "planning": t4 - t3, "tick": t4 - t0}
    return (MonitorState(beliefs, plans, state.step + 1, tuple(references), tuple(modes)),
            TickResult(means, covs, plans, planning, degenerate, timings))
