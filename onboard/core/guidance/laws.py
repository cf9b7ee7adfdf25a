"""P1's first control as a map of the start state: the affine law of a plan around its start
(``LocalLaw``, for the tracker's reference steering) and the free optimum's linear maps
(``FreeLaw``, the tracker's free steering); docs/TRACKING.md."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from onboard.core.dynamics import PLANAR, MotionModel
from onboard.core.guidance.qp import KN, GuidanceWorkspace, QPSolution, controls_kn, speed_bound_mps
from onboard.core.obstacles import Obstacles

if TYPE_CHECKING:
    from onboard.core.guidance.params import GuidanceParams


def first_control_gain(dP: np.ndarray, model: MotionModel, decay: float, gain: float) -> np.ndarray | None:
    """du_0/dx (3, 6), N per state unit, from dp_(2..T+1)/dx0 (T, 2, 4); None if not finite."""
    dp1 = np.hstack([np.eye(2), model.dt_s * np.eye(2)])
    dv0 = np.hstack([np.zeros((2, 2)), np.eye(2)])
    dw0 = ((dP[0] - dp1) / model.dt_s - decay * dv0) / gain  # kN per unit of (px, py, vx, vy)
    if not np.all(np.isfinite(dw0)):
        return None
    out = np.zeros((3, 6))
    out[:2, [0, 1, 3, 4]] = dw0 * KN
    return out



def later_gains(dP: np.ndarray, model: MotionModel, decay: float, gain: float, steps: int) -> list[np.ndarray]:
    """du_k/dx_k (3, 6), N per state unit, for k = 1..steps: how the plan's k-th control moves with
    the state it starts from, x_k = (p_k, v_k), along the plans from nearby starts (dp_(2..T+1)/dx0
    (T, 2, 4), the active set held). By the principle of optimality the plan from x_k is the rest of
    this one, so this is the law of the plan shifted by k ticks (``Plan.shifted``). Where x_k does
    not move with x0 in every direction (an active set pins it: a target at a corner of its speed
    polygon), the gain of the control before it stands in (the law's own, for k = 1)."""
    dt = model.dt_s
    p = [np.hstack([np.eye(2), dt * np.eye(2)])] + [dP[i] for i in range(min(steps + 1, len(dP)))]  # dp_1, dp_2..
    v = [np.hstack([np.zeros((2, 2)), np.eye(2)])] + [(p[i + 1] - p[i]) / dt for i in range(len(p) - 1)]  # dv_0..
    out = [first_control_gain(dP, model, decay, gain)]
    for k in range(1, min(steps, len(v) - 2) + 1):
        dw = (v[k + 1] - decay * v[k]) / gain  # kN per unit of x0
        dx = np.vstack([p[k], v[k]])
        g = out[-1]
        if np.all(np.isfinite(dx)) and np.all(np.isfinite(dw)) and np.linalg.cond(dx) < 1e8:
            g = np.zeros((3, 6))
            g[:2, [0, 1, 3, 4]] = np.linalg.solve(dx.T, dw.T).T * KN
        out.append(g)
    return out[1:]


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
            ok_edge &= np.all(v2[:, 0::2] + v2[:, 1::2] <= speed_bound_mps(p) ** 2, axis=1)
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
    none_active = QPSolution(None, None, 0.0, None, np.zeros(qp.ny), np.zeros(len(qp.A_fixed)))
    dP = qp.sensitivity(x0, goal, speed, coef, rhs, none_active)  # (T, 2, 4): p_2..p_(T+1)
    # push the four unit states r = e_i through the path: p_1..p_(T+1), then speeds and controls
    basis = np.eye(4)
    pts = np.concatenate([(basis[:, :2] + model.dt_s * basis[:, 2:])[:, None], np.moveaxis(dP, 2, 0)], axis=1)
    speeds = (np.diff(pts, axis=1) / model.dt_s).reshape(4, -1)  # v_1..v_T
    controls = KN * np.stack([controls_kn(e, p, model.dt_s, 1.0 - model.friction, qp.gain)
                              for e, p in zip(basis, pts)]).reshape(4, -1)
    # a ball in a weighted norm of r inside which no input or speed row can bind (Cauchy-Schwarz
    # per row): most particles of a cloud near its goal skip the row-by-row check. Velocity is
    # weighted by 10 s: a cloud's velocity spread is about a tenth of its position spread (m/s, m)
    w = np.array([1.0, 1.0, 10.0, 10.0])
    r_u = params.u_max_n / np.max(np.linalg.norm(controls / w[:, None], axis=0))
    vt = (speeds / w[:, None]).reshape(4, T, 2)
    r_v = speed_bound_mps(params) / max(np.linalg.norm(vt[:, t].T, 2) for t in range(T))
    pw = (pts[:, :T] / w[:, None, None])
    reach = max(np.linalg.norm(pw[:, t].T, 2) for t in range(T))
    return FreeLaw(first_control_gain(dP, model, 1.0 - model.friction, qp.gain),
                   pts[:, :T].reshape(4, -1), speeds, controls, params, w, float(min(r_u, r_v)),
                   float(reach))

