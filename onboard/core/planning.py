"""Next UAV position: candidate set S_(t+1) (eq. (3) of the paper), pseudo-posteriors from ideal
bearings (eq. (11)) and the argmin of summed traces (eq. (12)).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from onboard.core.bearings import bearing, wrap
from onboard.core.dynamics import MotionModel
from onboard.core.information import PLANAR, bearing_update_components, predict_planar_components
from onboard.core.obstacles import Obstacles, polygons_crossed
from onboard.core.setpoint import ramp_displacement, ramp_velocity
from onboard.core.tracking import logsumexp

OBJECTIVES = ("trace", "position_trace")


def _norms(xy: np.ndarray) -> np.ndarray:
    """|xy| of planar vectors (C, 2) as (C, 1): np.linalg.norm's values (sqrt(x x + y y)) without
    its generic path, which costs more than the arithmetic in the route planner's loops."""
    return np.sqrt(xy[:, 0] * xy[:, 0] + xy[:, 1] * xy[:, 1])[:, None]


@dataclass(frozen=True)
class CandidateGrid:
    step_m: float  # Delta_r
    n_radial: int  # N_r
    n_heading: int  # N_theta
    altitude_m: float  # h

    @classmethod
    def from_config(cls, u) -> "CandidateGrid":
        return cls(u.step_m, u.n_radial, u.n_heading, u.altitude_m)


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


def choose_next_position(particles: np.ndarray, log_weights: np.ndarray, center: np.ndarray,
                         grid: CandidateGrid, sigma_rad: float, area_min, area_max,
                         uav_obstacles: Obstacles, objective: str = "trace",
                         motion: "UavMotion | None" = None, velocity: np.ndarray | None = None,
                         dt: float = 1.0, acceleration: np.ndarray | None = None) -> PlanningResult:
    """Eq. (12) over the admissible next positions around ``center``: the paper's
    S_(t+1) with the jump motion (default), or those a vehicle reaches in one tick (from
    ``velocity`` and, continuous acceleration, ``acceleration``)."""
    motion = motion or JUMP
    velocity = np.zeros(2) if velocity is None else velocity
    paths, vel = motion_sequences(center, velocity, grid, motion, 1, dt, acceleration)
    cand = paths[:, 0]
    start = np.array([center[0], center[1], grid.altitude_m])
    ok = admissible(cand, start, area_min, area_max, uav_obstacles)
    traces = pseudo_posterior_traces(particles, log_weights, cand, sigma_rad, objective)
    scores = np.where(ok, traces.sum(axis=1), np.inf)
    index = int(np.argmin(scores)) if ok.any() else None
    return PlanningResult(cand, ok, traces, scores, index, None, vel[:, 0])


# --------------------------------------------------------------------------- beyond the paper


@dataclass(frozen=True)
class UavMotion:
    """How the UAV moves between ticks.

    ``jump``: the paper's model, any point of the polar grid S_(t+1) is reached in one tick.
    ``vehicle``: a multicopter with a speed and an acceleration limit (double integrator;
    ArduCopter's WPNAV_SPEED and WPNAV_ACCEL defaults, the scenario's, reproduce the measured 5.6 s
    for a 20 m step from hover); the next positions are those reached in one tick under a
    constant acceleration of N_r magnitudes (a_max k / N_r) in N_theta directions, or none.
    ``jerk_max_mps3`` > 0: the acceleration is continuous instead, changing linearly over each
    tick from where the last tick left it to the one asked for, by at most jerk_max_mps3 times
    the tick (onboard/core/setpoint.py: what ArduCopter's jerk-limited GUIDED follows).
    """

    kind: str  # jump | vehicle
    speed_max_mps: float  # vehicle only
    accel_max_mps2: float  # vehicle only
    jerk_max_mps3: float  # vehicle only; 0: the acceleration steps at each tick

    @classmethod
    def from_config(cls, planning) -> "UavMotion":
        """From the scenario's ``planning`` (onboard/settings.py declares the defaults)."""
        return cls(planning.motion, planning.speed_max_mps, planning.accel_max_mps2, planning.jerk_max_mps3)

    def step(self, p: np.ndarray, v: np.ndarray, a: np.ndarray, a_new: np.ndarray, dt: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Continuous acceleration (``jerk_max_mps3`` > 0): one tick from position, velocity and
        acceleration ``a`` (C, 2) asking for the acceleration ``a_new`` (|a_new| <= a_max): it
        ramps to it over the tick, the change capped at jerk_max_mps3 dt, the end speed at
        speed_max_mps (the end acceleration then what gives that speed). Returns (p, v, a) at
        the tick's end."""
        dj = a_new - a
        n = _norms(dj)
        a_end = a + dj * np.minimum(1.0, self.jerk_max_mps3 * dt / np.maximum(n, 1e-12))
        v_new = ramp_velocity(v, a, a_end, dt)
        sp = _norms(v_new)
        v_new = v_new * np.minimum(1.0, self.speed_max_mps / np.maximum(sp, 1e-12))
        a_end = 2.0 * (v_new - v) / dt - a
        disp = ramp_displacement(v, a, a_end, dt)
        return p + disp, v_new, a_end


JUMP = UavMotion("jump", math.inf, math.inf, 0.0)  # the paper's motion: no speed or acceleration limit applies


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
    alt = np.full(paths.shape[:2] + (1,), grid.altitude_m)
    return np.concatenate([paths, alt], axis=2), vel


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
        ok &= ~(blocked | _inside_2d(normals, offsets, ends[:, :2]))
    ok = ok.reshape(C, H)
    alive = np.logical_and.accumulate(ok, axis=1)
    n_ok = alive.sum(axis=1)  # the steps before the first that is not admissible
    last = np.minimum(np.arange(H)[None, :], n_ok[:, None] - 1)  # -1: the start
    held = ext[np.arange(C)[:, None], last + 1]
    return alive[:, 0].copy(), held


@dataclass(frozen=True)
class LookaheadParams:
    """The route planner's knobs (docs/PLANNING.md argues each value).

    ranges_m x n_headings: waypoints on a polar grid around the UAV; the targets' predicted
    positions (and their centroid) half-way and at the end of the horizon are waypoints too.
    Each route flies the shortest obstacle-free polyline to its waypoint at the motion's speed
    limit, then circles (left or right) through it with radius loiter_radius_m: a route always
    keeps moving, so the line of sight keeps turning. A route's score is the sum over the
    horizon and the targets of tr P_pos, position only and undiscounted (docs/PLANNING.md says
    why).
    """

    ranges_m: tuple[float, ...]  # m
    n_headings: int
    loiter_radius_m: float
    corner_clearance_m: float
    spacing_m: float  # arc-length resolution of the sampled routes, m

    @classmethod
    def from_config(cls, c) -> "LookaheadParams":
        """From the scenario's ``planning.lookahead`` (onboard/settings.py ``Lookahead`` declares
        the defaults, units and ranges)."""
        return cls(tuple(c.ranges_m), c.n_headings, c.loiter_radius_m, c.corner_clearance_m, c.spacing_m)


def blocking_2d(uav_obstacles: Obstacles, altitude_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Lateral faces (K, 4, 2), offsets (K, 4) of the obstacles the UAV cannot overfly at its altitude."""
    if not len(uav_obstacles):
        return np.zeros((0, 4, 2)), np.zeros((0, 4))
    n, b, lo, hi = uav_obstacles.lateral()
    keep = (lo < altitude_m) & (hi > altitude_m)
    return n[keep], b[keep]


def _inside_2d(normals, offsets, pts, extra: float = 0.0) -> np.ndarray:
    if not len(offsets):
        return np.zeros(len(pts), dtype=bool)
    c = np.einsum("kfd,pd->pkf", normals, pts) - offsets[None] - extra
    return np.all(c < 0, axis=-1).any(axis=-1)


def _corners_2d(normals, offsets, extra: float) -> np.ndarray:
    out = []
    for k in range(len(offsets)):
        for f in range(4):
            g = (f + 1) % 4
            out.append(np.linalg.solve(np.stack([normals[k, f], normals[k, g]]),
                                       [offsets[k, f] + extra, offsets[k, g] + extra]))
    return np.array(out).reshape(-1, 2)


def route_polylines(start: np.ndarray, waypoints: np.ndarray, normals, offsets,
                    clearance: float) -> list[np.ndarray]:
    """Shortest polyline start -> each waypoint around the blocking polygons (visibility graph
    over their corners pushed out by ``clearance``); a waypoint no route reaches gets None."""
    corners = _corners_2d(normals, offsets, clearance)
    if len(corners):
        corners = corners[~_inside_2d(normals, offsets, corners)]
    nodes = np.vstack([start[None], corners, waypoints])
    n, nc = len(nodes), 1 + len(corners)
    i, j = np.triu_indices(n, 1)
    keep = (i < nc) | (j < nc)  # waypoint-waypoint edges are never needed
    i, j = i[keep], j[keep]
    ok = ~polygons_crossed(normals, offsets, nodes[i], nodes[j])
    if not len(offsets):
        return [np.vstack([start, w]) for w in waypoints]
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import shortest_path
    w = np.maximum(np.linalg.norm(nodes[i] - nodes[j], axis=1), 1e-9)
    graph = coo_matrix((w[ok], (i[ok], j[ok])), shape=(n, n)).tocsr()
    dist, pred = shortest_path(graph, directed=False, indices=0, return_predecessors=True)
    out = []
    for t in range(nc, n):
        if not np.isfinite(dist[t]):
            out.append(None)
            continue
        order, v = [t], t
        while v != 0:
            v = pred[v]
            order.append(v)
        out.append(nodes[order[::-1]])
    return out


def _sample_routes(polys: list[np.ndarray], radius: float, length: float, ds: float) -> np.ndarray:
    """(2 C, S, 2): for each polyline, points every ds metres along it, then along a circle of
    ``radius`` that starts at its end, tangent to the last leg, turning left (route 2c) or right
    (route 2c + 1), up to ``length``. All routes at once: the polylines are padded with zero legs;
    what both turns share (the polyline's samples, the arc's angles) is computed once."""
    C = len(polys)
    n_seg = np.array([len(pl) - 1 for pl in polys])
    V = int(n_seg.max()) + 1
    poly = np.empty((C, V, 2))  # each polyline, then its end point repeated
    for c, pl in enumerate(polys):
        poly[c, :len(pl)] = pl
        poly[c, len(pl):] = pl[-1]
    seg = np.diff(poly, axis=1)
    seg_len = np.linalg.norm(seg, axis=2)
    cum = np.concatenate([np.zeros((C, 1)), np.cumsum(seg_len, axis=1)], axis=1)
    total = cum[np.arange(C), n_seg]
    s = np.arange(0.0, length + ds, ds)
    on = s[None, :] <= total[:, None]  # (C, S) along the polyline, else on the circle
    end = poly[np.arange(C), n_seg]
    # the last leg longer than 1e-9 m (the padding's zero legs come after n_seg): its direction
    real = (seg_len > 1e-9) & (np.arange(V - 1)[None, :] < n_seg[:, None])
    last = (V - 2) - np.argmax(real[:, ::-1], axis=1)
    tangent = np.tile([1.0, 0.0], (C, 1))
    for c in np.flatnonzero(total > 1e-9):
        tangent[c] = seg[c, last[c]] / np.linalg.norm(seg[c, last[c]])
    # on the polyline: the leg each sample falls on (searchsorted along each route's arc length)
    k = np.clip(np.array([np.searchsorted(row, s, side="right") for row in cum]) - 1, 0,
                np.maximum(n_seg - 1, 0)[:, None])
    rows = np.arange(C)[:, None]
    frac = (s[None, :] - cum[rows, k]) / np.maximum(seg_len[rows, k], 1e-12)
    along = poly[rows, k] + frac[..., None] * seg[rows, k]
    flat = total <= 1e-9  # a route that is its end point: the circle at once
    along[flat] = end[flat][:, None]
    ang = (s[None, :] - total[:, None]) / radius  # arc angle travelled on the circle
    cos, sin = np.cos(ang)[..., None], np.sin(ang)[..., None]
    out = np.empty((C, 2, len(s), 2))
    for i, side in enumerate((1.0, -1.0)):
        normal = side * np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
        centre = end + radius * normal
        r0 = -normal  # from the centre to the end point
        r1 = side * np.stack([-r0[:, 1], r0[:, 0]], axis=1)  # the travel direction at the start
        circle = centre[:, None] + radius * (cos * r0[:, None] + sin * r1[:, None])
        out[:, i] = np.where(on[..., None], along, circle)
    return out.reshape(2 * C, len(s), 2)


def _fly(routes: np.ndarray, p0: np.ndarray, v0: np.ndarray, motion: "UavMotion", grid: CandidateGrid,
         steps: int, dt: float, ds: float, a0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Positions (C, steps, 2) and velocities (C, steps, 2) of the UAV following each sampled
    route (C, S, 2). Jump: full-speed arc length N_r Delta_r per tick along the route. Vehicle:
    pursuit of a carrot on the route with |dv| <= a_max dt and |v| <= v_max every tick; with a
    continuous acceleration (``motion.jerk_max_mps3`` > 0, from ``a0``) the acceleration asked
    for is dv / dt (|.| <= a_max), ramped to over the tick (UavMotion.step)."""
    C, S, _ = routes.shape
    idx = np.arange(C)
    if motion.kind == "jump":
        step = grid.n_radial * grid.step_m
        k = np.minimum(np.round(np.arange(1, steps + 1) * step / ds).astype(int), S - 1)
        pos = routes[:, k]
        prev = np.concatenate([np.broadcast_to(p0, (C, 1, 2)), pos[:, :-1]], axis=1)
        return pos, (pos - prev) / dt
    vmax, amax = motion.speed_max_mps, motion.accel_max_mps2
    p = np.broadcast_to(np.asarray(p0, float), (C, 2)).copy()
    v = np.broadcast_to(np.asarray(v0, float), (C, 2)).copy()
    ramps = motion.jerk_max_mps3 > 0.0
    a = np.broadcast_to(np.zeros(2) if a0 is None else np.asarray(a0, float)[:2], (C, 2)).copy()
    near = np.zeros(C, dtype=int)  # the route sample reached so far (progress, in samples of ds)
    pos, vel = np.empty((C, steps, 2)), np.empty((C, steps, 2))
    look = vmax * dt
    window = np.arange(int(2 * look / ds) + 2)[None]
    lead = int(round(look / ds))
    # the routes flat, x and y apart: the window's gathers are then 1-D takes (the loop's cost)
    flat = routes.reshape(-1, 2)
    rx, ry = np.ascontiguousarray(flat[:, 0]), np.ascontiguousarray(flat[:, 1])
    first = idx * S
    for i in range(steps):
        # progress: the route point nearest to p in a window ahead of the last progress
        win = first[:, None] + np.minimum(near[:, None] + window, S - 1)
        dx, dy = rx.take(win) - p[:, :1], ry.take(win) - p[:, 1:]
        near = win[idx, np.argmin(dx * dx + dy * dy, axis=1)] - first
        carrot = flat[first + np.minimum(near + lead, S - 1)]
        to = carrot - p
        dist = _norms(to)
        v_des = to / np.maximum(dist, 1e-9) * np.minimum(vmax, dist / dt)
        dv = v_des - v
        n = _norms(dv)
        dv *= np.minimum(1.0, amax * dt / np.maximum(n, 1e-12))
        if ramps:
            p, v, a = motion.step(p, v, a, dv / dt, dt)
            pos[:, i], vel[:, i] = p, v
            continue
        v_new = v + dv
        sp = _norms(v_new)
        v_new *= np.minimum(1.0, vmax / np.maximum(sp, 1e-12))
        p = p + 0.5 * (v + v_new) * dt
        v = v_new
        pos[:, i], vel[:, i] = p, v
    return pos, vel


def _route_waypoints(position: np.ndarray, target_paths: np.ndarray, params: LookaheadParams,
                     area_min, area_max, normals, offsets, margin: float) -> np.ndarray:
    p0 = np.asarray(position, float)[:2]
    ang = np.arange(params.n_headings) * 2.0 * np.pi / params.n_headings
    rr = np.repeat(np.asarray(params.ranges_m, float), len(ang))
    aa = np.tile(ang, len(params.ranges_m))
    polar = p0 + np.column_stack([rr * np.cos(aa), rr * np.sin(aa)])
    H = target_paths.shape[1]
    at = [target_paths[:, k, :2] for k in sorted({max(H // 2 - 1, 0), H - 1})]
    targets = np.vstack(at + [a.mean(axis=0, keepdims=True) for a in at])
    wp = np.vstack([p0[None], polar, targets])
    lo = np.asarray(area_min, float)[:2] + margin
    hi = np.asarray(area_max, float)[:2] - margin
    wp = np.clip(wp, lo, hi)
    return wp[~_inside_2d(normals, offsets, wp)]


def choose_lookahead(particles: np.ndarray, log_weights: np.ndarray, target_paths: np.ndarray,
                     position: np.ndarray, velocity: np.ndarray, grid: CandidateGrid, motion: UavMotion,
                     model: MotionModel, sigma_rad: float, reduction: float, area_min, area_max,
                     uav_obstacles: Obstacles, *, params: LookaheadParams,
                     acceleration: np.ndarray | None = None, target_weights: np.ndarray | None = None
                     ) -> PlanningResult:
    """Non-myopic next position: score candidate *routes* over H = target_paths.shape[1] ticks.

    particles (M, N, 6) / log_weights (M, N): the predicted beliefs at t+1 (as for the greedy
    rule); target_paths (M, H, 6): each target's guidance plan, mu_(t+1..t+H|t).

    Routes (docs/PLANNING.md): to each waypoint (a polar grid around the UAV, the targets'
    predicted positions and centroid), the shortest polyline around the obstacles the UAV
    cannot overfly, flown at the speed limit, then a circle through the waypoint; the UAV's
    positions along it come from the motion model (jump: N_r Delta_r per tick; vehicle: speed
    and acceleration limits from the current velocity, and ``acceleration`` with a continuous
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
    dt = model.dt_s
    alt = grid.altitude_m
    p0 = np.asarray(position, float)[:2]
    v0 = np.zeros(2) if velocity is None else np.asarray(velocity, float)[:2]
    if motion.kind == "jump":
        v0 = np.zeros(2)
    routes = _routes(p0, target_paths, grid, motion, params, dt, area_min, area_max, uav_obstacles)
    if not len(routes):  # e.g. the UAV is inside an inflated obstacle: the paper's rule decides
        return choose_next_position(particles, log_weights, np.r_[p0, alt], grid, sigma_rad, area_min,
                                    area_max, uav_obstacles, "position_trace", motion, v0, dt, acceleration)
    pos, vel = _fly(routes, p0, v0, motion, grid, H, dt, params.spacing_m, acceleration)  # (C, H, 2)
    ok = _first_step(pos, vel, p0, grid, motion, dt, area_min, area_max, uav_obstacles)
    # a route that would leave the area or cross an obstacle later is scored as stopping there
    start3 = np.r_[p0, alt]
    paths3 = np.concatenate([pos, np.full(pos.shape[:2] + (1,), alt)], axis=2)
    _, paths3 = _admissible_paths(paths3, start3, area_min, area_max, uav_obstacles)
    total = _route_traces(particles, log_weights, target_paths, paths3[..., :2], model, sigma_rad, reduction)
    summed = total.sum(axis=1) if target_weights is None else total @ np.asarray(target_weights, float)
    scores = np.where(ok, summed, np.inf)
    index = int(np.argmin(scores)) if ok.any() else None
    return PlanningResult(paths3[:, 0], ok, total, scores, index, paths3, vel[:, 0])


def _routes(p0: np.ndarray, target_paths: np.ndarray, grid: CandidateGrid, motion: UavMotion,
            params: LookaheadParams, dt: float, area_min, area_max, uav_obstacles: Obstacles) -> np.ndarray:
    """The candidate routes (C, S, 2), sampled every ``spacing_m``: to each waypoint the shortest
    polyline around the obstacles the UAV cannot overfly, then a circle turning left or right."""
    H = target_paths.shape[1]
    normals, offsets = blocking_2d(uav_obstacles, grid.altitude_m)
    wp = _route_waypoints(p0, target_paths, params, area_min, area_max, normals, offsets,
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
    return _sample_routes(kept, params.loiter_radius_m, length, params.spacing_m)


def _first_step(pos: np.ndarray, vel: np.ndarray, p0: np.ndarray, grid: CandidateGrid, motion: UavMotion,
                dt: float, area_min, area_max, uav_obstacles: Obstacles) -> np.ndarray:
    """(C,) the routes whose first step is admissible. Jump: each route's first move is snapped
    (in place in ``pos``, ``vel``) to the admissible point of the paper's S_(t+1) nearest to it.
    Vehicle: the first step admissible and the vehicle's braking path from there clear too."""
    C = len(pos)
    alt = grid.altitude_m
    start3 = np.r_[p0, alt]
    if motion.kind == "jump":
        grid_pts = candidate_positions(p0, grid)
        grid_ok = admissible(grid_pts, start3, area_min, area_max, uav_obstacles)
        d = np.linalg.norm(grid_pts[None, :, :2] - pos[:, :1, :], axis=2)
        d[:, ~grid_ok] = np.inf
        snap = np.argmin(d, axis=1)
        ok = np.isfinite(d[np.arange(C), snap])
        pos[:, 0] = grid_pts[snap, :2]
        vel[:, 0] = (pos[:, 0] - p0) / dt
        return ok
    first = np.column_stack([pos[:, 0], np.full(C, alt)])
    ok = admissible(first, start3, area_min, area_max, uav_obstacles)
    sp = np.linalg.norm(vel[:, 0], axis=1, keepdims=True)
    stop = pos[:, 0] + vel[:, 0] / np.maximum(sp, 1e-9) * sp ** 2 / (2 * motion.accel_max_mps2)
    if motion.jerk_max_mps3 > 0.0:  # the braking acceleration is ramped to: up to 2 a_max / jerk later
        stop = stop + vel[:, 0] * 2.0 * motion.accel_max_mps2 / motion.jerk_max_mps3
    return ok & admissible(np.column_stack([stop, np.full(C, alt)]), first, area_min, area_max, uav_obstacles)


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
