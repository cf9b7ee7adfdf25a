"""Next UAV position: candidate set S_(t+1) (eq. (3) of the paper), pseudo-posteriors from ideal
bearings (eq. (11)) and the argmin of summed traces (eq. (12)); beyond the paper, the UAV's motion
between ticks and the non-myopic route planner (its route geometry: onboard/core/planning/routes.py).

What a planner is asked travels as frozen requests: ``UavState`` (where the UAV plans from),
``Moves`` (how and where it may move) and, for the lookahead, ``RouteScoring``; the pieces the
route geometry shares (the grid, ``UavState``, ``UavMotion``, ``LookaheadParams``) are in
onboard/core/planning/inputs.py.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.core.bearings import bearing, wrap
from onboard.core.dynamics import MotionModel
from onboard.core.planning.information import PLANAR, bearing_update_components, predict_planar_components
from onboard.core.obstacles import Obstacles, polygons_crossed
from onboard.core.planning.inputs import JUMP, CandidateGrid, LookaheadParams, UavMotion, UavState
from onboard.core.planning.routes import (blocking_2d, fly_routes, inside_2d, route_polylines, route_waypoints,
                                          sample_routes)
from onboard.core.tracking.filter import logsumexp

OBJECTIVES = ("trace", "position_trace")


def candidate_positions(center: np.ndarray, grid: CandidateGrid) -> np.ndarray:
    """S_(t+1) around center: "stay" first, then lambda = 1..N_r x kappa = 1..N_theta; (C, 3).

    Headings follow the paper: x += lambda Dr cos(kappa Dtheta), y += lambda Dr sin(kappa Dtheta).
    """
    lam = np.repeat(np.arange(1, grid.n_radial + 1), grid.n_heading)
    kap = np.tile(np.arange(1, grid.n_heading + 1), grid.n_radial)
    ang = kap * 2.0 * np.pi / grid.n_heading
    xy = np.stack([lam * grid.step_m * np.cos(ang), lam * grid.step_m * np.sin(ang)], axis=1)
    xy = np.vstack([[0.0, 0.0], xy]) + np.asarray(center, float)[:2]
    return np.column_stack([xy, np.full(len(xy), grid.altitude_m)])


def admissible(candidates: np.ndarray, start: np.ndarray, area_min, area_max,
               uav_obstacles: Obstacles) -> np.ndarray:
    """(C,) bool: inside the area and the straight path start -> candidate clears every obstacle
    (already inflated by the UAV's margin)."""
    c = np.asarray(candidates, float)
    inside = np.all((c >= np.asarray(area_min)) & (c <= np.asarray(area_max)), axis=1)
    if len(uav_obstacles):
        starts = np.broadcast_to(np.asarray(start, float), c.shape)
        blocked = uav_obstacles.segments_cross(starts, c).any(axis=1) | uav_obstacles.contains(c).any(axis=1)
        inside &= ~blocked
    return inside


def pseudo_posterior_traces(particles: np.ndarray, log_weights: np.ndarray, candidates: np.ndarray,
                            sigma_rad: float, objective: str = "trace") -> np.ndarray:
    """tr(Sigma~_j(s)) for every candidate s and target j: (C, M).

    particles (M, N, 6) and log_weights (M, N) are the predicted beliefs bel(x_(t+1)); the ideal
    bearing z = l(mu_pos, s) is taken to each target's predicted mean and the particles are
    re-weighted with N(z; l(x, s), sigma^2), without clutter (the paper's pseudo-update).
    Only the diagonal of each covariance is needed: tr = sum_d E[x_d^2] - E[x_d]^2.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    dims = slice(0, 6) if objective == "trace" else slice(0, 2)
    w = np.exp(log_weights - logsumexp(log_weights, axis=1, keepdims=True))  # (M, N)
    mu = np.einsum("mn,mnd->md", w, particles[:, :, :2])  # predicted mean positions (M, 2)
    s = np.asarray(candidates, float)[:, None, None, :2]  # (C, 1, 1, 2)
    z = bearing(mu[None, :, :], s[:, :, 0, :])  # (C, M) ideal bearings
    pred = bearing(particles[None, :, :, :2], s)  # (C, M, N)
    log_post = -0.5 * (wrap(z[:, :, None] - pred) / sigma_rad) ** 2 + log_weights[None]
    log_post -= log_post.max(axis=2, keepdims=True)
    wp = np.exp(log_post)
    wp /= wp.sum(axis=2, keepdims=True)  # (C, M, N); the max term is 1, so the sum is >= 1
    x = particles[:, :, dims]  # (M, N, D)
    wm = wp.transpose(1, 0, 2)  # (M, C, N): one matrix product per target
    m1 = np.matmul(wm, x)
    m2 = np.matmul(wm, x * x)
    return np.sum(m2 - m1 * m1, axis=2).T


@dataclass(frozen=True, eq=False)
class PlanningResult:
    candidates: np.ndarray  # (C, 3) next positions
    admissible: np.ndarray  # (C,) bool
    traces: np.ndarray  # (C, M): tr(Sigma~_j) per candidate and target (lookahead: summed over steps)
    scores: np.ndarray  # (C,): sum over targets; inf where not admissible
    index: int | None  # chosen candidate, None when no candidate is admissible
    paths: np.ndarray | None = None  # (C, H, 3) lookahead: each candidate's scored path
    velocities: np.ndarray | None = None  # (C, 2) vehicle motion: velocity at the next position

    @property
    def position(self) -> np.ndarray | None:
        return None if self.index is None else self.candidates[self.index]


@dataclass(frozen=True, eq=False)
class Area:
    """Where the UAV may go: the surveillance area's box and the obstacles (already inflated by
    the UAV's clearance margin)."""

    minimum: np.ndarray
    maximum: np.ndarray
    obstacles: Obstacles

    def admissible(self, candidates: np.ndarray, start: np.ndarray) -> np.ndarray:
        return admissible(candidates, start, self.minimum, self.maximum, self.obstacles)


def choose_next_position(particles: np.ndarray, log_weights: np.ndarray, uav: UavState, moves: Moves,
                         sigma_rad: float, objective: str = "trace", dt: float = 1.0) -> PlanningResult:
    """Eq. (12) over the admissible next positions around ``uav.position``: the paper's S_(t+1)
    with the jump motion (``Moves``' default), or those a vehicle reaches in one tick of ``dt``
    seconds (from ``uav.velocity`` and, continuous acceleration, ``uav.acceleration``)."""
    center, grid = uav.position, moves.grid
    velocity = np.zeros(2) if uav.velocity is None else uav.velocity
    paths, vel = motion_sequences(center, velocity, grid, moves.motion, 1, dt, uav.acceleration)
    cand = paths[:, 0]
    start = np.array([center[0], center[1], grid.altitude_m])
    ok = moves.area.admissible(cand, start)
    traces = pseudo_posterior_traces(particles, log_weights, cand, sigma_rad, objective)
    scores = np.where(ok, traces.sum(axis=1), np.inf)
    index = int(np.argmin(scores)) if ok.any() else None
    return PlanningResult(cand, ok, traces, scores, index, None, vel[:, 0])


# --------------------------------------------------------------------------- beyond the paper


@dataclass(frozen=True, eq=False)
class Moves:
    """How and where the UAV may move between ticks: the candidate grid (S_(t+1), and the
    vehicle's accelerations), the area and the motion (default the paper's jump)."""

    grid: CandidateGrid
    area: Area
    motion: UavMotion = JUMP


def motion_sequences(position: np.ndarray, velocity: np.ndarray, grid: CandidateGrid, motion: UavMotion,
                     steps: int, dt: float, acceleration: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Candidate UAV paths over ``steps`` ticks: (C, steps, 3) positions and (C, steps, 2) velocities.

    Each candidate repeats one action: jump, the same grid displacement every tick (so the first
    step is the paper's S_(t+1)), plus each displacement once and then staying; vehicle, one
    constant acceleration, the speed saturating at the limit, plus braking to a stop (with a
    continuous acceleration, ``motion.jerk_max_mps3`` > 0, ramped to from ``acceleration``, the
    plan's at the start, ENU m/s^2, default 0).
    """
    p0 = np.asarray(position, float)[:2]
    v0 = np.asarray(velocity, float)[:2]
    k = np.arange(1, steps + 1)[None, :, None]
    if motion.kind == "jump":
        step = candidate_positions(np.zeros(2), grid)[:, :2]  # stay first
        moving = step[1:]
        once = moving if steps > 1 else moving[:0]  # with one step "once" is "keep going"
        paths = np.concatenate([p0 + k * step[:, None, :],
                                np.broadcast_to(p0 + once[:, None, :], (len(once), steps, 2))])
        vel = np.concatenate([np.broadcast_to(step[:, None, :] / dt, (len(step), steps, 2)),
                              np.zeros((len(once), steps, 2))])
    else:
        mags = motion.accel_max_mps2 * np.arange(1, grid.n_radial + 1) / max(grid.n_radial, 1)
        ang = np.arange(1, grid.n_heading + 1) * 2.0 * np.pi / grid.n_heading
        acc = np.vstack([[0.0, 0.0], np.column_stack([np.repeat(mags, len(ang)) * np.cos(np.tile(ang, len(mags))),
                                                      np.repeat(mags, len(ang)) * np.sin(np.tile(ang, len(mags)))])])
        speed0 = np.linalg.norm(v0)
        brake = -v0 / speed0 * motion.accel_max_mps2 if speed0 > 1e-9 else np.zeros(2)
        acc = np.vstack([acc, brake])
        C = len(acc)
        paths, vel = np.empty((C, steps, 2)), np.empty((C, steps, 2))
        p, v = np.broadcast_to(p0, (C, 2)).copy(), np.broadcast_to(v0, (C, 2)).copy()
        is_brake = np.zeros(C, dtype=bool)
        is_brake[-1] = speed0 > 1e-9
        if motion.jerk_max_mps3 > 0.0:
            a = np.broadcast_to(np.zeros(2) if acceleration is None else np.asarray(acceleration, float)[:2],
                                (C, 2)).copy()
            for i in range(steps):
                stop = is_brake[:, None] & (np.linalg.norm(v, axis=1, keepdims=True) <= motion.accel_max_mps2 * dt)
                p, v, a = motion.step(p, v, a, np.where(stop, -v / dt, acc), dt)
                paths[:, i], vel[:, i] = p, v
        else:
            for i in range(steps):
                a = np.where(is_brake[:, None] & (np.linalg.norm(v, axis=1, keepdims=True)
                                                  <= motion.accel_max_mps2 * dt), -v / dt, acc)
                v_new = v + a * dt
                sp = np.linalg.norm(v_new, axis=1, keepdims=True)
                v_new *= np.minimum(1.0, motion.speed_max_mps / np.maximum(sp, 1e-12))
                p = p + 0.5 * (v + v_new) * dt
                v = v_new
                paths[:, i], vel[:, i] = p, v
    altitudes = np.full(paths.shape[:2] + (1,), grid.altitude_m)
    return np.concatenate([paths, altitudes], axis=2), vel


def _admissible_paths(paths: np.ndarray, start: np.ndarray, area_min, area_max,
                      uav_obstacles: Obstacles) -> tuple[np.ndarray, np.ndarray]:
    """First step admissible (C,), and the paths held at their last admissible point (C, H, 3):
    from a route's first step that leaves the area or crosses an obstacle on, it stays where it
    was (at the start if that is its first step). Every step is checked at once; at one altitude
    (the planner's paths) in the plane, against the side faces of the obstacles that block that
    altitude (``blocking_2d``, as the routes were drawn): the same test, on fewer faces."""
    C, H, _ = paths.shape
    start = np.broadcast_to(np.asarray(start, float), (C, 1, 3))
    ext = np.concatenate([start, paths], axis=1)  # (C, H+1, 3): the start, then the path
    ends, starts = paths.reshape(-1, 3), ext[:, :-1].reshape(-1, 3)
    if np.ptp(ext[:, :, 2]) > 0.0:
        ok = admissible(ends, starts, area_min, area_max, uav_obstacles)
    else:
        normals, offsets = blocking_2d(uav_obstacles, float(ext[0, 0, 2]))
        ok = np.all((ends >= np.asarray(area_min)) & (ends <= np.asarray(area_max)), axis=1)
        blocked = polygons_crossed(normals, offsets, starts[:, :2], ends[:, :2])
        ok &= ~(blocked | inside_2d(normals, offsets, ends[:, :2]))
    ok = ok.reshape(C, H)
    alive = np.logical_and.accumulate(ok, axis=1)
    n_ok = alive.sum(axis=1)  # the steps before the first that is not admissible
    last = np.minimum(np.arange(H)[None, :], n_ok[:, None] - 1)  # -1: the start
    held = ext[np.arange(C)[:, None], last + 1]
    return alive[:, 0].copy(), held


@dataclass(frozen=True, eq=False)
class RouteScoring:
    """How the lookahead draws and scores its routes: the targets' motion model (its tick is the
    planner's), the bearing noise sigma, the information reduction factor q (p_D, clutter) and
    the route planner's knobs."""

    model: MotionModel
    sigma_rad: float
    reduction: float
    params: LookaheadParams


def choose_lookahead(particles: np.ndarray, log_weights: np.ndarray, target_paths: np.ndarray, uav: UavState,
                     moves: Moves, scoring: RouteScoring, target_weights: np.ndarray | None = None
                     ) -> PlanningResult:
    """Non-myopic next position: score candidate *routes* over H = target_paths.shape[1] ticks.

    particles (M, N, 6) / log_weights (M, N): the predicted beliefs at t+1 (as for the greedy
    rule); target_paths (M, H, 6): each target's guidance plan, mu_(t+1..t+H|t).

    Routes (docs/PLANNING.md): to each waypoint (a polar grid around the UAV, the targets'
    predicted positions and centroid), the shortest polyline around the obstacles the UAV
    cannot overfly, flown at the speed limit, then a circle through the waypoint; the UAV's
    positions along it come from the motion model (jump: N_r Delta_r per tick; vehicle: speed
    and acceleration limits from ``uav.velocity``, and ``uav.acceleration`` with a continuous
    acceleration). Along each route the planar covariance
    of every target, initialised from its particles, is propagated with (A, Q) and updated with
    an ideal bearing from the route's position at each tick (EKF form, information scaled by the
    reduction factor q). Score: sum over ticks and targets of tr P_pos (the position, whatever
    the greedy rule's ``objective``), each target's weighted by ``target_weights`` (M,) when given
    (a target's modes as targets of their own, weighted by their probabilities).
    The first step of the best route is the next position (receding horizon): jump, the
    admissible point of S_(t+1) nearest to it; vehicle, the route's own first step, which is in
    the reachable set by construction.
    """
    H = target_paths.shape[1]
    model, area, motion = scoring.model, moves.area, moves.motion
    dt = model.dt_s
    altitude_m = moves.grid.altitude_m
    p0 = np.asarray(uav.position, float)[:2]
    v0 = np.zeros(2) if uav.velocity is None else np.asarray(uav.velocity, float)[:2]
    if motion.kind == "jump":
        v0 = np.zeros(2)
    routes = _routes(p0, target_paths, moves, scoring.params, dt)
    if not len(routes):  # e.g. the UAV is inside an inflated obstacle: the paper's rule decides
        return choose_next_position(particles, log_weights, UavState(np.r_[p0, altitude_m], v0, uav.acceleration),
                                    moves, scoring.sigma_rad, "position_trace", dt)
    pos, vel = fly_routes(routes, UavState(p0, v0, uav.acceleration), motion, moves.grid, H, dt,
                          scoring.params.spacing_m)  # (C, H, 2)
    ok = _first_step(pos, vel, p0, moves, dt)
    # a route that would leave the area or cross an obstacle later is scored as stopping there
    start3 = np.r_[p0, altitude_m]
    paths3 = np.concatenate([pos, np.full(pos.shape[:2] + (1,), altitude_m)], axis=2)
    _, paths3 = _admissible_paths(paths3, start3, area.minimum, area.maximum, area.obstacles)
    total = _route_traces(particles, log_weights, target_paths, paths3[..., :2], model, scoring.sigma_rad,
                          scoring.reduction)
    summed = total.sum(axis=1) if target_weights is None else total @ np.asarray(target_weights, float)
    scores = np.where(ok, summed, np.inf)
    index = int(np.argmin(scores)) if ok.any() else None
    return PlanningResult(paths3[:, 0], ok, total, scores, index, paths3, vel[:, 0])


def _routes(p0: np.ndarray, target_paths: np.ndarray, moves: Moves, params: LookaheadParams, dt: float
            ) -> np.ndarray:
    """The candidate routes (C, S, 2), sampled every ``spacing_m``: to each waypoint the shortest
    polyline around the obstacles the UAV cannot overfly, then a circle turning left or right."""
    H = target_paths.shape[1]
    grid, motion, area = moves.grid, moves.motion, moves.area
    normals, offsets = blocking_2d(area.obstacles, grid.altitude_m)
    wp = route_waypoints(p0, target_paths, params, area.minimum, area.maximum, normals, offsets,
                         params.corner_clearance_m)
    clearance = params.corner_clearance_m
    if motion.kind == "vehicle":  # it cuts corners: about half its turning radius v^2 / a
        clearance += 0.5 * motion.speed_max_mps ** 2 / motion.accel_max_mps2
    polys = route_polylines(p0, wp, normals, offsets, clearance)
    speed = grid.n_radial * grid.step_m / dt if motion.kind == "jump" else motion.speed_max_mps
    length = speed * dt * (H + 2)
    kept = [pl for pl in polys if pl is not None]
    if not kept:
        return np.zeros((0, 0, 2))
    return sample_routes(kept, params.loiter_radius_m, length, params.spacing_m)


def _first_step(pos: np.ndarray, vel: np.ndarray, p0: np.ndarray, moves: Moves, dt: float) -> np.ndarray:
    """(C,) the routes whose first step is admissible. Jump: each route's first move is snapped
    (in place in ``pos``, ``vel``) to the admissible point of the paper's S_(t+1) nearest to it.
    Vehicle: the first step admissible and the vehicle's braking path from there clear too."""
    C = len(pos)
    grid, motion, area = moves.grid, moves.motion, moves.area
    altitude_m = grid.altitude_m
    start3 = np.r_[p0, altitude_m]
    if motion.kind == "jump":
        grid_pts = candidate_positions(p0, grid)
        grid_ok = area.admissible(grid_pts, start3)
        d = np.linalg.norm(grid_pts[None, :, :2] - pos[:, :1, :], axis=2)
        d[:, ~grid_ok] = np.inf
        snap = np.argmin(d, axis=1)
        ok = np.isfinite(d[np.arange(C), snap])
        pos[:, 0] = grid_pts[snap, :2]
        vel[:, 0] = (pos[:, 0] - p0) / dt
        return ok
    first = np.column_stack([pos[:, 0], np.full(C, altitude_m)])
    ok = area.admissible(first, start3)
    sp = np.linalg.norm(vel[:, 0], axis=1, keepdims=True)
    stop = pos[:, 0] + vel[:, 0] / np.maximum(sp, 1e-9) * sp ** 2 / (2 * motion.accel_max_mps2)
    if motion.jerk_max_mps3 > 0.0:  # the braking acceleration is ramped to: up to 2 a_max / jerk later
        stop = stop + vel[:, 0] * 2.0 * motion.accel_max_mps2 / motion.jerk_max_mps3
    return ok & area.admissible(np.column_stack([stop, np.full(C, altitude_m)]), first)


def _route_traces(particles: np.ndarray, log_weights: np.ndarray, target_paths: np.ndarray, pos: np.ndarray,
                  model: MotionModel, sigma_rad: float, reduction: float) -> np.ndarray:
    """(C, M): per route (positions pos (C, H, 2)) and target, the sum over the horizon of tr P_pos,
    P the target's planar covariance from its particles, propagated with (A, Q) and updated at
    each tick with an ideal bearing to its planned position (EKF form, information times q)."""
    w = np.exp(log_weights - logsumexp(log_weights, axis=1, keepdims=True))  # (M, N)
    x = particles[:, :, PLANAR]
    mean = np.einsum("mn,mnd->md", w, x)
    dev = x - mean[:, None]
    P0 = np.einsum("mn,mni,mnj->ijm", w, dev, dev)  # (4, 4, M) predicted covariance at t+1, components first
    C, H = pos.shape[:2]
    P = np.broadcast_to(P0[:, :, None], (4, 4, C, len(w))).copy()  # (4, 4, C, M)
    total = np.zeros(P.shape[2:])
    for i in range(H):
        if i:
            P = predict_planar_components(P, model)
        P = bearing_update_components(P, target_paths[None, :, i, :2], pos[:, None, i], sigma_rad, reduction)
        total += P[0, 0] + P[1, 1]
    return total
