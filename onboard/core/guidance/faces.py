"""Face assignments of P1: which lateral face of each obstacle every segment of a path keeps
outside of, the geometry that picks and checks them, and the side (winding) an assignment
rounds an obstacle on (docs/GUIDANCE.md, "The assignment search", "A chosen side")."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path

from onboard.core.obstacles import N_LATERAL, Obstacles, polygons_crossed

NO_FACE = -1
FEAS_TOL_M = 1e-3  # accept a QP solution whose obstacle rows are violated by less than this
_PUSH_OUT_M = 0.01  # a start inside an inflated obstacle is planned from this far outside it


def _opposite(f: np.ndarray, g: np.ndarray) -> np.ndarray:
    return (f >= 0) & (g >= 0) & ((f - g) % N_LATERAL == 2)


@dataclass(eq=False)
class FaceGeometry:
    """Everything about the obstacles that a face assignment needs, for one tick."""

    normals: np.ndarray  # (K, 4, 2)
    offsets: np.ndarray  # (K, 4), inflated
    relevant: np.ndarray  # (T-1, K) segment s = 1..T-1 may meet obstacle k (altitude overlap)

    def clearance(self, pts: np.ndarray) -> np.ndarray:
        """pts (P, 2) -> (P, K, 4): a . p - b, > 0 outside that face."""
        return np.einsum("kfd,pd->pkf", self.normals, pts) - self.offsets[None]

    def push_out(self, x: np.ndarray, which: np.ndarray) -> np.ndarray | None:
        """x = (px, py, vx, vy): the position moved across the nearest face of each polygon in
        ``which`` (K,) it is inside, to just outside it, and the velocity's component into that
        face removed; None if it is inside none."""
        x = np.array(x, dtype=float)
        moved = False
        for _ in range(len(self.offsets)):
            c = self.clearance(x[None, :2])[0]  # (K, 4)
            inside = np.all(c < 0, axis=-1) & which
            if not inside.any():
                break
            k = int(np.flatnonzero(inside)[0])
            f = int(np.argmax(c[k]))
            n = self.normals[k, f]
            x[:2] += (_PUSH_OUT_M - c[k, f]) * n
            x[2:] -= min(0.0, float(n @ x[2:])) * n
            moved = True
        return x if moved else None

    def inside(self, pts: np.ndarray) -> np.ndarray:
        """(P, K): strictly inside the inflated polygon."""
        return np.all(self.clearance(pts) < 0, axis=-1)

    def repick(self, pts: np.ndarray) -> np.ndarray:
        """Per segment and obstacle, the face with the largest clearance of both end points.

        pts (T+1, 2) holds p_0..p_T; returns (T-1, K) for segments s = 1..T-1.
        """
        c = self.clearance(pts)
        seg = np.minimum(c[1:-1], c[2:])  # (T-1, K, 4)
        faces = np.argmax(seg, axis=-1)
        # segment 1 starts at p_1, which no control can move: prefer faces it already satisfies
        ok1 = c[1] >= 0  # (K, 4)
        seg1 = np.where(ok1, seg[0], -np.inf)
        faces[0] = np.where(ok1.any(axis=-1), np.argmax(seg1, axis=-1), np.argmax(c[2], axis=-1))
        return self.sanitise(faces, pts)

    def sanitise(self, faces: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """Irrelevant segments get no face, relevant ones one; no jump between opposite faces.

        pts (T+1, 2) is the path the assignment is meant for (where a face must be chosen afresh).
        """
        c = self.clearance(pts)
        missing = self.relevant & (faces < 0)
        if missing.any():
            fresh = np.argmax(np.minimum(c[1:-1], c[2:]), axis=-1)
            faces = np.where(missing, fresh, faces)
        faces = np.where(self.relevant, faces, NO_FACE)
        bad = np.flatnonzero(_opposite(faces[:-1], faces[1:]).any(axis=1))
        if bad.size == 0:
            return faces
        for s in range(int(bad[0]) + 1, len(faces)):  # a fix can make the next pair opposite
            bad = _opposite(faces[s - 1], faces[s])
            for k in np.flatnonzero(bad):
                f = faces[s - 1, k]
                adj = np.array([(f + 1) % N_LATERAL, (f - 1) % N_LATERAL])
                faces[s, k] = adj[np.argmax(c[s + 1, k, adj])]
        return faces

    def same_optimum(self, faces: np.ndarray, new: np.ndarray, pts: np.ndarray, duals: np.ndarray) -> bool:
        """True when a solution of ``faces`` is provably optimal for ``new`` as well: every
        changed segment's old rows were inactive (zero duals) and the path satisfies its new
        face at both ends. The re-pick's change can then only move slack rows: no solve needed.
        """
        changed = faces != new  # (T-1, K)
        if not changed.any():
            return True
        s_idx, k_idx = np.nonzero(changed)
        if np.any(np.abs(duals[k_idx, s_idx]) > 0.0):
            return False
        f = new[s_idx, k_idx]
        on = f >= 0
        a, b = self.normals[k_idx[on], f[on]], self.offsets[k_idx[on], f[on]]
        ends = np.stack([pts[s_idx[on] + 1], pts[s_idx[on] + 2]], axis=1)  # segment s = s_idx + 1
        return bool(np.all(np.einsum("cd,ced->ce", a, ends) - b[:, None] >= -FEAS_TOL_M))

    def violation(self, faces: np.ndarray, pts: np.ndarray) -> float:
        """Largest violation (m) of an assignment's rows by the path p_0..p_T."""
        coef, rhs = self.rows(faces)
        starts, ends = pts[1:-1], pts[2:]  # segment s = 1..T-1
        lhs = np.stack([np.einsum("ksd,sd->ks", coef[:, :, 0], starts),
                        np.einsum("ksd,sd->ks", coef[:, :, 1], ends)], axis=-1)
        gap = rhs - lhs
        return float(np.max(gap[np.isfinite(rhs)], initial=0.0))

    def rows(self, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """QP obstacle rows for an assignment: coef (K, T-1, 2, 2), rhs (K, T-1, 2)."""
        Tm1, K = faces.shape
        f = faces.T  # (K, T-1)
        on = f >= 0
        k = np.arange(K)[:, None]
        face = np.where(on, f, 0)
        coef = np.where(on[:, :, None, None], self.normals[k, face][:, :, None, :], 0.0)
        coef = np.broadcast_to(coef, (K, Tm1, 2, 2)).copy()  # the same row at both ends
        rhs = np.where(on[:, :, None], self.offsets[k, face][:, :, None], -np.inf)
        rhs = np.broadcast_to(rhs, (K, Tm1, 2)).copy()
        # p_1 is fixed by the current state: no row on it
        coef[:, 0, 0] = 0.0
        rhs[:, 0, 0] = -np.inf
        return coef, rhs

    def push_around(self, pts: np.ndarray, k: int, side: float) -> np.ndarray:
        """Move the points inside polygon k out of it, sideways to the travel direction.

        side +1 passes the obstacle on the left of the travel direction, -1 on the right.
        """
        inside = self.inside(pts)[:, k]
        idx = np.flatnonzero(inside)
        if idx.size == 0:
            return pts
        a, b = max(idx[0] - 1, 0), min(idx[-1] + 1, len(pts) - 1)
        d = pts[b] - pts[a]
        norm = np.linalg.norm(d)
        if norm < 1e-9:
            return pts
        e = side * np.array([-d[1], d[0]]) / norm
        out = pts.copy()
        A, B = self.normals[k], self.offsets[k]
        ae = A @ e
        for i in idx:
            with np.errstate(divide="ignore"):
                t = np.where(ae > 1e-12, (B - A @ pts[i]) / ae, np.inf)
            out[i] = pts[i] + (t.min() + 0.5) * e
        return out

    def segments_cross(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """(S,) True where segment a[s] -> b[s] passes through any polygon's interior."""
        return polygons_crossed(self.normals, self.offsets, a, b)

    def corners(self, extra: float) -> np.ndarray:
        """Corners of every polygon pushed out by ``extra`` along both faces: (4K, 2)."""
        out = []
        for k in range(len(self.offsets)):
            for f in range(N_LATERAL):
                g = (f + 1) % N_LATERAL
                M = np.stack([self.normals[k, f], self.normals[k, g]])
                out.append(np.linalg.solve(M, [self.offsets[k, f] + extra, self.offsets[k, g] + extra]))
        return np.array(out).reshape(-1, 2)

    def guide_path(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """Shortest polyline start -> goal around the polygons (visibility graph), or None."""
        nodes = np.vstack([start, goal, self.corners(1.0)])
        n = len(nodes)
        i, j = np.triu_indices(n, 1)
        ok = ~self.segments_cross(nodes[i], nodes[j])
        w = np.linalg.norm(nodes[i] - nodes[j], axis=1)
        graph = sp.coo_matrix((w[ok], (i[ok], j[ok])), shape=(n, n)).tocsr()
        dist, pred = shortest_path(graph, directed=False, indices=0, return_predecessors=True)
        if not np.isfinite(dist[1]):
            return None
        order, v = [1], 1
        while v != 0:
            v = pred[v]
            order.append(v)
        return nodes[order[::-1]]

    def guide_path_around(self, start: np.ndarray, goal: np.ndarray, sides: np.ndarray) -> np.ndarray | None:
        """Shortest polyline start -> goal through a waypoint beside each polygon k with
        ``sides[k]`` != 0, on the side that rounds it that way (+1 counterclockwise: the polygon on
        the left of the travel start -> goal), in order along the travel; None if a waypoint is
        inside a polygon or a leg has no path."""
        d = goal - start
        norm = np.linalg.norm(d)
        if norm < 1e-9:
            return None
        d = d / norm
        left = np.array([-d[1], d[0]])
        corners = self.corners(0.0).reshape(-1, N_LATERAL, 2)
        ks = np.flatnonzero(sides)
        centres = corners[ks].mean(axis=1)
        radii = np.linalg.norm(corners[ks] - centres[:, None], axis=-1).max(axis=1)
        order = np.argsort((centres - start) @ d)
        points = [centres[i] - sides[ks[i]] * (radii[i] + 2.0) * left for i in order]
        if len(points) and self.inside(np.array(points)).any():
            return None
        legs, a = [], start
        for b in points + [goal]:
            leg = self.guide_path(a, b)
            if leg is None:
                return None
            legs.append(leg if not legs else leg[1:])
            a = b
        return np.vstack(legs)

    def blocking(self, pts: np.ndarray) -> list[int]:
        """Obstacles the path pts passes through (a point inside or a segment crossing)."""
        c = self.clearance(pts)
        inside = np.all(c < 0, axis=-1).any(axis=0)
        # a segment crosses a convex polygon iff no face separates both end points and ... cheap
        # approximation enough for picking candidates: also test midpoints
        mid = 0.5 * (pts[1:] + pts[:-1])
        inside |= self.inside(mid).any(axis=0)
        return [int(k) for k in np.flatnonzero(inside)]



def face_geometry(obstacles: Obstacles, margin: float, z: np.ndarray,
                      lateral_margin: float | None = None) -> FaceGeometry:
    """The obstacles inflated by ``margin`` (``lateral_margin`` sideways, when given) as seen by
    a path at altitudes z (T+1,)."""
    normals, offsets, z_lo, z_hi = obstacles.inflate(margin).lateral()
    if lateral_margin is not None:
        normals, offsets, _, _ = obstacles.inflate(lateral_margin).lateral()
    # segment s (p_s -> p_(s+1)) misses obstacle k vertically iff both ends are above or below it
    za, zb = z[1:-1, None], z[2:, None]
    above = (za >= z_hi[None]) & (zb >= z_hi[None])
    below = (za <= z_lo[None]) & (zb <= z_lo[None])
    return FaceGeometry(normals, offsets, ~(above | below))


def timed_path(polyline: np.ndarray, p0: np.ndarray, step_m: float, T: int) -> np.ndarray:
    """p_0..p_T: p0, then points along the polyline (which starts at p_1) every step_m metres."""
    seg = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.minimum(np.arange(T) * step_m, arc[-1])
    pts = np.stack([np.interp(s, arc, polyline[:, d]) for d in range(2)], axis=1)
    return np.vstack([p0, pts])



def shift_switches(faces: np.ndarray, d: int) -> np.ndarray | None:
    """The assignment with every face switch d steps later (earlier for d < 0); None if a
    switch would leave the horizon."""
    out = faces.copy()
    n = len(faces)
    for k in range(faces.shape[1]):
        col = faces[:, k]
        sw = np.flatnonzero((col[1:] != col[:-1]) & (col[1:] >= 0) & (col[:-1] >= 0)) + 1
        if sw.size == 0:
            continue
        if sw.min() + d < 1 or sw.max() + d > n - 1:
            return None
        new = np.empty_like(col)
        idx = np.arange(n) - d  # segment i takes the face segment i - d had
        new[:] = col[np.clip(idx, 0, n - 1)]
        out[:, k] = np.where(col >= 0, new, col)
    return out



def winding(faces: np.ndarray) -> np.ndarray:
    """(K,) quarter turns a face assignment (T-1, K) makes about each obstacle: + counterclockwise
    (the obstacle on the path's left), - clockwise, 0 for a path that keeps one face. Its sign is
    the side on which a path rounds the obstacle (the homotopy class, for a path that rounds it);
    it shrinks as the target gets round and the passed faces leave the horizon."""
    a, b = faces[:-1], faces[1:]
    step = np.where((a >= 0) & (b >= 0), (b - a + 1) % N_LATERAL - 1, 0)
    return step.sum(axis=0)


def in_class(faces: np.ndarray, sides: np.ndarray | None, strict: bool = False) -> bool:
    """The assignment rounds no obstacle k the other way than ``sides[k]`` (+1 counterclockwise,
    -1 clockwise, 0 either); ``strict``: it does round each k with ``sides[k]`` != 0 that way
    (holding back short of it, or having passed it, winding 0, does not)."""
    if sides is None:
        return True
    sides = np.asarray(sides)
    w = winding(faces) * sides
    return bool(np.all(np.where(sides != 0, w > 0, True) if strict else w >= 0))

