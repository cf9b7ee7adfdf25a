"""The evaluation's posterior Cramer-Rao bound recursion (sim/evaluation/metrics.py) against an
optimal filter."""
import math

import numpy as np

from onboard.core.dynamics import MotionModel
from onboard.core.planning.information import planar_model
from sim.evaluation.metrics import pcrb


def test_pcrb_equals_the_kalman_covariance_and_bounds_its_error(rng):
    """Linear-Gaussian case (position measurements, known dynamics): the Kalman filter is the
    optimal estimator, its covariance is the bound, and its Monte Carlo MSE is not below it."""
    model = MotionModel.create(1.0, 0.2, 1300.0, [30.0, 30.0, 1e-10, 3.0, 3.0, 1e-10])
    A, _, Q = planar_model(model)
    R = np.diag([400.0, 100.0])  # position measurement noise, m^2
    H = np.hstack([np.eye(2), np.zeros((2, 2))])
    P0 = np.diag([200.0, 200.0, 20.0, 20.0])
    K = 25
    info = np.broadcast_to(H.T @ np.linalg.inv(R) @ H, (K + 1, 4, 4))
    bound = pcrb(np.linalg.inv(P0), np.broadcast_to(A, (K, 4, 4)), Q, info)
    n = 3000
    x = rng.multivariate_normal(np.zeros(4), P0, n)
    m, P = np.zeros((n, 4)), P0.copy()
    err2 = np.zeros((K + 1, 4))
    Lq, Lr = np.linalg.cholesky(Q), np.linalg.cholesky(R)
    for k in range(K + 1):
        if k:
            x = x @ A.T + rng.standard_normal((n, 4)) @ Lq.T
            m, P = m @ A.T, A @ P @ A.T + Q
        z = x @ H.T + rng.standard_normal((n, 2)) @ Lr.T
        S = H @ P @ H.T + R
        G = P @ H.T @ np.linalg.inv(S)
        m = m + (z - m @ H.T) @ G.T
        P = P - G @ S @ G.T
        np.testing.assert_allclose(P, bound[k], rtol=1e-8, atol=1e-8)
        err2[k] = np.mean((m - x) ** 2, axis=0)
    b = np.einsum("kii->ki", bound)
    # empirical MSE / bound: chi^2-distributed around 1 with n samples, never significantly below
    ratio = err2 / b
    assert ratio.min() > 1.0 - 4.0 * math.sqrt(2.0 / n), ratio.min()
    assert abs(ratio.mean() - 1.0) < 0.03
