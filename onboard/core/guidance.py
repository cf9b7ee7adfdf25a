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
from dataclasses import dataclass, field, replace
from typing import Callable

import daqp
import numpy as np
import osqp
import scipy.sparse as sp
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.sparse.csgraph import shortest_path

from onboard.core.dynamics import PLANAR, MotionModel, predict_mean, velocity_rollout
from onboard.core.obstacles import N_LATERAL, Obstacles, polygons_crossed

KN = 1000.0  # the QP works in kilonewtons: keeps its numbers near unity
_FEAS_TOL_M = 1e-3  # accept a QP solution whose obstacle rows are violated by less than this
_NO_FACE = -1
_PUSH_OUT_M = 0.01  # a start inside an inflated obstacle is planned from this far outside it
_STALL_SPEED_FRACTION = 0.25  # a warm plan against an obstacle this slow (of v_max) is stuck
_SWITCH_MOVES = (1, -1, 2, -2, 3, -3)  # local search: steps by which a face switch is moved
_GUIDE_SPEEDS = (0.8, 1.0, 0.6)  # fractions of v_max at which the shortest path is timed
_LOCAL_SEARCH_STARTS = 3  # local search from this many of the cheapest assignments found
_PAIR_MOVES = 4  # when no single move improves, pairs of this many cheapest ones are tried


@dataclass(frozen=True)
class GuidanceParams:
    """Problem P1's settings, each from the scenario (onboard/settings.py ``Guidance`` declares
    their defaults, units and ranges; no defaults here that could disagree)."""

    horizon: int
    u_max_n: float
    speed_max_mps: float
    speed_polygon_sides: int
    terminal_weight: float  # per m^2
    stage_weight: float  # per m^2
    smooth_weight: float  # per kN^2
    obstacle_margin_m: float
    max_qp_solves: int
    max_solve_time_s: float | None  # per plan; None: no limit (deterministic, for evaluation)

    @classmethod
    def from_config(cls, g) -> "GuidanceParams":
        return cls(g.horizon, g.u_max_n, g.speed_max_mps, g.speed_polygon_sides, g.terminal_weight,
                   g.stage_weight, g.smooth_weight, g.obstacle_margin_m, g.max_qp_solves,
                   g.max_solve_time_s)


@dataclass(frozen=True, eq=False)
class Plan:
    """A guidance solution for one target.

    ``status``: ``optimal`` (assignment stable, local search done), ``budget`` (best found when
    the QP budget ran out), ``timeout`` (best found when ``max_solve_time_s`` ran out),
    ``fallback_previous`` (no feasible plan: the previous plan shifted by one step) or ``fallback_coast`` (no feasible plan and none before: zero control, the target
    coasting under friction). ``cost`` is P1's objective (nan for fallbacks). ``margin_m``: the
    clearance from the obstacles the plan keeps: ``obstacle_margin_m``, or 0 where noise carried the
    target too close to an obstacle, or too fast toward it, for any plan to keep the margin.
    """

    status: str
    cost: float
    solve_time_s: float
    qp_solves: int
    controls: np.ndarray  # (T, 3) N, u_(t+tau|t)
    means: np.ndarray  # (T, 6) mu_(t+tau+1|t)
    faces: np.ndarray  # (T-1, K) lateral face per segment p_s -> p_(s+1), s = 1..T-1; -1: none
    active: "_Active | None" = None  # the QP rows active at the solution: next tick's warm start
    law: "LocalLaw | None" = None  # u_0 + du_0/dx (x - start) around the start (with_feedback=True)
    margin_m: float | None = None  # m; None when not set (plans built by hand)

    @property
    def feedback(self) -> np.ndarray | None:
        """(3, 6) du_0/dx, N per state unit (with_feedback=True), else None."""
        return None if self.law is None else self.law.gain

    @property
    def feasible(self) -> bool:
        return not self.status.startswith("fallback")

    @property
    def next_control(self) -> np.ndarray:
        return self.controls[0]

    @property
    def unconstrained(self) -> bool:
        """No row of P1 is active (no obstacle face, input or speed limit): the plan is the free
        optimum, which is affine in the state (``FreeLaw``). False when unknown."""
        return self.active is not None and not self.active.fixed.any() and not self.active.obstacles.any()

    @property
    def touches_obstacle(self) -> bool:
        """An obstacle row is active somewhere on the horizon: the plan rounds an obstacle, and a
        target could take another way around it. True when unknown (fallback plans)."""
        return self.active is None or bool(self.active.obstacles.any())


# --------------------------------------------------------------------------- the convex QP


@dataclass(frozen=True, eq=False)
class _Active:
    """Rows active at a QP solution: the constant rows (box, speed) and obstacle rows (K, T-1, 2)."""

    fixed: np.ndarray
    obstacles: np.ndarray

    def shifted(self, T: int) -> "_Active":
        """The same rows one horizon step later: the next tick's warm start."""
        def shift(a):
            return np.concatenate([a[1:], a[-1:]])
        box, speed = self.fixed[:2 * T].reshape(T, 2), self.fixed[2 * T:].reshape(T, -1)
        obs = np.concatenate([self.obstacles[:, 1:], self.obstacles[:, -1:]], axis=1)
        return _Active(np.concatenate([shift(box).ravel(), shift(speed).ravel()]), obs)


@dataclass(frozen=True, eq=False)
class _Solution:
    pts: np.ndarray  # (T+1, 2) p_1..p_(T+1), m
    duals: np.ndarray  # (K, T-1, 2) obstacle rows
    violation: float  # m, largest obstacle-row violation (soft solves)
    active: _Active
    y: np.ndarray  # the QP's solution (scaled units)
    lam: np.ndarray  # multipliers of every row of the QP (< 0: lower bound active, > 0: upper)


@dataclass(eq=False)
class _QP:
    """The convex QP of one face assignment, for a fixed horizon and obstacle count.

    Flat-output form: position is a flat output of the target model, so the decision variables
    are the positions y = [p_2 .. p_(T+1)] alone (p_1 = p_0 + dt v_0 is fixed). Velocities
    v_tau = (p_(tau+1) - p_tau) / dt and controls u_tau = m (v_(tau+1) - (1 - eps) v_tau) / dt are
    banded linear maps of y, so the QP has no equality constraints. Positions are relative to
    the goal, in units of L, which keeps the numbers near unity.

    Solver: DAQP, a dual active-set method made for small dense MPC problems, on a lazily grown
    working set of rows (start from the rows the unconstrained optimum violates, add the rows the
    last solution violates, repeat). At termination the solution satisfies every row and is
    optimal for a relaxation, so it is the optimum of the full QP; in practice 1-3 rounds of a
    few dozen rows each, out of about 1300. OSQP solves the same full QP when DAQP reports a
    numerical failure (never seen in the tests; counted in ``n_osqp``). docs/GUIDANCE.md has the
    measurements behind this choice (OSQP alone needed 300-4000 ADMM iterations per solve).

    ``soft=True`` makes every obstacle row soft (DAQP's soft constraints: a violation costs
    1/rho_soft per unit squared): always feasible, its solution only guides the face re-pick,
    the hard QP gives the answer.
    """

    T: int
    K: int
    dt: float
    decay: float  # 1 - friction
    gain: float  # m/s of velocity change per kN over one step
    params: GuidanceParams
    n_solves: int = field(init=False, default=0)
    _start: tuple | None = field(init=False, default=None, repr=False)
    n_osqp: int = field(init=False, default=0)

    L = 100.0  # m
    TOL = 1e-7  # row tolerance in units of L (1e-5 m)
    MAX_ROUNDS = 30

    def __post_init__(self):
        T, p = self.T, self.params
        self.ny = 2 * T
        # velocity v_tau (tau=1..T) = Vm @ y_axis + Vc; control w_tau (tau=0..T-1) = Wm @ y_axis + Wc
        Vm = (np.eye(T) - np.eye(T, k=-1)) / self.dt
        Wm = np.vstack([Vm[:1], Vm[1:] - self.decay * Vm[:-1]]) / self.gain
        self.DW = np.diff(Wm, axis=0)  # (T-1, T): w_tau - w_(tau-1)
        qw = np.full(T, p.stage_weight)
        qw[-1] = p.terminal_weight
        self.goal_weights = qw  # on p_1..p_T
        # cost / L^2 per axis: sum q_tau |p_tau|^2 (tau = 2..T) + r |DW y + dwc|^2; controls in
        # kN are w = L (Wm y + Wc) with y in units of L, so dividing by L^2 leaves r as it is
        Hax = 2.0 * (np.diag(np.concatenate([qw[1:], [0.0]])) + p.smooth_weight * self.DW.T @ self.DW)
        I2 = np.eye(2)
        self.H = np.kron(Hax, I2)  # variables interleaved (x, y) per point
        self.H_chol = cho_factor(self.H)
        # DAQP is handed the QP in whitened variables w = R y (H = R^T R): its Hessian is then the
        # identity, which it does not factor again on every call (10x faster, measured), and the
        # constant rows are whitened once here. Row values, bounds and duals are unchanged.
        R = np.triu(cho_factor(self.H, lower=False)[0])
        self.Rinv = solve_triangular(R, np.eye(self.ny))
        self.I = np.eye(self.ny)
        ang = 2 * np.pi * np.arange(p.speed_polygon_sides) / p.speed_polygon_sides
        self.speed_normals = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        # constant rows: control box (2T, per axis) then the speed polygon (sides x T)
        speed = np.einsum("tj,kd->tkjd", Vm, self.speed_normals).reshape(T * len(ang), 2 * T)
        self.A_fixed = np.vstack([np.kron(Wm, I2), speed])
        self.M_fixed = self.A_fixed @ self.Rinv
        self.n_box = 2 * T

    def _fixed_terms(self, x0: np.ndarray, goal: np.ndarray):
        """Constant parts of velocity and control maps, scaled, per axis: (Vc (T,2), Wc (T,2))."""
        L = self.L
        p1 = (x0[:2] + self.dt * x0[2:] - goal) / L
        v0 = x0[2:] / L
        Vc = np.zeros((self.T, 2))
        Vc[0] = -p1 / self.dt
        Wc = np.zeros((self.T, 2))
        Wc[0] = (Vc[0] - self.decay * v0) / self.gain
        Wc[1:] = (Vc[1:] - self.decay * Vc[:-1]) / self.gain
        return p1, Vc, Wc

    def _start_terms(self, x0, goal, speed_bound):
        """What depends only on the start, goal and speed bound (the same for every QP of one
        plan, so kept for the last start): p1, the fixed rows' bounds, the cost vector f and
        its whitened form Rinv^T f."""
        key = (x0.tobytes(), goal.tobytes(), speed_bound.tobytes())
        cached = self._start  # (key, terms), replaced in one assignment
        if cached is not None and cached[0] == key:
            return cached[1]
        L = self.L
        p1, Vc, Wc = self._fixed_terms(x0, goal)
        box = self.params.u_max_n / KN / L
        cv = np.einsum("kd,td->tk", self.speed_normals, Vc)
        lo = np.concatenate([(-box - Wc).reshape(-1), np.full(cv.size, -np.inf)])
        hi = np.concatenate([(box - Wc).reshape(-1), (speed_bound[:, None] / L - cv).reshape(-1)])
        f = self._cost_vector(x0, goal)
        terms = (p1, lo, hi, f, self.Rinv.T @ f)
        self._start = (key, terms)
        return terms

    def _bounds(self, x0, goal, speed_bound, coef, rhs):
        """Bounds of every row (fixed rows, then obstacle rows) and the obstacle rows' sparse form:
        p1, lower, upper (R,), obstacle index (k, s, end), coefficients (Ro, 2) on columns 2j, 2j+1."""
        p1, lo_fixed, hi_fixed, _, _ = self._start_terms(x0, goal, speed_bound)
        # obstacle rows: coef . p_tau >= rhs for segment s (1..T-1) and end tau = s, s+1; p_1 fixed
        k_i, s_i, e_i = np.nonzero(np.isfinite(rhs))
        c = coef[k_i, s_i, e_i]
        j = s_i + e_i - 1  # column pair of p_tau, tau = s_i + 1 + e_i (y holds p_2..p_(T+1))
        lo = np.concatenate([lo_fixed, (rhs[k_i, s_i, e_i] - c @ goal) / self.L])
        hi = np.concatenate([hi_fixed, np.full(len(k_i), np.inf)])
        return p1, lo, hi, (k_i, s_i, e_i), c, j

    @staticmethod
    def _obstacle_rows(c: np.ndarray, j: np.ndarray, basis: np.ndarray) -> np.ndarray:
        """Obstacle rows c0 y_(2j) + c1 y_(2j+1) as rows over ``basis`` (identity: y; Rinv: w)."""
        return c[:, :1] * basis[2 * j] + c[:, 1:] * basis[2 * j + 1]

    def _rows(self, x0, goal, speed_bound, coef, rhs):
        """Every row of the QP in y: A (R, 2T), lower, upper (R,) (for OSQP and the sensitivity)."""
        p1, lo, hi, _, c, j = self._bounds(x0, goal, speed_bound, coef, rhs)
        return p1, np.vstack([self.A_fixed, self._obstacle_rows(c, j, self.I)]), lo, hi

    def solve(self, x0: np.ndarray, goal: np.ndarray, speed_bound: np.ndarray, coef: np.ndarray,
              rhs: np.ndarray, soft: bool = False, hint: "_Active | None" = None) -> "_Solution | None":
        """x0 = (px, py, vx, vy); coef (K, T-1, 2, 2), rhs (K, T-1, 2) with -inf for rows off.

        ``hint``: rows active in a related solve (the previous assignment, or last tick's plan
        shifted), the first working set. None when the QP is infeasible (hard) or unsolved.
        """
        T, L = self.T, self.L
        self.n_solves += 1
        p1, lo, hi, obs_index, c, j = self._bounds(x0, goal, speed_bound, coef, rhs)
        c0, c1, col = c[:, 0], c[:, 1], 2 * j  # an obstacle row is c0 y[col] + c1 y[col + 1]
        n_fixed = len(self.A_fixed)
        _, _, _, f, fw = self._start_terms(x0, goal, speed_bound)  # min 1/2 |w|^2 + fw . w
        work = np.zeros(len(lo), dtype=bool)
        if hint is not None:
            work[:n_fixed] = hint.fixed
            work[n_fixed:] = hint.obstacles[obs_index]
        w = -fw if not work.any() else None
        lam = np.zeros(len(lo))
        for _ in range(self.MAX_ROUNDS):
            if w is not None:
                y = self.Rinv @ w
                r = np.concatenate([self.M_fixed @ w, c0 * y[col] + c1 * y[col + 1]])
                new = ((r < lo - self.TOL) | (r > hi + self.TOL)) & ~work
                if not new.any():
                    break
                work |= new
            idx = np.flatnonzero(work)
            fixed, obs = idx[idx < n_fixed], idx[idx >= n_fixed] - n_fixed
            rows = np.vstack([self.M_fixed[fixed], self._obstacle_rows(c[obs], j[obs], self.Rinv)])
            sense = np.where(idx >= n_fixed, 8, 0).astype(np.int32) if soft else None
            w_new, _, flag, info = daqp.solve(self.I, fw, rows, np.where(np.isfinite(hi[idx]), hi[idx], 1e30),
                                              np.where(np.isfinite(lo[idx]), lo[idx], -1e30), sense)
            if flag == -1 and not soft:
                return None  # infeasible: a relaxation already is
            if flag not in (1, 2):
                _, A, _, _ = self._rows(x0, goal, speed_bound, coef, rhs)
                y, lam = self._osqp(f, A, lo, hi)
                if y is None:
                    return None
                w = None
                break
            w = np.asarray(w_new)
            lam[:] = 0.0
            lam[idx] = info["lam"]
        if w is not None:
            y = self.Rinv @ w
        gap = lo[n_fixed:] - (c0 * y[col] + c1 * y[col + 1])
        pts = np.vstack([p1, y.reshape(T, 2)]) * L + goal
        violation = L * float(np.max(gap, initial=0.0))
        duals = np.zeros((self.K, T - 1, 2))
        duals[obs_index] = lam[n_fixed:]
        active = lam != 0.0
        obstacles = np.zeros((self.K, T - 1, 2), dtype=bool)
        obstacles[obs_index] = active[n_fixed:]
        return _Solution(pts, duals, violation, _Active(active[:n_fixed], obstacles), y, lam)

    def sensitivity(self, x0: np.ndarray, goal: np.ndarray, speed_bound: np.ndarray, coef: np.ndarray,
                    rhs: np.ndarray, sol: _Solution) -> np.ndarray:
        """d p_(2..T+1) / d x0 (T, 2, 4) in m per unit of x0 = (px, py, vx, vy), with the active
        set of ``sol`` held fixed (the optimum is affine in x0 there): the KKT system
        [H A_a^T; A_a 0] [dy; dlam] = [-df; db] solved for the four directions of x0.
        The cost vector and every bound are affine in x0, so differences are exact."""
        _, A, lo, hi = self._rows(x0, goal, speed_bound, coef, rhs)
        act = np.flatnonzero(sol.lam != 0.0)
        b0 = np.where(sol.lam[act] < 0, lo[act], hi[act])
        keep = np.isfinite(b0)  # a multiplier on an infinite bound is round-off, not a constraint
        act, b0 = act[keep], b0[keep]
        A_a = A[act]
        f0 = self._cost_vector(x0, goal)
        df, db = [], []
        for i in range(4):
            x1 = x0.copy()
            x1[i] += 1.0
            _, lo1, hi1, _, _, _ = self._bounds(x1, goal, speed_bound, coef, rhs)
            db.append(np.where(sol.lam[act] < 0, lo1[act], hi1[act]) - b0)
            df.append(self._cost_vector(x1, goal) - f0)
        df, db = np.column_stack(df), np.column_stack(db)
        # Schur complement on the (few) active rows, H's Cholesky factor cached: dy = -H^-1 (df +
        # A_a^T dlam), A_a dy = db. Dependent active rows make S singular: least squares there.
        Hi_df = cho_solve(self.H_chol, df)
        if len(act):
            Hi_At = cho_solve(self.H_chol, A_a.T)
            S = A_a @ Hi_At
            dlam = np.linalg.lstsq(S, -(db + A_a @ Hi_df), rcond=1e-10)[0]
            d = -(Hi_df + Hi_At @ dlam)
        else:
            d = -Hi_df
        return d.reshape(self.T, 2, 4) * self.L

    def _cost_vector(self, x0, goal):
        _, _, Wc = self._fixed_terms(x0, goal)
        return (2.0 * self.params.smooth_weight * self.DW.T @ np.diff(Wc, axis=0)).reshape(-1)

    def _osqp(self, f, A, lo, hi):
        """The same full QP on OSQP; (y, duals) or (None, None)."""
        self.n_osqp += 1
        solver = osqp.OSQP()
        solver.setup(sp.triu(sp.csc_matrix(self.H), format="csc"), f, sp.csc_matrix(A), lo, hi,
                     verbose=False, eps_abs=1e-6, eps_rel=1e-6, polishing=False, max_iter=20000)
        res = solver.solve(raise_error=False)
        if res.info.status_val not in (1, 2) or res.x is None or not np.all(np.isfinite(res.x)):
            return None, None
        return res.x, res.y


class GuidanceWorkspace:
    """Caches the QP matrices between ticks, per shape and model.

    Purely a performance cache: results do not depend on it.
    """

    def __init__(self):
        self._qps: dict[tuple, _QP] = {}

    def qp(self, T: int, K: int, model: MotionModel, params: GuidanceParams) -> _QP:
        # the search's limits do not change the QP: one cache entry whatever they are
        full = (T, K, model.dt_s, model.friction, model.mass_kg,
                replace(params, max_qp_solves=0, max_solve_time_s=None))
        if full not in self._qps:
            gain = model.dt_s / model.mass_kg * KN
            self._qps[full] = _QP(T, K, model.dt_s, 1.0 - model.friction, gain, params)
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
        faces = np.where(self.relevant, faces, _NO_FACE)
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
        return bool(np.all(np.einsum("cd,ced->ce", a, ends) - b[:, None] >= -_FEAS_TOL_M))

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


# --------------------------------------------------------------------------- the planner


def _reduce_obstacles(obstacles: Obstacles, margin: float, z: np.ndarray,
                      lateral_margin: float | None = None) -> _Geometry:
    """The obstacles inflated by ``margin`` (``lateral_margin`` sideways, when given) as seen by
    a path at altitudes z (T+1,)."""
    normals, offsets, z_lo, z_hi = obstacles.inflate(margin).lateral()
    if lateral_margin is not None:
        normals, offsets, _, _ = obstacles.inflate(lateral_margin).lateral()
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
    v = velocity_rollout(x0[2:], w_kn, decay, gain)
    return x0[:2] + dt * np.cumsum(np.vstack([x0[2:], v]), axis=0)


def _controls_kn(x0: np.ndarray, pts: np.ndarray, dt: float, decay: float, gain: float) -> np.ndarray:
    """Controls w_0..w_(T-1) (kN) that move the target through p_1..p_(T+1) (pts) from x0."""
    v = np.vstack([x0[2:], np.diff(pts, axis=0) / dt])  # v_0..v_T
    return (v[1:] - decay * v[:-1]) / gain


def _first_control_gain(dP: np.ndarray, model: MotionModel, decay: float, gain: float) -> np.ndarray | None:
    """du_0/dx (3, 6), N per state unit, from dp_(2..T+1)/dx0 (T, 2, 4); None if not finite."""
    dp1 = np.hstack([np.eye(2), model.dt_s * np.eye(2)])
    dv0 = np.hstack([np.zeros((2, 2)), np.eye(2)])
    dw0 = ((dP[0] - dp1) / model.dt_s - decay * dv0) / gain  # kN per unit of (px, py, vx, vy)
    if not np.all(np.isfinite(dw0)):
        return None
    out = np.zeros((3, 6))
    out[:2, [0, 1, 3, 4]] = dw0 * KN
    return out


@dataclass(frozen=True, eq=False)
class LocalLaw:
    """A plan's first control as an affine law of its start state: P1's optimum is affine in the
    start while the plan's active set (and face assignment) holds, u_0(x) = u_ref + gain (x - x_ref).
    Outside that region it is the plan's linearisation (how the tracker uses it: docs/TRACKING.md)."""

    x_ref: np.ndarray  # (4,) planar start (px, py, vx, vy) the plan was solved from, m and m/s
    u_ref: np.ndarray  # (3,) the plan's first control there, N
    gain: np.ndarray  # (3, 6) du_0/dx, N per state unit

    def controls(self, states: np.ndarray) -> np.ndarray:
        """(n, 3) first controls, N, from states (n, 6)."""
        dx = np.asarray(states, float)[:, PLANAR] - self.x_ref
        return self.u_ref + dx @ self.gain[:, PLANAR].T


@dataclass(frozen=True, eq=False)
class FreeLaw:
    """P1's optimum while none of its rows is active, as a map of the state. That optimum is
    linear in r = (p0 - goal, v0) (the QP is translation invariant and has no other constant
    term), and so are its whole path, speeds and controls: one set of maps serves every state and
    goal. Built once by ``free_law``."""

    gain: np.ndarray  # (3, 6) du_0/dx, N per state unit
    points: np.ndarray  # (4, 2T): p_1..p_T - goal = r @ points, m
    speeds: np.ndarray  # (4, 2T): v_1..v_T, m/s
    controls_map: np.ndarray  # (4, 2T): u_0..u_(T-1), N
    params: GuidanceParams
    scale: np.ndarray  # (4,) weights of r: within |scale * r| <= radius no input or speed row binds
    radius: float
    reach_gain: float  # |p_tau - goal| <= reach_gain * |scale * r| for every tau, m

    def controls(self, states: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """(n, 3) first controls u_0, N, of the free optimum from states (n, 6) toward goal (3,)."""
        rel = np.asarray(states, float).copy()
        rel[:, :2] -= np.asarray(goal, float)[:2]
        return rel @ self.gain.T

    def is_optimal(self, states: np.ndarray, goal: np.ndarray, obstacles: Obstacles,
                   u0: np.ndarray | None = None) -> np.ndarray:
        """(n,) bool: the free optimum from each state is feasible for P1, hence P1's optimum
        (it is optimal for the relaxation without constraints): every control inside the input
        box, every speed inside the polygon's inscribed circle (conservative), and every segment
        p_s -> p_(s+1), s = 1..T-1, outside one face of each inflated obstacle at the state's
        altitude, as P1 demands. Where True, ``controls`` is what the guidance commands.
        ``u0``: ``controls(states, goal)`` when the caller has it already."""
        p, T = self.params, self.params.horizon
        u_max = p.u_max_n * (1 + 1e-9)
        u0 = self.controls(states, goal) if u0 is None else u0
        ok = np.all(np.abs(u0[:, :2]) <= u_max, axis=1)
        cand = np.flatnonzero(ok)  # u_0 outside the box rules out most states cheaply
        if not len(cand):
            return ok
        goal2 = np.asarray(goal, float)[:2]
        rel = np.asarray(states, float)[cand][:, PLANAR]
        rel[:, :2] -= goal2
        sub = np.ones(len(cand), dtype=bool)
        size = np.linalg.norm(rel * self.scale, axis=1)
        edge = np.flatnonzero(size > self.radius)  # the others pass
        if len(edge):
            r = rel[edge]
            ok_edge = np.all(np.abs(r @ self.controls_map) <= u_max, axis=1)
            v2 = (r @ self.speeds) ** 2  # (n, 2T): vx, vy interleaved
            ok_edge &= np.all(v2[:, 0::2] + v2[:, 1::2] <= _speed_bound_mps(p) ** 2, axis=1)
            sub[edge] = ok_edge
        if len(obstacles) and sub.any():
            normals, offsets, z_lo, z_hi = obstacles.inflate(p.obstacle_margin_m).lateral()
            z = float(np.mean(np.asarray(states, float)[cand, 2]))
            near = (z_lo <= z) & (z <= z_hi)
            normals, offsets = normals[near], offsets[near] - normals[near] @ goal2  # goal-relative
            # a path stays within reach_gain * size of the goal: an obstacle one of whose faces has
            # the goal that far outside it has the whole path outside that face, every segment OK
            gap = (-offsets).max(axis=1)  # the goal's largest clearance over each obstacle's faces
            check = np.flatnonzero(sub & (self.reach_gain * size[:, None] >= gap[None]).any(axis=1))
            if len(check):
                k = gap <= self.reach_gain * size[check].max()  # the obstacles any of them can reach
                normals, offsets = normals[k], offsets[k]
                pts = (rel[check] @ self.points).reshape(-1, T, 2)
                out = (pts @ normals.reshape(-1, 2).T).reshape(len(check), T, -1, 4) > offsets  # outside
                sub[check] = np.all(np.any(out[:, :-1] & out[:, 1:], axis=-1), axis=(1, 2))
        ok[cand] = sub
        return ok


def free_law(model: MotionModel, params: GuidanceParams, workspace: GuidanceWorkspace | None = None) -> FreeLaw:
    """P1's unconstrained optimum as linear maps (``FreeLaw``); its ``gain`` is how the guidance
    steers a state that deviates a little from the planned one, away from obstacles and limits."""
    ws = workspace or GuidanceWorkspace()
    T = params.horizon
    qp = ws.qp(T, 0, model, params)
    x0, goal = np.zeros(4), np.zeros(2)
    speed = np.full(T, np.inf)
    coef, rhs = np.zeros((0, T - 1, 2, 2)), np.zeros((0, T - 1, 2))
    none_active = _Solution(None, None, 0.0, None, np.zeros(qp.ny), np.zeros(len(qp.A_fixed)))
    dP = qp.sensitivity(x0, goal, speed, coef, rhs, none_active)  # (T, 2, 4): p_2..p_(T+1)
    # push the four unit states r = e_i through the path: p_1..p_(T+1), then speeds and controls
    basis = np.eye(4)
    pts = np.concatenate([(basis[:, :2] + model.dt_s * basis[:, 2:])[:, None], np.moveaxis(dP, 2, 0)], axis=1)
    speeds = (np.diff(pts, axis=1) / model.dt_s).reshape(4, -1)  # v_1..v_T
    controls = KN * np.stack([_controls_kn(e, p, model.dt_s, 1.0 - model.friction, qp.gain)
                              for e, p in zip(basis, pts)]).reshape(4, -1)
    # a ball in a weighted norm of r inside which no input or speed row can bind (Cauchy-Schwarz
    # per row): most particles of a cloud near its goal skip the row-by-row check. Velocity is
    # weighted by 10 s: a cloud's velocity spread is about a tenth of its position spread (m/s, m)
    w = np.array([1.0, 1.0, 10.0, 10.0])
    r_u = params.u_max_n / np.max(np.linalg.norm(controls / w[:, None], axis=0))
    vt = (speeds / w[:, None]).reshape(4, T, 2)
    r_v = _speed_bound_mps(params) / max(np.linalg.norm(vt[:, t].T, 2) for t in range(T))
    pw = (pts[:, :T] / w[:, None, None])
    reach = max(np.linalg.norm(pw[:, t].T, 2) for t in range(T))
    return FreeLaw(_first_control_gain(dP, model, 1.0 - model.friction, qp.gain),
                   pts[:, :T].reshape(4, -1), speeds, controls, params, w, float(min(r_u, r_v)),
                   float(reach))


def _speed_bound_mps(params: GuidanceParams) -> float:
    """The speed polygon's inscribed radius, m/s: below it no speed row binds."""
    return params.speed_max_mps * np.cos(np.pi / params.speed_polygon_sides)


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


def plan_guidance(model: MotionModel, params: GuidanceParams, obstacles: Obstacles,
                  mean0: np.ndarray, goal: np.ndarray, previous: Plan | None = None,
                  workspace: GuidanceWorkspace | None = None,
                  timer: Callable[[], float] = time.perf_counter, with_feedback: bool = False,
                  sides: np.ndarray | None = None, strict_sides: bool = False) -> Plan:
    """Solve P1 for one target from state mean0 (6,) toward goal centroid (3,).

    ``previous`` (this target's plan of the last tick) warm-starts the face assignment and is the
    fallback when no feasible plan is found. ``workspace`` caches the QP matrices.
    ``with_feedback``: also compute ``Plan.feedback``, the closed-loop gain du_0/dx (for the
    posterior Cramer-Rao bound of a target that steers by this guidance) and ``Plan.law`` (for
    the tracker's ``plan_steering``).
    ``sides`` (K,): the best plan that rounds no obstacle k the other way than counterclockwise
    (+1) or clockwise (-1) (0: either); ``strict_sides``: that does round each of them that way
    (``in_class``; the tracker's ``plan_sides``).
    """
    t_start = timer()
    plan = _search(model, params, obstacles, mean0, goal, previous, workspace, timer, with_feedback, sides,
                   strict_sides, params.obstacle_margin_m)
    left = None if params.max_solve_time_s is None else t_start + params.max_solve_time_s - timer()
    if plan.feasible or not len(obstacles) or params.obstacle_margin_m <= 0.0 or (left is not None and left <= 0):
        return plan
    # noise has carried the target so close to an obstacle, or so fast toward it, that no control
    # keeps the margin: it keeps clear of the obstacle itself (the margin stays vertical, which
    # keeps ground targets level with the obstacles' bases)
    retry = _search(model, replace(params, max_solve_time_s=left), obstacles, mean0, goal, previous, workspace,
                    timer, with_feedback, sides, strict_sides, 0.0)
    return replace(retry, solve_time_s=timer() - t_start, qp_solves=plan.qp_solves + retry.qp_solves)


def _search(model: MotionModel, params: GuidanceParams, obstacles: Obstacles, mean0: np.ndarray,
            goal: np.ndarray, previous: Plan | None, workspace: GuidanceWorkspace | None,
            timer: Callable[[], float], with_feedback: bool, sides: np.ndarray | None, strict_sides: bool,
            lateral_margin_m: float) -> Plan:
    """``plan_guidance``'s search with the obstacles inflated by ``lateral_margin_m`` sideways."""
    t_start = timer()
    T, K = params.horizon, len(obstacles)
    mean0 = np.asarray(mean0, dtype=float)
    goal2 = np.asarray(goal, dtype=float)[:2]
    ws = workspace or GuidanceWorkspace()
    qp = ws.qp(T, K, model, params)
    decay, gain = 1.0 - model.friction, qp.gain
    solves = 0

    x0 = mean0[[0, 1, 3, 4]]
    z_path = predict_mean(model, mean0, np.zeros((T, 3)))[:, 2]
    geo = _reduce_obstacles(obstacles, params.obstacle_margin_m, np.concatenate([[mean0[2]], z_path]),
                            lateral_margin_m)
    # a start inside an inflated obstacle (noise carried the target into the margin, or an
    # estimate averages particles on both sides of an obstacle) has no feasible plan: plan from
    # the nearest point just outside, not moving into the obstacle
    out = geo.push_out(x0, geo.relevant[0]) if K else None
    if out is not None:
        mean0 = mean0.copy()
        mean0[[0, 1, 3, 4]] = x0 = out
    v0 = float(np.linalg.norm(x0[2:]))
    speed_bound = np.maximum(_speed_bound_mps(params),
                             v0 * decay ** np.arange(1, T + 1) + 1e-6)

    def path(pts):
        """p_0..p_T from a QP's p_1..p_(T+1)."""
        return np.vstack([x0[:2], pts[:T]])

    def cost(pts):
        w = _controls_kn(x0, pts, model.dt_s, decay, gain)
        d2 = np.sum((pts[:T] - goal2) ** 2, axis=1)
        return float(qp.goal_weights @ d2 + params.smooth_weight * np.sum(np.diff(w, axis=0) ** 2))

    best = {"cost": np.inf, "pts": None, "faces": None, "duals": None, "active": None, "sol": None}
    tried: set[bytes] = set()
    found: list[tuple[float, np.ndarray, np.ndarray]] = []  # every feasible (cost, faces, path)
    # first working set of the QP: last tick's active rows shifted, then each solve's own
    hint = [previous.active.shifted(T) if previous is not None and previous.active is not None
            and previous.faces.shape == (T - 1, K) else None]

    deadline = None if params.max_solve_time_s is None else t_start + params.max_solve_time_s

    def timed_out():
        return deadline is not None and timer() >= deadline

    def budget_left():
        return solves < params.max_qp_solves and not timed_out()

    def solve(faces, soft=False):
        nonlocal solves
        solves += 1
        out = qp.solve(x0, goal2, speed_bound, *geo.rows(faces), soft=soft, hint=hint[0])
        if out is not None:
            hint[0] = out.active
        return out

    def evaluate(faces):
        """Hard solve of an assignment; keep the best. Returns the result or None.

        The solution is re-integrated from its controls clipped to the input box, and checked
        again: what is kept is exactly what the dynamics do, within every bound.
        """
        tried.add(faces.tobytes())
        out = solve(faces)
        if out is None or out.violation > _FEAS_TOL_M:
            return None
        w = np.clip(_controls_kn(x0, out.pts, model.dt_s, decay, gain), -params.u_max_n / KN, params.u_max_n / KN)
        pts = _integrate(x0, w, model.dt_s, decay, gain)
        if geo.violation(faces, path(pts)) > _FEAS_TOL_M:
            return None
        # the speed rows the QP imposed, the polygon of apothem speed_bound: its corners lie
        # outside a circle of that radius, which a 2-norm check would reject whenever the bound
        # is relaxed above speed_max's (a target faster than speed_max / (1 - friction))
        vel = np.diff(pts, axis=0) / model.dt_s
        if np.any(vel @ qp.speed_normals.T > speed_bound[:, None] + 1e-3):
            return None
        c = cost(pts)
        if not in_class(faces, sides, strict_sides):
            return out  # its path still guides the re-pick
        found.append((c, faces, pts))
        if c < best["cost"] - 1e-9 * max(1.0, abs(c)):
            best.update(cost=c, pts=pts, faces=faces, duals=out.duals, active=out.active, sol=out)
        return out

    def refine(faces):
        """Solve, re-pick faces by clearance, repeat until the assignment repeats.

        An infeasible assignment is solved once more with slack: its path shows where the
        faces should change, which the re-pick then reads.
        """
        while budget_left():
            out = evaluate(faces)
            feasible = out is not None
            if not feasible:
                if K == 0 or not budget_left():
                    return
                out = solve(faces, soft=True)
                if out is None:
                    return
            pts = path(out.pts)
            nxt = geo.repick(pts)
            if nxt.tobytes() in tried or (feasible and geo.same_optimum(faces, nxt, pts, out.duals)):
                return
            faces = nxt

    def hold_assignment():
        """Every obstacle kept, for every segment, on the face p_1 is outside of: the target
        does not pass any obstacle within the horizon."""
        still = np.tile(x0[:2] + model.dt_s * x0[2:], (T + 1, 1))
        return geo.sanitise(np.broadcast_to(geo.repick(still)[:1], (T - 1, K)).copy(), still)

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
    # 2. the shortest path around the obstacles, timed at a cruise speed; the obstacle-free
    #    optimum, and copies of it pushed around the blocking obstacles on either side (the
    #    shortest path can be the dearer side given the initial velocity); holding back. All of
    #    it for a plan from scratch. A warm plan with no obstacle row active solves a relaxation
    #    of every assignment, so it is globally optimal. A warm plan that is stuck (an obstacle
    #    row active and the target planned to crawl, less than a quarter of v_max, at its first
    #    step: a shifted assignment can hold a target pressed against a face, a local optimum
    #    seen with T1 against O3) gets a light search: the shortest path at one speed and
    #    holding back, a handful of QPs.
    pressed = best["duals"] is not None and bool(np.any(best["duals"] != 0.0))
    first_speed = float(np.linalg.norm(best["pts"][1] - best["pts"][0])) / model.dt_s if warm else 0.0
    stalled = warm and pressed and first_speed < _STALL_SPEED_FRACTION * params.speed_max_mps
    explore = not warm
    if K and budget_left() and (explore or stalled):
        start = x0[:2] + model.dt_s * x0[2:]
        guides = [geo.guide_path(start, goal2)]
        if sides is not None and explore:  # the class's own shortest path first
            guides.insert(0, geo.guide_path_around(start, goal2, sides))
        for guide in guides:
            if guide is None:
                continue
            for speed in _GUIDE_SPEEDS if explore else _GUIDE_SPEEDS[:1]:
                faces = geo.repick(_timed(guide, x0[:2], speed * params.speed_max_mps * model.dt_s, T))
                if faces.tobytes() not in tried and budget_left():
                    refine(faces)
    if K and budget_left() and explore:
        free = solve(empty)
        if free is not None:
            ref = path(free.pts)
            variants = [ref]
            blocking = geo.blocking(ref)[:3]
            for way in itertools.product((1.0, -1.0), repeat=len(blocking)):
                pts = ref
                for k, side in zip(blocking, way):
                    pts = geo.push_around(pts, k, side)
                variants.append(pts)
            for pts in variants:
                faces = geo.repick(pts)
                if faces.tobytes() not in tried and budget_left():
                    refine(faces)
        # holding back, alone, and for each obstacle in the best assignment so far
        hold = hold_assignment()
        holds = [hold]
        if best["faces"] is not None:
            for k in range(K):
                f = best["faces"].copy()
                f[:, k] = np.where(f[:, k] >= 0, hold[:, k], f[:, k])
                holds.append(geo.sanitise(f, path(best["pts"])))
        for faces in holds:
            if faces.tobytes() not in tried and budget_left():
                refine(faces)
    elif K and budget_left() and stalled:
        hold = hold_assignment()
        if hold.tobytes() not in tried:
            refine(hold)

    # 3. local search: move each face switch one to three steps either way (the switch between
    #    two faces happens where the path rounds a corner; its best step is what the re-pick by
    #    clearance guesses least well), and all switches together; descend while it improves.
    #    From the best few assignments found, not only the best: the cheapest homotopy class can
    #    start out dearer before its switch times are right. Only when exploring: a warm plan's
    #    switches were searched when it was found.
    def neighbours(faces0, pts0):
        change = (faces0[1:] != faces0[:-1]) & (faces0[1:] >= 0) & (faces0[:-1] >= 0)
        for s, k in zip(*np.nonzero(change)):
            s += 1  # the face changes between segments s-1 and s
            before, after = faces0[s - 1, k], faces0[s, k]
            for d in _SWITCH_MOVES:
                f = faces0.copy()
                # past either end of the horizon the switch disappears
                seg = np.arange(s, min(s + d, len(f))) if d > 0 else np.arange(max(s + d, 0), s)
                if np.any(f[seg, k] != (after if d > 0 else before)):
                    continue  # runs into another switch
                f[seg, k] = before if d > 0 else after
                if not _opposite(f[1:, k], f[:-1, k]).any():
                    yield f
        for d in _SWITCH_MOVES:
            f = _shift_switches(faces0, d)
            if f is not None:
                yield geo.sanitise(f, path(pts0))

    def descend(c, faces, pts):
        while budget_left():
            n_found = len(found)
            for f in neighbours(faces, pts):
                if f.tobytes() not in tried and budget_left():
                    evaluate(f)
            better = [x for x in found[n_found:] if x[0] < c - 1e-9 * max(1.0, abs(c))]
            if not better:
                # switch times interact (rounding one corner later can pay only if the next
                # switch goes too): combine pairs of the cheapest feasible single moves
                near = sorted(found[n_found:], key=lambda x: x[0])[:_PAIR_MOVES]
                for (_, f1, _), (_, f2, _) in itertools.combinations(near, 2):
                    d1, d2 = f1 != faces, f2 != faces
                    if np.any(d1 & d2):
                        continue
                    f = np.where(d1, f1, np.where(d2, f2, faces))
                    if f.tobytes() not in tried and budget_left():
                        evaluate(f)
                better = [x for x in found[n_found:] if x[0] < c - 1e-9 * max(1.0, abs(c))]
                if not better:
                    return
            c, faces, pts = min(better, key=lambda x: x[0])

    if explore and K:
        starts, seen = [], set()
        for c, faces, pts in sorted(found, key=lambda x: x[0]):
            if faces.tobytes() not in seen:
                seen.add(faces.tobytes())
                starts.append((c, faces, pts))
        for c, faces, pts in starts[:_LOCAL_SEARCH_STARTS]:
            descend(c, faces, pts)

    if best["pts"] is None:
        return _fallback(model, params, mean0, previous, K, timer() - t_start, solves)
    controls = np.zeros((T, 3))
    controls[:, :2] = _controls_kn(x0, best["pts"], model.dt_s, decay, gain) * KN
    status = "optimal" if budget_left() else ("timeout" if timed_out() else "budget")
    law = None
    if with_feedback and np.all(np.isfinite(best["sol"].y)):
        # the closed-loop gain du_0/dx of this plan: the optimum is affine in the state while
        # its active set holds, so a nearby state would be steered by u_0 + K dx (about 3 ms)
        try:
            dP = qp.sensitivity(x0, goal2, speed_bound, *geo.rows(best["faces"]), best["sol"])
        except np.linalg.LinAlgError:
            dP = np.full((T, 2, 4), np.nan)
        feedback = _first_control_gain(dP, model, decay, gain)
        if feedback is not None:
            law = LocalLaw(x0.copy(), controls[0].copy(), feedback)
    return Plan(status, best["cost"], timer() - t_start, solves, controls,
                predict_mean(model, mean0, controls), best["faces"], best["active"], law, lateral_margin_m)


def _shift_switches(faces: np.ndarray, d: int) -> np.ndarray | None:
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
