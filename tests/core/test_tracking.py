import math

import numpy as np
import pytest
from scipy.stats import norm, poisson

from onboard.core.tracking import filter as tracking
from onboard.core.bearings import bearing, wrap
from onboard.core.dynamics import MotionModel

SENSOR = tracking.SensorModel(sigma_rad=math.radians(1.0), p_detect=0.95, clutter_rate=1.0)


def brute_force_g(phis, x, s, model):
    """Eq. (10) term by term: factorials, Poisson pmf, sums and products over the set."""
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


# --- recovery: the jump mixture (1 - e) f + e u, u uniform on a disc, drawn along the bearings ---

def _jump_posterior_share(ps, s, phis, rec, model):
    """P(jumped | bearings) of the mixture prior, by quadrature: e Z_u / (e Z_u + (1 - e) Z_f),
    Z_u = integral of u g on a 0.5 m grid over u's 3-sigma disc, Z_f = sum_i w_i g(x_i)."""
    centre = ps.weights @ ps.particles[:, :2]
    d = ps.particles[:, :2] - centre
    cov = (d * ps.weights[:, None]).T @ d + rec.sigma_m ** 2 * np.eye(2)
    radius = 3.0 * np.sqrt(np.linalg.eigvalsh(cov)[-1])
    h = 0.5
    ax = np.arange(-radius, radius + h, h)
    gx, gy = np.meshgrid(ax, ax)
    inside = gx ** 2 + gy ** 2 <= radius ** 2
    e = np.stack([gx[inside], gy[inside]], axis=1)
    u = np.exp(-0.5 * np.einsum("ki,ij,kj->k", e, np.linalg.inv(cov), e)) / (2 * np.pi * np.sqrt(np.linalg.det(cov)))
    z_u = (u * np.exp(tracking.log_likelihood(e + centre, s, phis, model))).sum() * h * h
    z_f = ps.weights @ np.exp(tracking.log_likelihood(ps.particles[:, :2], s, phis, model))
    return rec.prior * z_u / (rec.prior * z_u + (1 - rec.prior) * z_f)


@pytest.mark.parametrize("offset_m", [0.0, 40.0, 80.0])
def test_recovery_weights_are_the_mixture_posterior(offset_m, rng):
    # the cloud offset_m east of the bearing's ray; the injected particles' posterior weight must
    # match the mixture's exact posterior probability of the jump (a wrong u/q, Jacobian or 1/K fails)
    s = np.array([0.0, 0.0])
    truth = np.array([0.0, 400.0])
    phis = np.array([float(bearing(truth, s))])
    ps = tracking.initialise([offset_m, 400, 0, 0, 0, 0], np.diag([25, 25, 1e-10, 1, 1, 1e-10]), 4000, rng)
    rec = tracking.Recovery(prior=0.01, share=1.0, sigma_m=50.0)
    expected = _jump_posterior_share(ps, s, phis, rec, SENSOR)
    mixed = tracking.recover(ps, s, phis, rec, SENSOR.sigma_rad, rng)
    assert len(mixed) == 8000 and mixed.labels is None
    post = tracking.update(mixed, [(s, phis)], SENSOR).particles
    got = post.weights[4000:].sum()
    assert got == pytest.approx(expected, rel=0.1, abs=1e-4)
    assert (expected < 0.01) if offset_m == 0.0 else expected > 0.5


def test_recovery_finds_a_lost_target_that_the_filter_alone_does_not(rng):
    truth = np.array([500.0, 500.0])
    still = MotionModel.create(1.0, 0.5, 1.0, (4, 4, 1e-10, 0.1, 0.1, 1e-10))

    def final_error(rec, seed):
        r = np.random.default_rng(seed)
        ps = tracking.initialise([600, 500, 0, 0, 0, 0], np.diag([100, 100, 1e-10, 1, 1, 1e-10]), 2000, r)
        for t in range(25):
            s = np.array([200.0 + 20 * t, 100.0 + 10 * t])
            phis = np.concatenate([[float(bearing(truth, s)) + SENSOR.sigma_rad * r.standard_normal()],
                                   r.uniform(-np.pi, np.pi, r.poisson(1.0))])
            if rec is not None:
                ps = tracking.recover(ps, s, phis, rec, SENSOR.sigma_rad, r)
            ps = tracking.trim(tracking.update(ps, [(s, phis)], SENSOR).particles, 2000)
            assert len(ps) == 2000
            err = float(np.hypot(*(tracking.estimate(ps)[0][:2] - truth)))
            ps = tracking.predict(tracking.resample_if_needed(ps, 0.5, r, 0.2), still, np.zeros(3), r)
        return err

    rec = tracking.Recovery(prior=0.01, share=0.02, sigma_m=50.0)
    for seed in range(3):
        assert final_error(None, seed) > 60.0
        assert final_error(rec, seed) < 30.0


def test_recovery_leaves_the_set_alone_when_no_bearing_passes_near_the_prediction(rng):
    ps = tracking.initialise([0, 500, 0, 0, 0, 0], np.eye(6), 100, rng)
    rec = tracking.Recovery(prior=0.01, share=0.5, sigma_m=10.0)
    assert tracking.recover(ps, np.zeros(2), np.array([np.pi / 2, np.nan]), rec, SENSOR.sigma_rad, rng) is ps


def test_trim_keeps_the_heaviest_renormalised_with_their_labels():
    ps = tracking.ParticleSet(np.arange(12.0).reshape(6, 2).repeat(3, axis=1),
                              np.log([0.1, 0.3, 0.05, 0.25, 0.2, 0.1]), np.arange(6))
    out = tracking.trim(ps, 3)
    np.testing.assert_array_equal(out.labels, [1, 3, 4])
    np.testing.assert_allclose(out.weights, np.array([0.3, 0.25, 0.2]) / 0.75)
