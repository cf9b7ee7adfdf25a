"""The guidance predictor: Problem P1 solved with OSQP, without a mixed-integer solver.

P1 (Sec. III) is a mixed-integer QP: per horizon step and obstacle, binaries pick a face of the
cuboid that the target is outside of. Here the binaries are fixed to a *face assignment*, the
remaining convex QP is solved with OSQP, and the assignment is improved until it is stable:

1. candidate assignments: the previous tick's shifted by one step (warm start); and, when there
   is none or it fails, the faces with the most clearance along the obstacle-free optimum and
   along copies of it pushed around each blocking obstacle on either side (homotopy classes);
2. each candidate: solve, re-pick every segment's face by largest clearance, re-solve until the
   assignment repeats;
3. local search on the best: move each face change that has an active constraint one step
   earlier or later, keep improvements, within a budget of QP solves.

Exactness is measured against an exact MIQP solve (``bench/guidance_vs_miqp.py``).

Deliberate differences from the paper's text (docs/GUIDANCE.md says why):

* Segments, not only points: the two end points of the straight segment between consecutive
  horizon points must be outside the *same* face, so the segment cannot cut a corner.
* Ground plane: with u_z = 0 the vertical state is not a decision variable, so the top/bottom
  faces' binaries are fixed by the predicted altitude; obstacles are solved as polygons of their
  four lateral faces wherever the target's altitude is within their (inflated) height.
* Cost: sum_tau q_tau ||p_tau - G_o||^2 + r sum ||u_tau - u_(tau-1)||^2 with u in kN.
  ``terminal_weight`` is the paper's term (tau = T); ``stage_weight`` adds tau < T, without
  which a receding-horizon target never arrives (the optimum reaches the goal exactly at T).
* The 2-norm speed bound is an inscribed polygon of ``speed_polygon_sides`` sides; from a state
  faster than the bound, the bound at step tau relaxes to what friction alone achieves.
* Position p_(t+1) = p_t + dt v_t does not depend on the controls, so constraints on it are
  dropped (they can only be infeasible, never helpful).
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import osqp
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path

from onboard.core.dynamics import MotionModel, predict_mean
from onboard.core.obstacles import N_LATERAL, Obstacles

KN = 1000.0  # the QP works in kilonewtons: keeps its numbers near unity
_FEAS_TOL_M = 1e-3  # accept a QP solution whose obstacle rows are violated by less than this
_NO_FACE = -1


@dataclass(frozen=True)
class GuidanceParams:
    horizon: int = 50
    u_max_n: float = 6000.0
    speed_max_mps: float = 16.0
    speed_polygon_sides: int = 16
    terminal_weight: float = 1.0  # per m^2
    stage_weight: float = 1.0  # per m^2
    smooth_weight: float = 1000.0  # per kN^2
    obstacle_margin_m: float = 5.0
    max_qp_solves: int = 12

    @classmethod
    def from_config(cls, g) -> "GuidanceParams":
        return cls(g.horizon, g.u_max_n, g.speed_max_mps, g.speed_polygon_sides, g.terminal_weight,
                   g.stage_weight, g.smooth_weight, g.obstacle_margin_m, g.max_qp_solves)


@dataclass(frozen=True, eq=False)
class Plan:
    """A guidance solution for one target.

    ``status``: ``optimal`` (assignment stable, local search done), ``budget`` (best found when
    the QP budget ran out), ``fallback_previous`` (no feasible plan: the previous plan shifted by
    one step) or ``fallback_coast`` (no feasible plan and none before: zero control, the target
    coasting under friction). ``cost`` is P1's objective (nan for fallbacks).
    """

    status: str
    cost: float
    solve_time_s: float
    qp_solves: int
    controls: np.ndarray  # (T, 3) N, u_(t+tau|t)
    means: np.ndarray  # (T, 6) mu_(t+tau+1|t)
    faces: np.ndarray  # (T-1, K) lateral face per segment p_s -> p_(s+1), s = 1..T-1; -1: none

    @property
    def feasible(self) -> bool:
        return not self.status.startswith("fallback")

    @property
    def next_control(self) -> np.ndarray:
        return self.controls[0]


# --------------------------------------------------------------------------- the convex QP


@dataclass(eq=False)
class _QP:
    """One OSQP instance for a fixed horizon and obstacle count; obstacle rows are updated in place.

    Flat-output form: position is a flat output of the target model, so the decision variables
    are the positions y = [p_2 .. p_(T+1)] alone (p_1 = p_0 + dt v_0 is fixed). Velocities
    v_tau = (p_(tau+1) - p_tau) / dt and controls u_tau = m (v_(tau+1) - (1 - eps) v_tau) / dt are
    banded linear maps of y, so the QP has no equality constraints and a banded KKT matrix.
    (The textbook sparse form with states, inputs and dynamics equalities took OSQP thousands
    of iterations per solve here; this form converges in tens to hundreds.) Positions are
    relative to the goal, in units of L, which keeps the numbers near unity for ADMM.
    Optional slack: ``soft`` adds sigma >= 0 per obstacle row with a quadratic penalty, always
    feasible; its solution only guides the face re-pick, the hard QP gives the answer.
    """

    T: int
    K: int
    dt: float
    decay: float  # 1 - friction
    gain: float  # m/s of velocity change per kN over one step
    params: GuidanceParams
    soft: bool = False
    solver: osqp.OSQP = field(init=False)
    n_solves: int = field(init=False, default=0)

    L = 100.0  # m
    SLACK_WEIGHT = 1e3  # per L^2

    def __post_init__(self):
        T, K, p, L = self.T, self.K, self.params, self.L
        ny = 2 * T
        n_obs = 2 * K * (T - 1)
        n = ny + (n_obs if self.soft else 0)
        self.n, self.ny, self.n_obs = n, ny, n_obs
        # affine maps of the positions: P_all (T+2 points) = Sel y + fixed(p_0, p_1)
        # velocity v_tau, tau = 1..T:  (p_(tau+1) - p_tau) / dt
        # control  w_tau, tau = 0..T-1: (v_(tau+1) - decay v_tau) / gain, v_0 given
        # represented per axis with matrices over the T unknown points p_2..p_(T+1)
        Vm = np.zeros((T, T))  # v_tau (tau=1..T) = Vm @ y_axis + Vc
        for tau in range(1, T + 1):
            Vm[tau - 1, tau - 1] = 1.0 / self.dt  # p_(tau+1) is y index tau-1
            if tau >= 2:
                Vm[tau - 1, tau - 2] = -1.0 / self.dt
        self.Vm = Vm
        Wm = np.zeros((T, T))  # w_tau (tau=0..T-1) from v_(tau+1) and v_tau (tau>=1)
        Wm[0] = Vm[0] / self.gain
        for tau in range(1, T):
            Wm[tau] = (Vm[tau] - self.decay * Vm[tau - 1]) / self.gain
        self.Wm = Wm
        Dm = np.diff(np.eye(T), axis=0)  # (T-1, T): w_tau - w_(tau-1)
        DW = Dm @ Wm
        self.DW = DW
        qw = np.full(T, p.stage_weight)
        qw[-1] = p.terminal_weight
        self.goal_weights = qw  # on p_1..p_T
        # cost / L^2 per axis: sum q_tau |p_tau|^2 (tau = 2..T) + r |DW y + dwc|^2, since the
        # controls in kN are w = L (Wm y + Wc) with y in units of L
        self.r_scaled = p.smooth_weight  # the cost divided by L^2 keeps r as it is
        Pax = 2.0 * (np.diag(np.concatenate([qw[1:], [0.0]])) + self.r_scaled * DW.T @ DW)
        blocks = [sp.kron(sp.csc_matrix(Pax), sp.eye(2))]  # interleaved (x, y) per point
        if self.soft:
            blocks.append(sp.eye(n_obs) * 2.0 * self.SLACK_WEIGHT)
        self.P = sp.triu(sp.block_diag(blocks), format="csc")

        rows, cols, vals = [], [], []

        def put_dense(r0, M):
            """Rows r0.. of kron(M, I2): each axis separately."""
            nz = np.nonzero(M)
            for i, j in zip(*nz):
                for ax in range(2):
                    rows.append(r0 + 2 * i + ax)
                    cols.append(2 * j + ax)
                    vals.append(M[i, j])

        r = 0
        put_dense(r, Wm)  # control box (kN), per axis
        self.box_rows = slice(r, r + 2 * T)
        r += 2 * T
        # speed polygon: c_k . v_tau <= bound_tau
        ang = 2 * np.pi * np.arange(p.speed_polygon_sides) / p.speed_polygon_sides
        self.speed_normals = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        self.speed_row0 = r
        for tau in range(T):
            for c in self.speed_normals:
                for j in np.flatnonzero(Vm[tau]):
                    for ax in range(2):
                        rows.append(r)
                        cols.append(2 * j + ax)
                        vals.append(Vm[tau, j] * c[ax])
                r += 1
        # obstacles: obstacle k, segment s = 1..T-1: a_f . p_s >= b_f (s >= 2), a_f . p_(s+1) >= b_f
        self.obs_row0 = r
        obs_entries = []
        for k in range(K):
            for s in range(1, T):
                for tau in (s, s + 1):
                    j = max(tau - 2, 0)  # p_1 is not a variable: its row gets zero coefficients
                    for ax in range(2):
                        obs_entries.append(len(vals))
                        rows.append(r)
                        cols.append(2 * j + ax)
                        vals.append(1.0)
                    if self.soft:
                        rows.append(r)
                        cols.append(ny + r - self.obs_row0)
                        vals.append(1.0)
                    r += 1
        if self.soft:
            self.slack_rows = slice(r, r + n_obs)
            for i in range(n_obs):
                rows.append(r)
                cols.append(ny + i)
                vals.append(1.0)
                r += 1
        self.m = r

        nnz = len(vals)
        ids = sp.coo_matrix((np.arange(1, nnz + 1, dtype=float), (rows, cols)), shape=(r, n)).tocsc()
        order = ids.data.astype(int) - 1  # csc position -> original entry
        where = np.empty(nnz, dtype=int)
        where[order] = np.arange(nnz)
        A = ids.copy()
        A.data = np.asarray(vals, dtype=float)[order]
        self.A = A
        self.obs_idx = where[np.asarray(obs_entries, dtype=int)]
        self.l = np.full(r, -np.inf)
        self.u = np.full(r, np.inf)
        if self.soft:
            self.l[self.slack_rows] = 0.0
        self.solver = osqp.OSQP()
        self.solver.setup(self.P, np.zeros(n), self.A, self.l, self.u, verbose=False,
                          eps_abs=1e-5, eps_rel=1e-5, polishing=True, max_iter=4000,
                          warm_starting=True)

    def _fixed_terms(self, x0: np.ndarray, goal: np.ndarray):
        """Constant parts of velocity and control maps, scaled, per axis: (Vc (T,2), Wc (T,2))."""
        L = self.L
        p1 = (x0[:2] + self.dt * x0[2:] - goal) / L
        v0 = x0[2:] / L
        Vc = np.zeros((self.T, 2))
        Vc[0] = -p1 / self.dt
        Wc = np.zeros((self.T, 2))
        Wc[0] = (Vc[0] - self.decay * v0) / self.gain
        for tau in range(1, self.T):
            Wc[tau] = (Vc[tau] - self.decay * Vc[tau - 1]) / self.gain
        return p1, Vc, Wc

    def solve(self, x0: np.ndarray, goal: np.ndarray, speed_bound: np.ndarray,
              coef: np.ndarray, rhs: np.ndarray):
        """x0 = (px, py, vx, vy); coef (K, T-1, 2, 2), rhs (K, T-1, 2) with -inf for rows off.

        Returns (positions (T+1, 2) p_1..p_(T+1) in m, duals (K, T-1, 2), violation_m) or None.
        """
        T, L = self.T, self.L
        p1, Vc, Wc = self._fixed_terms(x0, goal)
        dwc = np.diff(Wc, axis=0)  # (T-1, 2)
        q = np.zeros(self.n)
        q[:self.ny] = (2.0 * self.r_scaled * self.DW.T @ dwc).reshape(-1)
        l, u = self.l.copy(), self.u.copy()
        box = self.params.u_max_n * (1.0 - 1e-3) / KN / L  # inside by 0.1 %: ADMM's tolerance
        l[self.box_rows] = (-box - Wc).reshape(-1)
        u[self.box_rows] = (box - Wc).reshape(-1)
        cv = np.einsum("kd,td->tk", self.speed_normals, Vc)
        u[self.speed_row0:self.obs_row0] = (speed_bound[:, None] / L - cv).reshape(-1)
        # obstacle rows in scaled, goal-relative units; the p_1 row is off (coef zero)
        lo = (rhs - np.einsum("ksed,d->kse", coef, goal)) / L
        l[self.obs_row0:self.obs_row0 + self.n_obs] = lo.reshape(-1)
        kw = dict(q=q, l=l, u=u)
        if self.n_obs:
            kw.update(Ax=coef.reshape(-1), Ax_idx=self.obs_idx)
        self.solver.update(**kw)
        self.n_solves += 1
        res = self.solver.solve(raise_error=False)
        if res.info.status_val not in (1, 2) or res.x is None or not np.all(np.isfinite(res.x)):
            return None
        y = res.x[:self.ny].reshape(T, 2)
        ax = (self.A[self.obs_row0:self.obs_row0 + self.n_obs] @ np.concatenate(
            [res.x[:self.ny], np.zeros(self.n - self.ny)]))
        lo = lo.reshape(-1)
        finite = np.isfinite(lo)
        violation = L * float(np.max(lo[finite] - ax[finite], initial=0.0))
        pts = np.vstack([p1, y]) * L + goal
        duals = res.y[self.obs_row0:self.obs_row0 + self.n_obs].reshape(self.K, T - 1, 2)
        return pts, duals, violation


class GuidanceWorkspace:
    """Caches OSQP instances between ticks (one per target, shape and hard/soft form).

    Purely a performance cache: results do not depend on it beyond solver tolerances.
    """

    def __init__(self):
        self._qps: dict[tuple, _QP] = {}

    def qp(self, key, T: int, K: int, model: MotionModel, params: GuidanceParams, soft: bool) -> _QP:
        full = (key, T, K, model.dt_s, model.friction, model.mass_kg, params, soft)
        if full not in self._qps:
            gain = model.dt_s / model.mass_kg * KN
            self._qps[full] = _QP(T, K, model.dt_s, 1.0 - model.friction, gain, params, soft)
        return self._qps[full]


# --------------------------------------------------------------------------- face assignment


def _opposite(f: np.ndarray, g: np.ndarray) -> np.ndarray:
    return (f >= 0) & (g >= 0) & ((f - g) % N_LATERAL == 2)


@dataclass(eq=False)
class _Geometry:
    """Everything about the obstacles that a face assignment needs, for one tick."""

    normals: np.ndarray  # (K, 4, 2)
    offsets: np.ndarray  # (K, 4), inflated
    relevant: np.ndarray  # (T-1, K) segment s = 1..T-1 may meet obstacle k (altitude overlap)

    def clearance(self, pts: np.ndarray) -> np.ndarray:
        """pts (P, 2) -> (P, K, 4): a . p - b, > 0 outside that face."""
        return np.einsum("kfd,pd->pkf", self.normals, pts) - self.offsets[None]

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
        faces = np.where(self.relevant, faces, _NO_FACE)
        for s in range(1, len(faces)):
            bad = _opposite(faces[s - 1], faces[s])
            for k in np.flatnonzero(bad):
                f = faces[s - 1, k]
                adj = np.array([(f + 1) % N_LATERAL, (f - 1) % N_LATERAL])
                faces[s, k] = adj[np.argmax(c[s + 1, k, adj])]
        return faces

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
        coef = np.zeros((K, Tm1, 2, 2))
        rhs = np.full((K, Tm1, 2), -np.inf)
        on = faces >= 0
        s_idx, k_idx = np.nonzero(on)
        f = faces[s_idx, k_idx]
        a = self.normals[k_idx, f]
        b = self.offsets[k_idx, f]
        for end in (0, 1):
            coef[k_idx, s_idx, end] = a
            rhs[k_idx, s_idx, end] = b
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
        """(S,) True where segment a[s] -> b[s] passes through any polygon's interior (Liang-Barsky)."""
        d = b - a
        num = self.offsets[None] - np.einsum("kfd,sd->skf", self.normals, a)
        den = np.einsum("kfd,sd->skf", self.normals, d)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / den
        t_in = np.maximum(np.where(den < 0, t, -np.inf).max(axis=-1), 0.0)
        t_out = np.minimum(np.where(den > 0, t, np.inf).min(axis=-1), 1.0)
        parallel_out = np.any((den == 0) & (num <= 0), axis=-1)
        return ((t_out - t_in > 1e-9) & ~parallel_out).any(axis=-1)

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

    def blocking(self, pts: np.ndarray) -> list[int]:
        """Obstacles the path pts passes through (a point inside or a segment crossing)."""
        c = self.clearance(pts)
        inside = np.all(c < 0, axis=-1).any(axis=0)
        # a segment crosses a convex polygon iff no face separates both end points and ... cheap
        # approximation enough for picking candidates: also test midpoints
        mid = 0.5 * (pts[1:] + pts[:-1])
        inside |= self.inside(mid).any(axis=0)
        return [int(k) for k in np.flatnonzero(inside)]


# --------------------------------------------------------------------------- the planner


def _reduce_obstacles(obstacles: Obstacles, margin: float, z: np.ndarray) -> _Geometry:
    inflated = obstacles.inflate(margin)
    normals, offsets, z_lo, z_hi = inflated.lateral()
    # segment s (p_s -> p_(s+1)) misses obstacle k vertically iff both ends are above or below it
    za, zb = z[1:-1, None], z[2:, None]
    above = (za >= z_hi[None]) & (zb >= z_hi[None])
    below = (za <= z_lo[None]) & (zb <= z_lo[None])
    return _Geometry(normals, offsets, ~(above | below))


def _timed(polyline: np.ndarray, p0: np.ndarray, step_m: float, T: int) -> np.ndarray:
    """p_0..p_T: p0, then points along the polyline (which starts at p_1) every step_m metres."""
    seg = np.linalg.norm(np.diff(polyline, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.minimum(np.arange(T) * step_m, arc[-1])
    pts = np.stack([np.interp(s, arc, polyline[:, d]) for d in range(2)], axis=1)
    return np.vstack([p0, pts])


def _integrate(x0: np.ndarray, w_kn: np.ndarray, dt: float, decay: float, gain: float) -> np.ndarray:
    """p_1..p_(T+1) (T+1, 2) from x0 = (px, py, vx, vy) under controls w (T, 2) in kN."""
    p, v = x0[:2].copy(), x0[2:].copy()
    out = []
    for w in w_kn:
        p = p + dt * v
        out.append(p)
        v = decay * v + gain * w
    out.append(p + dt * v)
    return np.array(out)


def _controls_kn(x0: np.ndarray, pts: np.ndarray, dt: float, decay: float, gain: float) -> np.ndarray:
    """Controls w_0..w_(T-1) (kN) that move the target through p_1..p_(T+1) (pts) from x0."""
    v = np.vstack([x0[2:], np.diff(pts, axis=0) / dt])  # v_0..v_T
    return (v[1:] - decay * v[:-1]) / gain


def plan_guidance(model: MotionModel, params: GuidanceParams, obstacles: Obstacles,
                  mean0: np.ndarray, goal: np.ndarray, previous: Plan | None = None,
                  workspace: GuidanceWorkspace | None = None, key=None,
                  timer: Callable[[], float] = time.perf_counter) -> Plan:
    """Solve P1 for one target from state mean0 (6,) toward goal centroid (3,).

    ``previous`` (this target's plan of the last tick) warm-starts the face assignment and is the
    fallback when no feasible plan is found. ``workspace``/``key`` cache the OSQP instances.
    """
    t_start = timer()
    T, K = params.horizon, len(obstacles)
    mean0 = np.asarray(mean0, dtype=float)
    goal2 = np.asarray(goal, dtype=float)[:2]
    ws = workspace or GuidanceWorkspace()
    hard = ws.qp(key, T, K, model, params, soft=False)
    soft = ws.qp(key, T, K, model, params, soft=True) if K else None
    decay, gain = 1.0 - model.friction, hard.gain
    solves = 0

    x0 = mean0[[0, 1, 3, 4]]
    v0 = float(np.linalg.norm(x0[2:]))
    speed_bound = np.maximum(params.speed_max_mps * np.cos(np.pi / params.speed_polygon_sides),
                             v0 * decay ** np.arange(1, T + 1) + 1e-6)
    z_path = predict_mean(model, mean0, np.zeros((T, 3)))[:, 2]
    geo = _reduce_obstacles(obstacles, params.obstacle_margin_m, np.concatenate([[mean0[2]], z_path]))

    def path(pts):
        """p_0..p_T from a QP's p_1..p_(T+1)."""
        return np.vstack([x0[:2], pts[:T]])

    def cost(pts):
        w = _controls_kn(x0, pts, model.dt_s, decay, gain)
        d2 = np.sum((pts[:T] - goal2) ** 2, axis=1)
        return float(hard.goal_weights @ d2 + params.smooth_weight * np.sum(np.diff(w, axis=0) ** 2))

    best = {"cost": np.inf, "pts": None, "faces": None, "duals": None}
    tried: set[bytes] = set()

    def budget_left():
        return solves < params.max_qp_solves

    def solve(qp, faces):
        nonlocal solves
        solves += 1
        return qp.solve(x0, goal2, speed_bound, *geo.rows(faces))

    def evaluate(faces):
        """Hard solve of an assignment; keep the best. Returns the result or None.

        The solution is re-integrated from its controls clipped to the input box, and checked
        again: what is kept is exactly what the dynamics do, within every bound.
        """
        tried.add(faces.tobytes())
        out = solve(hard, faces)
        if out is None or out[2] > _FEAS_TOL_M:
            return None
        w = np.clip(_controls_kn(x0, out[0], model.dt_s, decay, gain), -params.u_max_n / KN, params.u_max_n / KN)
        pts = _integrate(x0, w, model.dt_s, decay, gain)
        if geo.violation(faces, path(pts)) > _FEAS_TOL_M:
            return None
        speed = np.linalg.norm(np.diff(pts, axis=0) / model.dt_s, axis=1)
        if np.any(speed > np.maximum(params.speed_max_mps, speed_bound) + 1e-3):
            return None
        c = cost(pts)
        if c < best["cost"] - 1e-9 * max(1.0, abs(c)):
            best.update(cost=c, pts=pts, faces=faces, duals=out[1])
        return out

    def refine(faces):
        """Solve, re-pick faces by clearance, repeat until the assignment repeats.

        An infeasible assignment is solved once more with slack: its path shows where the
        faces should change, which the re-pick then reads.
        """
        while budget_left():
            out = evaluate(faces)
            if out is None:
                if soft is None or not budget_left():
                    return
                out = solve(soft, faces)
                if out is None:
                    return
            nxt = geo.repick(path(out[0]))
            if nxt.tobytes() in tried:
                return
            faces = nxt

    empty = np.full((T - 1, K), _NO_FACE)
    if K == 0:
        evaluate(empty)
    # 1. the previous plan, shifted by one step
    warm = False
    if K and previous is not None and previous.feasible and previous.faces.shape == (T - 1, K):
        shifted = np.vstack([previous.faces[1:], previous.faces[-1:]])
        prev_path = np.vstack([x0[:2], previous.means[1:, :2], previous.means[-1:, :2]])
        refine(geo.sanitise(shifted, prev_path))
        warm = best["pts"] is not None
    # 2. without one: the shortest path around the obstacles, timed at a cruise speed; the
    #    obstacle-free optimum, and copies of it pushed around blocking obstacles on either side
    if K and best["pts"] is None and budget_left():
        guide = geo.guide_path(x0[:2] + model.dt_s * x0[2:], goal2)
        if guide is not None:
            refine(geo.repick(_timed(guide, x0[:2], 0.8 * params.speed_max_mps * model.dt_s, T)))
    if K and best["pts"] is None and budget_left():
        free = solve(hard, empty)
        if free is not None:
            ref = path(free[0])
            variants = [ref]
            blocking = geo.blocking(ref)[:3]
            for sides in itertools.product((1.0, -1.0), repeat=len(blocking)):
                pts = ref
                for k, side in zip(blocking, sides):
                    pts = geo.push_around(pts, k, side)
                variants.append(pts)
            for pts in variants:
                faces = geo.repick(pts)
                if faces.tobytes() not in tried and budget_left():
                    refine(faces)

    # 3. local search: move face changes that carry an active constraint one step either way.
    #    Only when exploring: in the rolling horizon the shifted assignment has had it already,
    #    and each OSQP solve costs milliseconds of the 1 s tick.
    improved = best["pts"] is not None and not warm
    while improved and budget_left() and K:
        cost_before = best["cost"]
        faces0 = best["faces"]
        active = np.abs(best["duals"]).max(axis=-1).T > 1e-7  # (T-1, K)
        change = (faces0[1:] != faces0[:-1]) & (faces0[1:] >= 0) & (faces0[:-1] >= 0)
        for s, k in zip(*np.nonzero(change)):
            s += 1  # the face changes between segments s-1 and s
            if not (active[s - 1, k] or active[s, k]):
                continue
            for src, dst in ((s - 1, s), (s, s - 1)):
                f = faces0.copy()
                f[dst, k] = f[src, k]
                if _opposite(f[1:, k], f[:-1, k]).any() or f.tobytes() in tried or not budget_left():
                    continue
                evaluate(f)
        improved = best["cost"] < cost_before - 1e-9 * max(1.0, abs(cost_before))

    if best["pts"] is None:
        return _fallback(model, params, mean0, previous, K, timer() - t_start, solves)
    controls = np.zeros((T, 3))
    controls[:, :2] = _controls_kn(x0, best["pts"], model.dt_s, decay, gain) * KN
    status = "optimal" if budget_left() else "budget"
    return Plan(status, best["cost"], timer() - t_start, solves, controls,
                predict_mean(model, mean0, controls), best["faces"])


def _fallback(model, params, mean0, previous, K, elapsed, solves) -> Plan:
    T = params.horizon
    if previous is not None and previous.controls.shape == (T, 3):
        controls = np.vstack([previous.controls[1:], np.zeros((1, 3))])
        status = "fallback_previous"
    else:
        controls = np.zeros((T, 3))
        status = "fallback_coast"
    return Plan(status, float("nan"), elapsed, solves, controls, predict_mean(model, mean0, controls),
                np.full((T - 1, K), _NO_FACE))
