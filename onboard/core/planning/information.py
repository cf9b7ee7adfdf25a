"""Fisher information of bearings: the Gaussian (EKF) pseudo-update and the information reduction
factor of detection and clutter (the evaluation's posterior Cramer-Rao bound builds on them:
sim/evaluation/metrics.py).

Everything here works on the planar part of the state, x = [px, py, vx, vy] (m, m/s): u_z = 0 and
the vertical process noise is 1e-10 in the paper, so the vertical states carry no information
and only make the matrices ill-conditioned.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from onboard.core.dynamics import PLANAR, MotionModel  # noqa: F401  (PLANAR re-exported)



def planar_model(model: MotionModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(A, B, Q) restricted to [px, py, vx, vy] and [ux, uy]."""
    A = model.A[np.ix_(PLANAR, PLANAR)]
    B = model.B[np.ix_(PLANAR, [0, 1])]
    Q = model.Q[np.ix_(PLANAR, PLANAR)]
    return A, B, Q


def bearing_gradient(target_xy: np.ndarray, sensor_xy: np.ndarray) -> np.ndarray:
    """d phi / d(x_t, y_t) for phi = atan2(x_t - x_s, y_t - y_s): (..., 2), rad/m."""
    d = np.asarray(target_xy, float)[..., :2] - np.asarray(sensor_xy, float)[..., :2]
    r2 = np.maximum(np.sum(d * d, axis=-1, keepdims=True), 1e-6)
    return np.stack([d[..., 1], -d[..., 0]], axis=-1) / r2


def bearing_information(target_xy: np.ndarray, sensor_xy: np.ndarray, sigma_rad: float,
                        reduction: float = 1.0) -> np.ndarray:
    """Fisher information of one scan about [px, py, vx, vy]: q H^T H / sigma^2, (..., 4, 4)."""
    g = bearing_gradient(target_xy, sensor_xy)
    H = np.concatenate([g, np.zeros_like(g)], axis=-1)
    return reduction * H[..., :, None] * H[..., None, :] / sigma_rad**2


@lru_cache(maxsize=32)
def information_reduction_factor(p_detect: float, clutter_rate: float, sigma_rad: float,
                                 samples: int = 200_000, seed: int = 0) -> float:
    """q in J = q H^T H / sigma^2 for a scan with detection probability p_D and Poisson(Lambda)
    clutter uniform on (-pi, pi] (the set likelihood, eq. (10)).

    q = sigma^2 E[(d/dh log g(Z | h))^2] over measurement sets Z, by Monte Carlo with a fixed
    seed (deterministic). Dividing g by the clutter-only term leaves
        g ~ (1 - p_D) + p_D sum_i N(z_i; h, sigma^2) / (Lambda c),   c = 1 / 2 pi,
    whose derivative in h is explicit. Without clutter q = p_D exactly (the empty set carries
    nothing, a detection carries 1 / sigma^2), which is returned without sampling.
    """
    if clutter_rate <= 0.0:
        return float(p_detect)
    rng = np.random.default_rng(seed)
    lam_c = clutter_rate / (2.0 * np.pi)
    n_clutter = rng.poisson(clutter_rate, samples)
    width = int(n_clutter.max())
    # residuals z - h of every bearing of each set: clutter columns, then the detection column
    clutter = rng.uniform(-np.pi, np.pi, (samples, width))
    detected = rng.random(samples) < p_detect
    resid = np.column_stack([clutter, rng.normal(0.0, sigma_rad, samples)])
    present = np.column_stack([np.arange(width)[None, :] < n_clutter[:, None], detected])
    dens = np.exp(-0.5 * (resid / sigma_rad) ** 2) / (np.sqrt(2.0 * np.pi) * sigma_rad) * present
    num = p_detect * np.sum(dens * resid / sigma_rad**2, axis=1) / lam_c
    den = (1.0 - p_detect) + p_detect * np.sum(dens, axis=1) / lam_c
    score = num / den
    return float(sigma_rad**2 * np.mean(score**2))


def kalman_pseudo_update(P: np.ndarray, target_xy: np.ndarray, sensor_xy: np.ndarray,
                         sigma_rad: float, reduction: float = 1.0) -> np.ndarray:
    """Covariance after one bearing, linearised at the predicted target position (EKF form,
    scalar measurement with variance sigma^2 / q). P (..., 4, 4); returns (..., 4, 4).

    The gradient's 1/r uses r^2 + tr(P_pos) instead of r^2: a linearisation at the mean
    promises unbounded information as the sensor nears the target, which the particle
    pseudo-update (and the real filter) does not see when r is comparable to the target's
    own uncertainty; without this a planner flies onto the targets."""
    Pc = bearing_update_components(np.moveaxis(P, (-2, -1), (0, 1)), target_xy, sensor_xy, sigma_rad, reduction)
    return np.moveaxis(Pc, (0, 1), (-2, -1))


def bearing_update_components(Pc: np.ndarray, target_xy: np.ndarray, sensor_xy: np.ndarray,
                              sigma_rad: float, reduction: float = 1.0) -> np.ndarray:
    """``kalman_pseudo_update`` on covariances stored components first, Pc (4, 4, ...): the
    route planner's hot loop, where each component is then one contiguous array instead of the
    (..., 4, 4) layout's strided and stacked products (the same values). H = [g, 0, 0] is
    written out: P H^T is P's first two columns times g."""
    d = np.asarray(target_xy, float)[..., :2] - np.asarray(sensor_xy, float)[..., :2]
    dx, dy = d[..., 0], d[..., 1]
    r2 = (dx * dx + dy * dy) + (Pc[0, 0] + Pc[1, 1])
    gx, gy = dy / r2, -dx / r2
    PH = Pc[:, 0] * gx + Pc[:, 1] * gy  # (4, ...)
    s = (gx * PH[0] + gy * PH[1]) + sigma_rad**2 / max(reduction, 1e-12)
    return Pc - PH[:, None] * PH[None, :] / s


def predict_planar_components(Pc: np.ndarray, model: MotionModel) -> np.ndarray:
    """A P A^T + Q on [px, py, vx, vy], P stored components first (4, 4, ...), with the model's
    A = [[I, dt I], [0, (1 - eps) I]] and diagonal Q written out (the same values as the matrix
    products, in a few contiguous array operations)."""
    dt, decay = model.dt_s, 1.0 - model.friction
    X = np.empty_like(Pc)
    X[:2] = Pc[:2] + dt * Pc[2:]
    X[2:] = decay * Pc[2:]
    Y = np.empty_like(Pc)
    Y[:, :2] = X[:, :2] + dt * X[:, 2:]
    Y[:, 2:] = decay * X[:, 2:]
    for k, q in enumerate(np.diag(model.Q)[PLANAR]):
        Y[k, k] += q
    return Y
