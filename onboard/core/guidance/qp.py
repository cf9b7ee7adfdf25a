"""The convex QP of P1 for one face assignment (flat-output form, DAQP with OSQP behind it), and
the maps between a target's positions and its controls (docs/GUIDANCE.md, "How it is solved")."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Callable

import daqp
import numpy as np
import osqp
import scipy.sparse as sp
from scipy.linalg import cho_factor, cho_solve, solve_triangular

from onboard.core.dynamics import MotionModel, velocity_rollout

if TYPE_CHECKING:
    from onboard.core.guidance.params import GuidanceParams

KN = 1000.0  # the QP works in kilonewtons: keeps its numbers near unity


@dataclass(frozen=True, eq=False)
class ActiveRows:
    """Rows active at a QP solution: the constant rows (box, speed) and obstacle rows (K, T-1, 2)."""

    fixed: np.ndarray
    obstacles: np.ndarray

    def shifted(self, T: int) -> "ActiveRows":
        """The same rows one horizon step later: the next tick's warm start."""
        def shift(a):
            return np.concatenate([a[1:], a[-1:]])
        box, speed = self.fixed[:2 * T].reshape(T, 2), self.fixed[2 * T:].reshape(T, -1)
        obs = np.concatenate([self.obstacles[:, 1:], self.obstacles[:, -1:]], axis=1)
        return ActiveRows(np.concatenate([shift(box).ravel(), shift(speed).ravel()]), obs)


@dataclass(frozen=True, eq=False)
class QPSolution:
    pts: np.ndarray  # (T+1, 2) p_1..p_(T+1), m
    duals: np.ndarray  # (K, T-1, 2) obstacle rows
    violation: float  # m, largest obstacle-row violation (soft solves)
    active: ActiveRows
    y: np.ndarray  # the QP's solution (scaled units)
    lam: np.ndarray  # multipliers of every row of the QP (< 0: lower bound active, > 0: upper)


@dataclass(eq=False)
class AssignmentQP:
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
        p1, lo, hi, f = self._fixed_bounds(x0, goal, speed_bound)
        terms = (p1, lo, hi, f, self.Rinv.T @ f)
        self._start = (key, terms)
        return terms

    def _fixed_bounds(self, x0, goal, speed_bound):
        """p1, the fixed rows' lower and upper bounds, and the cost vector f, from the start."""
        L = self.L
        p1, Vc, Wc = self._fixed_terms(x0, goal)
        box = self.params.u_max_n / KN / L
        cv = np.einsum("kd,td->tk", self.speed_normals, Vc)
        lo = np.concatenate([(-box - Wc).reshape(-1), np.full(cv.size, -np.inf)])
        hi = np.concatenate([(box - Wc).reshape(-1), (speed_bound[:, None] / L - cv).reshape(-1)])
        return p1, lo, hi, self._cost_of(Wc)

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
              rhs: np.ndarray, soft: bool = False, hint: "ActiveRows | None" = None) -> "QPSolution | None":
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
        lo_tol, hi_tol = lo - self.TOL, hi + self.TOL
        lo_daqp, hi_daqp = np.where(np.isfinite(lo), lo, -1e30), np.where(np.isfinite(hi), hi, 1e30)
        for _ in range(self.MAX_ROUNDS):
            if w is not None:
                y = self.Rinv @ w
                r = np.concatenate([self.M_fixed @ w, c0 * y[col] + c1 * y[col + 1]])
                new = ((r < lo_tol) | (r > hi_tol)) & ~work
                if not new.any():
                    break
                work |= new
            idx = np.flatnonzero(work)
            fixed, obs = idx[idx < n_fixed], idx[idx >= n_fixed] - n_fixed
            rows = np.vstack([self.M_fixed[fixed], self._obstacle_rows(c[obs], j[obs], self.Rinv)])
            sense = np.where(idx >= n_fixed, 8, 0).astype(np.int32) if soft else None
            w_new, _, flag, info = daqp.solve(self.I, fw, rows, hi_daqp[idx], lo_daqp[idx], sense)
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
        return QPSolution(pts, duals, violation, ActiveRows(active[:n_fixed], obstacles), y, lam)

    def sensitivity(self, x0: np.ndarray, goal: np.ndarray, speed_bound: np.ndarray, coef: np.ndarray,
                    rhs: np.ndarray, sol: QPSolution) -> np.ndarray:
        """d p_(2..T+1) / d x0 (T, 2, 4) in m per unit of x0 = (px, py, vx, vy), with the active
        set of ``sol`` held fixed (the optimum is affine in x0 there): the KKT system
        [H A_a^T; A_a 0] [dy; dlam] = [-df; db] solved for the four directions of x0.
        The cost vector and every bound are affine in x0, so differences are exact; only the
        fixed rows' bounds depend on x0 (an obstacle row's difference is 0)."""
        _, lo, hi, _, c, j = self._bounds(x0, goal, speed_bound, coef, rhs)
        n_fixed = len(self.A_fixed)
        act = np.flatnonzero(sol.lam != 0.0)
        b0 = np.where(sol.lam[act] < 0, lo[act], hi[act])
        keep = np.isfinite(b0)  # a multiplier on an infinite bound is round-off, not a constraint
        act, b0 = act[keep], b0[keep]
        fixed, obs = act[act < n_fixed], act[act >= n_fixed] - n_fixed
        A_a = np.vstack([self.A_fixed[fixed], self._obstacle_rows(c[obs], j[obs], self.I)])
        lower = sol.lam[act] < 0
        f0 = self._cost_vector(x0, goal)
        df, db = [], []
        for i in range(4):
            x1 = x0.copy()
            x1[i] += 1.0
            _, lo1, hi1, f1 = self._fixed_bounds(x1, goal, speed_bound)
            b1 = b0.copy()  # the obstacle rows' bounds: those at x0
            b1[:len(fixed)] = np.where(lower[:len(fixed)], lo1[fixed], hi1[fixed])
            db.append(b1 - b0)
            df.append(f1 - f0)
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
        return self._cost_of(self._fixed_terms(x0, goal)[2])

    def _cost_of(self, Wc):
        """The cost vector f from the controls' constant part Wc (T, 2)."""
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
        self._qps: dict[tuple, AssignmentQP] = {}
        self._last: tuple | None = None  # (T, K, model, params, qp): the last lookup, by identity
        self._geometries: dict[tuple, Any] = {}

    def qp(self, T: int, K: int, model: MotionModel, params: GuidanceParams) -> AssignmentQP:
        last = self._last
        if last is not None and last[0] == T and last[1] == K and last[2] is model and last[3] is params:
            return last[4]
        # the search's limits do not change the QP: one cache entry whatever they are
        full = (T, K, model.dt_s, model.friction, model.mass_kg,
                replace(params, max_qp_solves=0, max_solve_time_s=None))
        if full not in self._qps:
            gain = model.dt_s / model.mass_kg * KN
            self._qps[full] = AssignmentQP(T, K, model.dt_s, 1.0 - model.friction, gain, params)
        self._last = (T, K, model, params, self._qps[full])
        return self._qps[full]

    def geometry(self, key: tuple, make: Callable[[], Any]) -> Any:
        """The face geometry of ``key`` (the obstacles, margins and altitudes it was made for; the
        obstacles by identity, held in the entry), made by ``make`` when not cached; the last 64."""
        entry = self._geometries.get(key[1:])
        if entry is not None and entry[0] is key[0]:
            return entry[1]
        if len(self._geometries) >= 64:
            self._geometries.clear()
        geo = make()
        self._geometries[key[1:]] = (key[0], geo)
        return geo



def integrate(x0: np.ndarray, w_kn: np.ndarray, dt: float, decay: float, gain: float) -> np.ndarray:
    """p_1..p_(T+1) (T+1, 2) from x0 = (px, py, vx, vy) under controls w (T, 2) in kN."""
    v = velocity_rollout(x0[2:], w_kn, decay, gain)
    return x0[:2] + dt * np.cumsum(np.vstack([x0[2:], v]), axis=0)


def controls_kn(x0: np.ndarray, pts: np.ndarray, dt: float, decay: float, gain: float) -> np.ndarray:
    """Controls w_0..w_(T-1) (kN) that move the target through p_1..p_(T+1) (pts) from x0."""
    v = np.vstack([x0[2:], np.diff(pts, axis=0) / dt])  # v_0..v_T
    return (v[1:] - decay * v[:-1]) / gain



def speed_bound_mps(params: GuidanceParams) -> float:
    """The speed polygon's inscribed radius, m/s: below it no speed row binds."""
    return params.speed_max_mps * np.cos(np.pi / params.speed_polygon_sides)

