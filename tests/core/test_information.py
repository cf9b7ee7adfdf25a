"""Fisher information of bearings, the reduction factor, and the EKF pseudo-update against the particle
pseudo-update."""
import math

import numpy as np

from onboard.core.dynamics import MotionModel
from onboard.core.planning.information import (bearing_gradient, bearing_update_components, information_reduction_factor,
                                               kalman_pseudo_update, planar_model, predict_planar_components)
from onboard.core.planning.next_position import pseudo_posterior_traces

SIGMA = math.radians(1.0)


def test_bearing_gradient_is_the_derivative_of_the_bearing():
    def phi(t, s):
        return math.atan2(t[0] - s[0], t[1] - s[1])

    t, s = np.array([120.0, 340.0]), np.array([-50.0, 20.0])
    g = bearing_gradient(t, s)
    h = 1e-4
    num = [(phi(t + e * h, s) - phi(t - e * h, s)) / (2 * h) for e in np.eye(2)]
    np.testing.assert_allclose(g, num, rtol=1e-6)


def test_reduction_factor_is_p_detect_without_clutter_and_falls_with_clutter():
    assert information_reduction_factor(0.95, 0.0, SIGMA) == 0.95
    assert information_reduction_factor(1.0, 0.0, SIGMA) == 1.0
    # without clutter the Monte Carlo estimate itself agrees (a tiny rate: essentially no clutter)
    q0 = information_reduction_factor(0.95, 1e-9, SIGMA, samples=20_000)
    assert abs(q0 - 0.95) < 0.01
    qs = [information_reduction_factor(0.95, lam, SIGMA, samples=50_000) for lam in (1.0, 8.0, 50.0)]
    assert 0.95 > qs[0] > qs[1] > qs[2] > 0.3, qs


def _beliefs(rng, n, mean_xy, cov_xy):
    x = np.zeros((1, n, 6))
    x[0, :, :2] = rng.multivariate_normal(mean_xy, cov_xy, n)
    x[0, :, 3:5] = rng.normal(0.0, 2.0, (n, 2))
    return x, np.full((1, n), -math.log(n))


def _spd(rng, shape):
    B = rng.normal(size=shape + (4, 4)) * [10.0, 10.0, 2.0, 2.0]
    return B @ np.swapaxes(B, -1, -2) + np.eye(4)


def test_the_written_out_planar_prediction_and_update_are_the_matrix_forms(rng):
    """The route planner's hot loop works on covariances components first with A, Q and H written
    out: each must be the textbook matrix formula (a friction and dt other than the paper's too)."""
    for model in (MotionModel.create(1.0, 0.2, 1300.0, [30.0, 30.0, 1e-10, 3.0, 3.0, 1e-10]),
                  MotionModel.create(0.5, 0.35, 900.0, [12.0, 7.0, 1e-10, 0.4, 2.5, 1e-10])):
        A, _, Q = planar_model(model)
        P = _spd(rng, (3, 5))
        got = np.moveaxis(predict_planar_components(np.moveaxis(P, (-2, -1), (0, 1)).copy(), model), (0, 1), (-2, -1))
        np.testing.assert_allclose(got, A @ P @ A.T + Q, rtol=1e-13, atol=1e-12)
    P = _spd(rng, (3, 5))
    tgt, sen = rng.normal(size=(3, 5, 2)) * 300.0, rng.normal(size=(5, 2)) * 300.0
    d = tgt - sen
    r2 = np.sum(d * d, axis=-1) + P[..., 0, 0] + P[..., 1, 1]
    H = np.concatenate([np.stack([d[..., 1], -d[..., 0]], axis=-1) / r2[..., None], np.zeros((3, 5, 2))], axis=-1)
    R = SIGMA**2 / 0.8
    S = np.einsum("...i,...ij,...j->...", H, P, H) + R
    K = np.einsum("...ij,...j->...i", P, H) / S[..., None]
    want = P - K[..., :, None] * np.einsum("...j,...jk->...k", H, P)[..., None, :]
    got = bearing_update_components(np.moveaxis(P, (-2, -1), (0, 1)).copy(), tgt, sen, SIGMA, 0.8)
    np.testing.assert_allclose(np.moveaxis(got, (0, 1), (-2, -1)), want, rtol=1e-10, atol=1e-9)
    np.testing.assert_array_equal(kalman_pseudo_update(P, tgt, sen, SIGMA, 0.8), np.moveaxis(got, (0, 1), (-2, -1)))


def test_ekf_pseudo_update_matches_the_particle_pseudo_update(rng):
    """The cheap score the lookahead uses (EKF form) against the paper's particle pseudo-update,
    on the same predicted belief (position std about 25 m) and the same candidate sensor positions
    (ranges 30 to 700 m, all bearings). From 150 m on the traces agree within 5 %; closer, the
    linearisation is conservative (it never promises more than the particles give, so a planner
    using it is not lured onto the targets); over all candidates it ranks them alike."""
    particles, logw = _beliefs(rng, 20_000, [300.0, 500.0], [[400.0, 150.0], [150.0, 250.0]])
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ranges = np.repeat([30.0, 60.0, 150.0, 350.0, 700.0], len(ang))
    cands = np.array([300.0, 500.0]) + ranges[:, None] * np.column_stack([np.cos(np.tile(ang, 5)), np.sin(np.tile(ang, 5))])
    pf = pseudo_posterior_traces(particles, logw, cands, SIGMA, "position_trace")[:, 0]
    x = particles[0][:, [0, 1, 3, 4]]
    P = np.cov(x.T)
    mu = x.mean(axis=0)
    ekf = np.trace(kalman_pseudo_update(np.broadcast_to(P, (len(cands), 4, 4)), mu[None, :2], cands, SIGMA)[:, :2, :2],
                   axis1=1, axis2=2)
    ratio = ekf / pf
    far = ranges >= 150.0
    assert np.abs(ratio[far] - 1.0).max() < 0.05, ratio[far]
    assert ratio[~far].min() > 0.98 and ratio[~far].max() < 1.7, ratio[~far]
    rank = lambda v: np.argsort(np.argsort(v))  # noqa: E731
    rho = np.corrcoef(rank(ekf), rank(pf))[0, 1]
    assert rho > 0.95, rho
