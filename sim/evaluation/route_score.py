"""The lookahead planner's route score checked two ways: against a particle rollout of the same
routes (bench/route_score.py; the method is in its docstring), and as a forward pass with an
adjoint gradient in the route's positions (bench/route_variants.py --refine)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from onboard.core.bearings import bearing, wrap
from onboard.core.dynamics import PLANAR
from onboard.core.planning.information import information_reduction_factor, planar_model
from onboard.core.monitor import MonitorSetup
from onboard.core.tracking.filter import systematic_indices
from sim.evaluation.closed_loop import closed_loop


@dataclass(frozen=True)
class RolloutModel:
    """What a particle rollout moves and weighs its particles by: the planar motion model
    (``A``, ``Q``: 4 x 4) and the bearing's noise (``sigma_rad``) with the information
    reduction factor of detection and clutter (``reduction``)."""

    A: np.ndarray
    Q: np.ndarray
    sigma_rad: float
    reduction: float


def particle_route_scores(particles: np.ndarray, log_weights: np.ndarray, plans: np.ndarray,
                          routes: np.ndarray, model: RolloutModel, rng: np.random.Generator) -> np.ndarray:
    """Sum over the horizon of the weighted position variance of each target's particle cloud,
    per route and target: (C, M).

    particles (M, N, 4) planar, log_weights (M, N): the predicted beliefs at t+1; plans (M, H, 4):
    mu_(t+1..t+H); routes (C, H, 2): the sensor's positions at t+1..t+H.
    """
    A, Q, sigma_rad, reduction = model.A, model.Q, model.sigma_rad, model.reduction
    M, N, _ = particles.shape
    C, H, _ = routes.shape
    x = np.broadcast_to(particles, (C, M, N, 4)).copy()
    logw = np.broadcast_to(log_weights - logsumexp(log_weights, axis=1, keepdims=True), (C, M, N)).copy()
    L = np.linalg.cholesky(Q + 1e-12 * np.eye(4))
    total = np.zeros((C, M))
    for k in range(H):
        if k:  # linear about the plan, the same noise for every route (common random numbers)
            w = rng.standard_normal((M, N, 4)) @ L.T
            x = plans[None, :, k, None] + (x - plans[None, :, k - 1, None]) @ A.T + w[None]
        s = routes[:, None, k]  # (C, 1, 2)
        z = bearing(plans[None, :, k, :2], s)  # (C, M) ideal bearings to the planned positions
        pred = bearing(x[..., :2], s[:, :, None])  # (C, M, N)
        logw += -0.5 * reduction * (wrap(z[..., None] - pred) / sigma_rad) ** 2
        logw -= logsumexp(logw, axis=2, keepdims=True)
        wt = np.exp(logw)
        m1 = np.einsum("cmn,cmnd->cmd", wt, x[..., :2])
        m2 = np.einsum("cmn,cmnd->cmd", wt, x[..., :2] ** 2)
        total += np.sum(m2 - m1 ** 2, axis=2)
        ess = 1.0 / np.sum(wt ** 2, axis=2)  # (C, M)
        xf, lf, wf = x.reshape(C * M, N, 4), logw.reshape(C * M, N), wt.reshape(C * M, N)  # views
        for r in np.flatnonzero(ess.ravel() < 0.5 * N):
            xf[r] = xf[r][systematic_indices(wf[r], rng)]
            lf[r] = -np.log(N)
    return total


def snapshots(setup: MonitorSetup, ticks: set[int], seed: int, start_xy=(150.0, 200.0)):
    """sim.evaluation.closed_loop from the UAV at start_xy (m, ENU); yields, at each tick in ticks,
    (tick, particles (M, N, 4), log_w, plans (M, H, 4), planning, uav) of that tick's plan."""
    for k, state, res, uav in closed_loop(setup, max(ticks) + 1, seed, start_xy):
        p = res.planning
        if k in ticks and p is not None and p.paths is not None:
            yield (k, np.stack([b.particles[:, PLANAR] for b in state.beliefs]),
                   np.stack([b.log_weights for b in state.beliefs]),
                   np.stack([pl.means[:setup.lookahead_steps][:, PLANAR] for pl in res.plans]), p, uav)


def compare_routes(setup: MonitorSetup, particles: np.ndarray, log_w: np.ndarray, plans: np.ndarray,
                   planning, rollouts: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The EKF scores of the admissible routes of ``planning`` (C,) and their particle scores
    summed over targets from ``rollouts`` independent rollouts (rollouts, C), on a snapshot."""
    A, _, Q = planar_model(setup.model)
    q = information_reduction_factor(setup.sensor.p_detect, setup.sensor.clutter_rate, setup.sensor.sigma_rad)
    model = RolloutModel(A, Q, setup.sensor.sigma_rad, q)
    ok = np.flatnonzero(planning.admissible)
    runs = [particle_route_scores(particles, log_w, plans, planning.paths[ok, :, :2], model, rng).sum(axis=1)
            for _ in range(rollouts)]
    return planning.scores[ok], np.array(runs)


def score(P0, A, Q, targets, pos, c_meas, grad=False):
    """The planner's route score (``planning._route_traces`` for one route) and, grad, its gradient
    in the positions (H, 2) with the regulariser tr P_pos of the bearing's r^2 held fixed.
    P0 (M, 4, 4), targets (H, M, 2), pos (H, 2), c_meas = sigma^2 / q."""
    H, M = targets.shape[:2]
    P = P0.copy()
    At = A.T
    if grad:
        Pp_all, u_all, s_all, g_all, r2_all = (np.empty((H, M, 4, 4)), np.empty((H, M, 4)), np.empty((H, M)),
                                              np.empty((H, M, 2)), np.empty((H, M)))
    total = 0.0
    for i in range(H):
        if i:
            P = A @ P @ At + Q
        d = targets[i] - pos[i]
        r2 = d[:, 0] ** 2 + d[:, 1] ** 2 + P[:, 0, 0] + P[:, 1, 1]
        g = np.stack([d[:, 1], -d[:, 0]], axis=1) / r2[:, None]
        u = P[:, :, 0] * g[:, :1] + P[:, :, 1] * g[:, 1:]
        s = u[:, 0] * g[:, 0] + u[:, 1] * g[:, 1] + c_meas
        if grad:
            Pp_all[i], u_all[i], s_all[i], g_all[i], r2_all[i] = P, u, s, g, r2
        P = P - u[:, :, None] * u[:, None, :] / s[:, None, None]
        total += float(np.sum(P[:, 0, 0] + P[:, 1, 1]))
    if not grad:
        return total
    grad_g = np.empty((H, M, 2))
    G = np.zeros((M, 4, 4))
    for k in range(H - 1, -1, -1):
        G[:, 0, 0] += 1.0
        G[:, 1, 1] += 1.0
        uk, sk = u_all[k][..., None], s_all[k][:, None, None]
        Gu = G @ uk
        du = -(Gu + np.swapaxes(G, -1, -2) @ uk) / sk
        ds = (np.swapaxes(uk, -1, -2) @ Gu) / sk ** 2
        dh = (Pp_all[k] @ du + 2 * ds * uk)[..., 0]
        grad_g[k] = dh[:, :2]
        if k:
            GPp = G.copy()
            gk = g_all[k][:, None, :]
            GPp[..., :2] += du * gk
            GPp[..., :2, :2] += ds * np.swapaxes(gk, -1, -2) * gk
            G = At @ GPp @ A
    d = targets - pos[:, None, :]
    r2 = r2_all
    dx, dy = d[..., 0], d[..., 1]
    u1, u2 = grad_g[..., 0], grad_g[..., 1]
    ddx = u1 * (-2 * dx * dy / r2 ** 2) + u2 * (-1 / r2 + 2 * dx * dx / r2 ** 2)
    ddy = u1 * (1 / r2 - 2 * dy * dy / r2 ** 2) + u2 * (2 * dx * dy / r2 ** 2)
    return total, -np.stack([ddx, ddy], axis=-1).sum(axis=1)
