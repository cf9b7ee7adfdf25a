import math

import numpy as np
import pytest
from scipy.stats import norm, poisson

from onboard.core import tracking
from onboard.core.bearings import bearing, wrap

SENSOR = tracking.SensorModel(sigma_rad=math.radians(1.0), p_detect=0.95, clutter_rate=1.0)


def brute_force_g(phis, x, s, model):
    """eq:rfs_like term by term: factorials, Poisson pmf, sums and products over the set."""
    n = len(phis)
    kappa = 1.0 / (2 * math.pi)
    ell = float(bearing(x, s))
    c = lambda phi: norm.pdf(float(wrap(phi - ell)), 0.0, model.sigma_rad)  # noqa: E731
    first = (1 - model.p_detect) * math.factorial(n) * poisson.pmf(n, model.clutter_rate) * kappa ** n
    second = 0.0
    if n >= 1:
        total = 0.0
        for i, phi in enumerate(phis):
            others = math.prod(kappa for j in range(n) if j != i)
            total += c(phi) * others
        second = math.factorial(n - 1) * poisson.pmf(n - 1, model.clutter_rate) * model.p_detect * total
    return first + second


@pytest.mark.parametrize("n", range(7))
def test_likelihood_equals_brute_force_up_to_a_constant(n, rng):
    s = np.array([100.0, 50.0])
    xs = rng.uniform(0, 1000, size=(40, 2))
    true_b = float(bearing(xs[0], s))
    phis = list(rng.uniform(-np.pi, np.pi, size=n))
    if n:
        phis[0] = true_b + 0.01  # one bearing near particle 0 so the terms are not all clutter
    mine = tracking.log_likelihood(xs, s, np.array(phis), SENSOR)
    brute = np.log([brute_force_g(phis, x, s, SENSOR) for x in xs])
    ratio = brute - mine
    np.testing.assert_allclose(ratio, ratio[0], atol=1e-9)


def test_clutter_far_from_target_leaves_prior(rng):
    prior = tracking.initialise([500, 500, 0, 0, 0, 0], np.diag([200, 200, 1e-10, 20, 20, 1e-10]), 4000, rng)
    s = np.array([150.0, 200.0])
    toward = float(bearing(np.array([500, 500]), s))
    clutter = wrap(toward + np.pi + np.array([-0.4, 0.1, 0.5]))  # behind the sensor
    post = tracking.update(prior, [(s, clutter)], SENSOR).particles
    m0, P0 = tracking.estimate(prior)
    m1, P1 = tracking.estimate(post)
    assert np.linalg.norm(m1[:2] - m0[:2]) < 0.5
    assert np.trace(P1[:2, :2]) == pytest.approx(np.trace(P0[:2, :2]), rel=0.02)


def test_target_across_the_pi_cut_is_tracked_without_a_jump(model, rng):
    """A target due south of the sensor: bearings flip between +pi and -pi every scan."""
    s = np.array([0.0, 0.0])
    truth = np.array([0.5, -300.0, 0, 0, 0, 0])
    ps = tracking.initialise(truth + [20, 15, 0, 0, 0, 0], np.diag([400, 400, 1e-10, 1, 1, 1e-10]), 3000, rng)
    errs = []
    for k in range(15):
        sensor = s + [40.0 * (k % 3 - 1), 0.0]  # a little parallax
        phi = float(wrap(bearing(truth, sensor) + rng.normal(0, SENSOR.sigma_rad)))
        ps = tracking.update(ps, [(sensor, np.array([phi]))], SENSOR).particles
        mean, _ = tracking.estimate(ps)
        errs.append(abs(mean[0] - truth[0]))
        ps = tracking.resample_if_needed(ps, 0.5, rng)
    assert max(errs[3:]) < 10.0  # cross-range error stays small: no jump across the cut


def test_static_target_from_three_positions_is_localised(rng):
    truth = np.array([420.0, 610.0])
    sensors = [np.array([150.0, 200.0]), np.array([800.0, 200.0]), np.array([500.0, 900.0])]
    ps = tracking.initialise([450, 580, 0, 0, 0, 0], np.diag([2500, 2500, 1e-10, 1e-6, 1e-6, 1e-10]), 20000, rng)
    for _ in range(5):
        scans = [(s, np.array([float(bearing(truth, s) + rng.normal(0, SENSOR.sigma_rad))])) for s in sensors]
        ps = tracking.update(ps, scans, tracking.SensorModel(SENSOR.sigma_rad, 1.0, 0.0)).particles
        ps = tracking.resample_if_needed(ps, 0.5, rng)
        # roughening so that resampled duplicates spread over the shrinking posterior
        ps = tracking.ParticleSet(ps.particles + np.r_[rng.normal(0, 1.0, (len(ps), 2)).T, np.zeros((4, len(ps)))].T,
                                  ps.log_weights)
    mean, cov = tracking.estimate(ps)
    assert np.linalg.norm(mean[:2] - truth) < 5.0
    assert np.sqrt(np.trace(cov[:2, :2])) < 10.0


def test_vanishing_likelihoods_stay_finite(rng):
    """Every linear-domain weight would underflow to 0 (1e-6 rad noise, no clutter): log-weights
    keep the posterior finite and on the particles nearest the bearing."""
    model = tracking.SensorModel(sigma_rad=1e-6, p_detect=1.0, clutter_rate=0.0)
    prior = tracking.initialise([0, 100, 0, 0, 0, 0], np.eye(6) * 100, 500, rng)
    res = tracking.update(prior, [(np.zeros(2), np.array([0.3]))], model)
    lw = res.particles.log_weights
    assert not res.degenerate and np.all(~np.isnan(lw))
    assert np.isclose(np.exp(lw).sum(), 1.0)
    best = np.argmax(lw)
    off = np.abs(wrap(bearing(prior.particles[:, :2], np.zeros(2)) - 0.3))
    assert best == np.argmin(off)


def test_non_finite_bearing_keeps_prior_and_reports_it(rng):
    prior = tracking.initialise([0, 100, 0, 0, 0, 0], np.eye(6), 100, rng)
    res = tracking.update(prior, [(np.zeros(2), np.array([np.inf]))], SENSOR)
    assert res.degenerate
    np.testing.assert_array_equal(res.particles.log_weights, prior.log_weights)


def test_empty_set_is_uninformative_and_resampling_keeps_mean(rng):
    ps = tracking.initialise([10, 20, 0, 1, 2, 0], np.eye(6) * 4, 5000, rng)
    post = tracking.update(ps, [(np.zeros(2), np.array([]))], SENSOR).particles
    np.testing.assert_allclose(post.log_weights, ps.log_weights)
    w = rng.uniform(size=5000)
    skewed = tracking.ParticleSet(ps.particles, np.log(w / w.sum()))
    res = tracking.resample_if_needed(skewed, 1.0, rng)
    np.testing.assert_allclose(tracking.estimate(res)[0], tracking.estimate(skewed)[0], atol=0.15)


def test_particle_labels_follow_their_particles_through_update_prediction_and_resampling(model, rng):
    """The side of an obstacle a particle's target takes (monitor plan_sides) is carried with it."""
    ps = tracking.initialise([0, 0, 0, 0, 0, 0], np.eye(6), 3000, rng)
    labels = np.arange(3000)
    ps = tracking.ParticleSet(ps.particles, ps.log_weights, labels)
    post = tracking.update(ps, [(np.array([-10.0, 0.0]), bearing(np.zeros((1, 2)), np.array([-10.0, 0.0])))], SENSOR).particles
    np.testing.assert_array_equal(post.labels, labels)
    for bandwidth in (0.0, 0.2):
        res = tracking.resample_if_needed(post, 1.0, rng, bandwidth)
        assert len(np.unique(res.labels)) < 3000  # resampled: copies of the likely ones
        if bandwidth == 0.0:
            np.testing.assert_array_equal(res.particles, post.particles[res.labels])
        else:
            np.testing.assert_array_equal(res.particles[:, 2], post.particles[res.labels, 2])  # z untouched
    moved = tracking.predict(res, model, np.zeros(3), rng)
    np.testing.assert_array_equal(moved.labels, res.labels)


def test_regularised_resampling_spreads_copies_and_widens_by_one_plus_h_squared(rng):
    """A collapsed cloud (few distinct particles) comes back with distinct particles, the same
    mean, and a planar covariance (1 + h^2) times the weighted one; z stays untouched."""
    base = tracking.initialise([100, 200, 30, 3, -2, 0], np.diag([25, 25, 1e-10, 1, 1, 1e-10]), 20000, rng)
    logw = np.full(20000, -np.inf)
    logw[:400] = -np.log(400)  # 400 survivors: resampling makes ~50 copies of each
    skewed = tracking.ParticleSet(base.particles, logw)
    h = 0.3
    plain = tracking.resample_if_needed(skewed, 0.5, rng)
    reg = tracking.resample_if_needed(skewed, 0.5, rng, bandwidth=h)
    assert len(np.unique(plain.particles[:, 0])) <= 400
    assert len(np.unique(reg.particles[:, 0])) == 20000
    m0, c0 = tracking.estimate(skewed)
    m1, c1 = tracking.estimate(reg)
    np.testing.assert_allclose(m1[[0, 1, 3, 4]], m0[[0, 1, 3, 4]], atol=0.2)
    planar = [0, 1, 3, 4]
    ratio = np.diag(c1)[planar] / np.diag(c0)[planar]
    np.testing.assert_allclose(ratio, 1 + h ** 2, rtol=0.1)
    np.testing.assert_array_equal(np.sort(reg.particles[:, 2]), np.sort(plain.particles[:, 2]))
