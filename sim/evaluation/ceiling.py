"""The clairvoyant ceiling: the UAV path that minimises the evaluation's PCRB, knowing the truth.

For one evaluation trial (the true target states, the closed-loop guidance gains, the UAV start),
find the path p_0..p_(K-1) of a vehicle at given limits that minimises the bound ``pmon eval``
reports as ``bound_m`` for it: the posterior Cramer-Rao bound of ``sim.evaluation.trials.pcrb_position``
(Tichavsky's recursion on [px, py, vx, vy] with the truth's closed-loop Jacobians F_k, process
noise Q, prior Sigma_0 and q h h^T / sigma^2 per tick from the UAV at p_k, q the information
reduction factor of p_D and clutter), averaged as the evaluation averages it:

    objective = mean over window ticks k >= w0 and targets j of sqrt(B_kj),   B = tr of the (x, y) block.

(For one trial this is ``bound_m`` of ``pmon eval --trials 1``; over trials the evaluation takes
sqrt of the trial mean first, ``aggregate_bound``.) The path is a clairvoyant lower bound on what
any planner with that vehicle and this sensor can reach, up to how well the search finds the
global minimum (``sim.evaluation.ceiling_search``: many starts, and an independent sampling search).

The vehicle (the flight planner's model, ``onboard.core.planning.routes.fly_routes``): a double integrator
with a constant acceleration through each tick, |a| <= a_max and |v| <= v_max at every tick (so
between ticks too), starting at rest at the start; it flies at the UAV's altitude, so it keeps
out of the obstacles it cannot overfly, inflated by the UAV's margin (``routes.blocking_2d``),
along the whole curved path, and inside the area.

The search (``sim.evaluation.ceiling_search``) works on the accelerations a_k (positions and velocities
are linear in them, ``Kinematics``), with the exact gradient of the objective (an adjoint pass of
the bound's recursion, ``objective_gradient``). Every result is flown through the saturating
dynamics (``fly``: speed and acceleration clipped, so always within the limits) and checked
densely against the area and obstacles (``check_path``): only checked paths count.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.core.planning.information import PLANAR, information_reduction_factor, planar_model
from onboard.core.obstacles import polygons_crossed
from onboard.core.planning.routes import blocking_2d

SUBSTEPS = 4  # points per tick where the penalties hold the curved path out of obstacles
CHECK_SUBSTEPS = 20  # points per tick of the final check (chords of <= 0.5 m at 9 m/s)
BUFFER_M = 0.5  # the penalties keep this clear of obstacles and the area's edge
SPEED_BUFFER = 1e-3  # relative: penalised above v_max (1 - this), a_max (1 - this)


@dataclass(frozen=True, eq=False)
class CeilingProblem:
    """One trial's bound and the vehicle's limits (SI; planar, mission ENU)."""

    targets: np.ndarray  # (K, M, 2) true positions at the ticks
    F: np.ndarray  # (K-1, M, 4, 4) closed-loop transition Jacobians
    Q: np.ndarray  # (4, 4) process noise
    J0: np.ndarray  # (4, 4) prior information Sigma_0^-1
    info_scale: float  # q / sigma^2 (1/rad^2)
    window_start: int
    start: np.ndarray  # (2,) p_0
    dt: float
    speed_max: float
    accel_max: float
    area_lo: np.ndarray  # (2,)
    area_hi: np.ndarray  # (2,)
    normals: np.ndarray  # (P, 4, 2) the blocking obstacles' lateral faces (inflated)
    offsets: np.ndarray  # (P, 4)

    @property
    def K(self) -> int:
        return self.targets.shape[0]

    def with_limits(self, speed_max: float, accel_max: float) -> "CeilingProblem":
        from dataclasses import replace
        return replace(self, speed_max=float(speed_max), accel_max=float(accel_max))


def problem_for_trial(setup, truth: np.ndarray, gains: np.ndarray, start: np.ndarray, window_start: int,
                      speed_max: float, accel_max: float, clutter_rate: float = 1.0) -> CeilingProblem:
    """The problem of one evaluation trial: ``setup`` a ``MonitorSetup`` of the scenario, truth
    (K, M, 6), gains (K-1, M, 3, 6) from ``sim.truth.world.simulate_truth(..., with_gains=True)``, the
    UAV's start (3,); the bound's q as the UAV methods' (p_D of the scenario, Lambda =
    ``clutter_rate``: 1 for every flown method of the evaluation)."""
    A, B, Q = planar_model(setup.model)
    K = truth.shape[0]
    G = np.asarray(gains, float)[:K - 1, :, :2][..., PLANAR]  # (K-1, M, 2, 4)
    F = A[None, None] + np.einsum("ij,kmjl->kmil", B, G)
    P0 = np.asarray(setup.initial_cov, float)[np.ix_(PLANAR, PLANAR)]
    sigma = setup.sensor.sigma_rad
    q = information_reduction_factor(setup.sensor.p_detect, clutter_rate, sigma)
    normals, offsets = blocking_2d(setup.uav_obstacles, setup.grid.altitude_m)
    return CeilingProblem(np.asarray(truth, float)[:, :, :2].copy(), F, Q, np.linalg.inv(P0), q / sigma**2,
                          int(window_start), np.asarray(start, float)[:2].copy(), setup.model.dt_s,
                          float(speed_max), float(accel_max), np.asarray(setup.area_min, float)[:2],
                          np.asarray(setup.area_max, float)[:2], normals, offsets)


# --------------------------------------------------------------------------- the bound


def _gradient_g(d: np.ndarray) -> np.ndarray:
    """bearing gradient g = (d_y, -d_x) / r^2 for d = target - sensor, as bearing_gradient."""
    r2 = np.maximum(np.sum(d * d, axis=-1, keepdims=True), 1e-6)
    return np.stack([d[..., 1], -d[..., 0]], axis=-1) / r2


def bound_m2(pb: CeilingProblem, paths: np.ndarray, keep: bool = False):
    """The PCRB of every target's position along each path: paths (B, K, 2) -> (B, K, M) m^2,
    ``sim.evaluation.trials.pcrb_position``'s figure for that path (to round-off: the same recursion in
    covariance form, where one bearing's information q h h^T / sigma^2 is a rank-one update,
    J^-1 = Pp - Pp h h^T Pp / (h^T Pp h + sigma^2 / q) with Pp = F P F^T + Q, so no inverse).
    keep: also the predicted covariances Pp_k, u_k = Pp_k h_k and s_k for the adjoint."""
    d = pb.targets[None] - paths[:, :, None, :]  # (B, K, M, 2)
    g = _gradient_g(d)
    Bn, K, M = g.shape[:3]
    c = 1.0 / pb.info_scale
    out = np.empty((Bn, K, M))
    if keep:
        Pp_all, u_all, s_all = np.empty((Bn, K, M, 4, 4)), np.empty((Bn, K, M, 4)), np.empty((Bn, K, M))
    P = np.broadcast_to(np.linalg.inv(pb.J0), (Bn, M, 4, 4))
    Ft = np.swapaxes(pb.F, -1, -2)
    for k in range(K):
        Pp = pb.F[k - 1] @ P @ Ft[k - 1] + pb.Q if k else P
        u = np.einsum("bmij,bmj->bmi", Pp[..., :2], g[:, k])
        s = np.einsum("bmi,bmi->bm", u[..., :2], g[:, k]) + c
        P = Pp - u[..., :, None] * u[..., None, :] / s[..., None, None]
        if keep:
            Pp_all[:, k], u_all[:, k], s_all[:, k] = Pp, u, s
        out[:, k] = P[..., 0, 0] + P[..., 1, 1]
    return (out, g, Pp_all, u_all, s_all) if keep else out


def window_bound(pb: CeilingProblem, b: np.ndarray) -> np.ndarray:
    """(B, K, M) m^2 -> (B,) the objective: mean over the window and targets of sqrt(B)."""
    return np.sqrt(b[:, pb.window_start:]).mean(axis=(1, 2))


def aggregate_bound(b_trials: np.ndarray, window_start: int) -> float:
    """``pmon eval``'s ``bound_m`` over trials: (N, K, M) m^2 -> the window mean of the
    target-averaged sqrt of the trial mean (``sim.evaluation.trials._bound_summary``)."""
    return float(np.sqrt(np.mean(b_trials, axis=0)).mean(axis=1)[window_start:].mean())


def objective_gradient(pb: CeilingProblem, paths: np.ndarray, weights: np.ndarray | None = None):
    """Objective (B,) and its gradient in the path positions (B, K, 2) (adjoint of the
    recursion). weights None: the window mean of sqrt(B) (``window_bound``); else (K, M): the
    linear sum over k, j of weights * B (the majoriser ``aggregate_bound`` is minimised through)."""
    b, g, Pp, u, s = bound_m2(pb, paths, keep=True)
    Bn, K, M = b.shape
    if weights is None:
        w = np.zeros((K, M))
        w[pb.window_start:] = 1.0 / ((K - pb.window_start) * M)
        f = window_bound(pb, b)
        direct = w[None] * 0.5 / np.sqrt(np.maximum(b, 1e-300))  # d f / d B
    else:
        f = np.einsum("km,bkm->b", weights, b)
        direct = np.broadcast_to(weights, b.shape)
    grad_g = np.empty_like(g)
    G = np.zeros((Bn, M, 4, 4))  # dL/dP_k (general, not symmetrised)
    for k in range(K - 1, -1, -1):
        G[..., 0, 0] += direct[:, k]
        G[..., 1, 1] += direct[:, k]
        uk, sk = u[:, k, ..., None], s[:, k][..., None, None]
        # P = Pp - u u^T / s, u = Pp h, s = h^T Pp h + c, h = (g, 0, 0)
        Gu = G @ uk
        du = -(Gu + np.swapaxes(G, -1, -2) @ uk) / sk  # (B, M, 4, 1)
        ds = (np.swapaxes(uk, -1, -2) @ Gu) / sk**2  # (B, M, 1, 1)
        dh = (Pp[:, k] @ du + 2 * ds * uk)[..., 0]
        grad_g[:, k] = dh[..., :2]
        if k:
            GPp = G.copy()
            gk = g[:, k, :, None, :]  # (B, M, 1, 2)
            GPp[..., :2] += du * gk
            GPp[..., :2, :2] += ds * np.swapaxes(gk, -1, -2) * gk
            G = np.swapaxes(pb.F[k - 1], -1, -2) @ GPp @ pb.F[k - 1]
    d = pb.targets[None] - paths[:, :, None, :]
    r2 = np.maximum(np.sum(d * d, axis=-1), 1e-6)
    dx, dy = d[..., 0], d[..., 1]
    u1, u2 = grad_g[..., 0], grad_g[..., 1]
    # d g / d d: g1 = dy / r2, g2 = -dx / r2
    ddx = u1 * (-2 * dx * dy / r2**2) + u2 * (-1 / r2 + 2 * dx * dx / r2**2)
    ddy = u1 * (1 / r2 - 2 * dy * dy / r2**2) + u2 * (2 * dx * dy / r2**2)
    grad_p = -np.stack([ddx, ddy], axis=-1).sum(axis=2)  # d = target - sensor
    return f, grad_p


# --------------------------------------------------------------------------- the vehicle


@dataclass(frozen=True, eq=False)
class Kinematics:
    """Linear maps from the accelerations a (B, K-1, 2) to the positions at the ticks (K) and at
    ``substeps`` points inside each tick ((K-1) * substeps + 1: the tick's start first, the last
    tick at the end), and to the velocities at the ticks; the vehicle starts at rest at p_0."""

    Lp: np.ndarray  # (K, K-1)
    Ls: np.ndarray  # ((K-1) S + 1, K-1)
    Lv: np.ndarray  # (K, K-1)

    @classmethod
    def create(cls, K: int, dt: float, substeps: int = SUBSTEPS) -> "Kinematics":
        k = np.arange(K)[:, None]
        lag = np.arange(K - 1)[None, :]
        Lp = np.where(lag < k, dt * dt * (k - lag - 0.5), 0.0)
        Lv = np.where(lag < k, dt, 0.0)
        s = np.arange(substeps) / substeps
        rows = []
        for i in range(K - 1):
            for f in s:
                rows.append(Lp[i] + f * dt * Lv[i] + np.where(lag[0] == i, 0.5 * (f * dt) ** 2, 0.0))
        rows.append(Lp[K - 1])
        return cls(Lp, np.array(rows), Lv)


def fly(pb: CeilingProblem, acc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vehicle asked for accelerations acc (B, K-1, 2): each tick's velocity change clipped
    to a_max dt, the new velocity to v_max (both projections onto discs, so the limits hold and
    a feasible sequence passes unchanged); constant acceleration through the tick. Returns the
    positions (B, K, 2) and the accelerations flown (B, K-1, 2)."""
    acc = np.asarray(acc, float)
    Bn, K1, _ = acc.shape
    p = np.empty((Bn, K1 + 1, 2))
    p[:, 0] = pb.start
    v = np.zeros((Bn, 2))
    flown = np.empty_like(acc)
    for k in range(K1):
        dv = acc[:, k] * pb.dt
        n = np.linalg.norm(dv, axis=1, keepdims=True)
        dv *= np.minimum(1.0, pb.accel_max * pb.dt / np.maximum(n, 1e-300))
        vn = v + dv
        s = np.linalg.norm(vn, axis=1, keepdims=True)
        vn *= np.minimum(1.0, pb.speed_max / np.maximum(s, 1e-300))
        flown[:, k] = (vn - v) / pb.dt
        p[:, k + 1] = p[:, k] + 0.5 * (v + vn) * pb.dt
        v = vn
    return p, flown


def clearance(pb: CeilingProblem, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point and blocking polygon: max_f (n_f . p - b_f) (> 0 outside) and the face (..., P)."""
    c = np.einsum("pfd,...d->...pf", pb.normals, pts) - pb.offsets
    f = np.argmax(c, axis=-1)
    return np.take_along_axis(c, f[..., None], axis=-1)[..., 0], f


def penalty_gradient(pb: CeilingProblem, kin: Kinematics, acc: np.ndarray, buffer_m: float = BUFFER_M):
    """Quadratic penalty (B,) of the limits, area and obstacles, and its gradient in acc."""
    Bn = acc.shape[0]
    grad = np.zeros_like(acc)
    pen = np.zeros(Bn)
    # acceleration
    n = np.linalg.norm(acc, axis=2)
    ex = np.maximum(n - pb.accel_max * (1 - SPEED_BUFFER), 0.0)
    pen += np.sum(ex**2, axis=1)
    grad += 2 * ex[..., None] * acc / np.maximum(n, 1e-12)[..., None]
    # speed at the ticks
    v = kin.Lv @ acc
    n = np.linalg.norm(v, axis=2)
    ex = np.maximum(n - pb.speed_max * (1 - SPEED_BUFFER), 0.0)
    pen += np.sum(ex**2, axis=1)
    grad += kin.Lv.T @ (2 * ex[..., None] * v / np.maximum(n, 1e-12)[..., None])
    # area and obstacles at the sub-steps
    pts = pb.start + kin.Ls @ acc  # (B, S, 2)
    lo = np.maximum(pb.area_lo + buffer_m - pts, 0.0)
    hi = np.maximum(pts - pb.area_hi + buffer_m, 0.0)
    pen += np.sum(lo**2 + hi**2, axis=(1, 2))
    gp = -2 * lo + 2 * hi
    if len(pb.offsets):
        c, f = clearance(pb, pts)  # (B, S, P)
        ex = np.maximum(buffer_m - c, 0.0)
        pen += np.sum(ex**2, axis=(1, 2))
        nrm = pb.normals[np.arange(len(pb.offsets))[None, None], f]  # (B, S, P, 2)
        gp += np.sum(-2 * ex[..., None] * nrm, axis=2)
    grad += kin.Ls.T @ gp
    return pen, grad


def check_path(pb: CeilingProblem, paths: np.ndarray, acc: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """(B,) True where the path flown with acc keeps every rule: p_0 the start, at rest; |a| <=
    a_max, |v| <= v_max at the ticks; the curved path, sampled CHECK_SUBSTEPS times a tick,
    inside the area and its chords through no blocking obstacle; the positions those of acc."""
    kin = kinematics(pb.K, pb.dt, CHECK_SUBSTEPS)
    ok = np.all(np.linalg.norm(acc, axis=2) <= pb.accel_max * (1 + tol), axis=1)
    ok &= np.all(np.linalg.norm(kin.Lv @ acc, axis=2) <= pb.speed_max * (1 + tol), axis=1)
    ok &= np.all(np.abs(pb.start + kin.Lp @ acc - paths) < 1e-6, axis=(1, 2))
    pts = pb.start + kin.Ls @ acc
    ok &= np.all((pts >= pb.area_lo - tol) & (pts <= pb.area_hi + tol), axis=(1, 2))
    for b in np.flatnonzero(ok):
        if len(pb.offsets) and polygons_crossed(pb.normals, pb.offsets, pts[b, :-1], pts[b, 1:]).any():
            ok[b] = False
    return ok


_KIN: dict = {}


def kinematics(K: int, dt: float, substeps: int = SUBSTEPS) -> Kinematics:
    key = (K, dt, substeps)
    if key not in _KIN:
        _KIN[key] = Kinematics.create(K, dt, substeps)
    return _KIN[key]
