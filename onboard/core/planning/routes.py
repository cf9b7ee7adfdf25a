"""The lookahead's route geometry (docs/PLANNING.md): the obstacles the UAV cannot overfly at its
altitude as polygons, the waypoints around the UAV and the targets, the shortest polylines to them
around the polygons, the routes sampled along them and a circle at their end, and the UAV's
positions flying them."""
from __future__ import annotations

import numpy as np

from onboard.core.obstacles import Obstacles, polygons_crossed
from onboard.core.planning.inputs import CandidateGrid, LookaheadParams, UavMotion, UavState, planar_norms


def blocking_2d(uav_obstacles: Obstacles, altitude_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Lateral faces (K, 4, 2), offsets (K, 4) of the obstacles the UAV cannot overfly at its altitude."""
    if not len(uav_obstacles):
        return np.zeros((0, 4, 2)), np.zeros((0, 4))
    n, b, lo, hi = uav_obstacles.lateral()
    keep = (lo < altitude_m) & (hi > altitude_m)
    return n[keep], b[keep]


def inside_2d(normals, offsets, pts, extra: float = 0.0) -> np.ndarray:
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
        corners = corners[~inside_2d(normals, offsets, corners)]
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


def sample_routes(polys: list[np.ndarray], radius: float, length: float, ds: float) -> np.ndarray:
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



def route_waypoints(position: np.ndarray, target_paths: np.ndarray, params: LookaheadParams,
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
    return wp[~inside_2d(normals, offsets, wp)]


def fly_routes(routes: np.ndarray, uav: UavState, motion: UavMotion, grid: CandidateGrid, steps: int,
               dt: float, ds: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions (C, steps, 2) and velocities (C, steps, 2) of the UAV following each sampled
    route (C, S, 2) from ``uav`` (planar; its velocity given). Jump: full-speed arc length
    N_r Delta_r per tick along the route. Vehicle: pursuit of a carrot on the route with
    |dv| <= a_max dt and |v| <= v_max every tick; with a continuous acceleration
    (``motion.jerk_max_mps3`` > 0, from ``uav.acceleration``) the acceleration asked for is dv / dt
    (|.| <= a_max), ramped to over the tick (UavMotion.step)."""
    p0, v0, a0 = uav.position, uav.velocity, uav.acceleration
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
        dist = planar_norms(to)
        v_des = to / np.maximum(dist, 1e-9) * np.minimum(vmax, dist / dt)
        dv = v_des - v
        n = planar_norms(dv)
        dv *= np.minimum(1.0, amax * dt / np.maximum(n, 1e-12))
        if ramps:
            p, v, a = motion.step(p, v, a, dv / dt, dt)
            pos[:, i], vel[:, i] = p, v
            continue
        v_new = v + dv
        sp = planar_norms(v_new)
        v_new *= np.minimum(1.0, vmax / np.maximum(sp, 1e-12))
        p = p + 0.5 * (v + v_new) * dt
        v = v_new
        pos[:, i], vel[:, i] = p, v
    return pos, vel
