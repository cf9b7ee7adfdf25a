"""The simulated direction finders match their stated parameters, statistically.

Tolerances come from the sampling distributions (binomial, Poisson, normal, chi-square) at a
two-sided level of about 1e-4, so a correct model fails with odds ~1e-4 per check (and never,
with the fixed seeds here), while a wrong parameter (e.g. p_D off by 0.02) fails.
"""
import math

import numpy as np
import pytest
from scipy import stats

from onboard.core.bearings import bearing
from sim.truth.sensors import FIXED_SENSORS_M, DirectionFinder, df_scan, fixed_scans

Z = 3.9  # two-sided normal quantile for ~1e-4
ALPHA = 1e-4


def _bounds_ok(values):
    v = np.concatenate(values) if isinstance(values, (list, tuple)) else values
    return np.all(v > -np.pi) and np.all(v <= np.pi)


def test_detection_rate_matches_p_detect():
    df = DirectionFinder(math.radians(1.0), 0.95, 0.0)
    rng = np.random.default_rng(1)
    n = 20000
    counts = np.array([len(df_scan([[300.0, 400.0]], [0.0, 0.0], df, rng)[0]) for _ in range(n)])
    assert set(np.unique(counts)) <= {0, 1}
    k = counts.sum()
    assert abs(k - n * df.p_detect) <= Z * math.sqrt(n * df.p_detect * (1 - df.p_detect))


def test_clutter_count_is_poisson_and_uniform_on_the_circle():
    lam = 3.0
    df = DirectionFinder(math.radians(1.0), 0.0, lam)  # no target bearing: everything is clutter
    rng = np.random.default_rng(2)
    n = 5000
    scans = [df_scan([[300.0, 400.0]], [0.0, 0.0], df, rng)[0] for _ in range(n)]
    counts = np.array([len(s) for s in scans])
    assert abs(counts.mean() - lam) <= Z * math.sqrt(lam / n)
    # Poisson: the variance equals the mean. The sample variance of n Poisson counts has variance
    # (mu_4 - sigma^4) / n = (lam + 2 lam^2) / n, and is close to normal at this n
    assert abs(counts.var(ddof=1) - lam) <= Z * math.sqrt((lam + 2 * lam**2) / n)
    allb = np.concatenate(scans)
    assert _bounds_ok(allb)
    assert stats.kstest(allb, stats.uniform(loc=-np.pi, scale=2 * np.pi).cdf).pvalue > ALPHA


def test_bearing_noise_is_unbiased_with_sigma():
    sigma = math.radians(2.0)
    df = DirectionFinder(sigma, 1.0, 0.0)
    rng = np.random.default_rng(3)
    target, sensor = np.array([400.0, 300.0]), np.array([100.0, -100.0])
    true = float(bearing(target, sensor))
    n = 20000
    b = np.array([df_scan([target], sensor, df, rng)[0][0] for _ in range(n)])
    resid = b - true
    assert abs(resid.mean()) <= Z * sigma / math.sqrt(n)
    stat = (n - 1) * resid.var(ddof=1) / sigma**2
    assert stats.chi2.ppf(ALPHA / 2, n - 1) < stat < stats.chi2.ppf(1 - ALPHA / 2, n - 1)


def test_bearing_convention_and_wrap_near_south():
    """Clockwise from north; a target due south of the sensor sits at +-pi: output stays in (-pi, pi]."""
    df = DirectionFinder(math.radians(1.0), 1.0, 0.0)
    rng = np.random.default_rng(4)
    east = df_scan([[1000.0, 0.0]], [0.0, 0.0], df, rng)[0][0]
    north = df_scan([[0.0, 1000.0]], [0.0, 0.0], df, rng)[0][0]
    assert abs(east - np.pi / 2) < 5 * df.sigma_rad and abs(north) < 5 * df.sigma_rad
    south = np.array([df_scan([[0.0, -1000.0]], [0.0, 0.0], df, rng)[0][0] for _ in range(2000)])
    assert _bounds_ok(south)
    assert (south > 0).any() and (south < 0).any()  # both sides of the cut, wrapped
    assert np.all(np.abs(south) > np.pi - 5 * df.sigma_rad)


def test_scan_has_one_channel_per_target_and_takes_3d_positions():
    df = DirectionFinder(math.radians(1.0), 0.9, 1.5)
    targets = np.array([[100.0, 100.0, 0.0, 1, 2, 0], [500.0, 700.0, 0.0, 0, 0, 0], [900.0, 50.0, 0.0, 0, 0, 0]])
    out = df_scan(targets, np.array([400.0, 400.0, 40.0]), df, np.random.default_rng(5))
    assert len(out) == 3 and all(isinstance(b, np.ndarray) and b.ndim == 1 and b.dtype == float for b in out)
    # same seed, same scan; the draws per channel do not depend on what was detected
    again = df_scan(targets, np.array([400.0, 400.0, 40.0]), df, np.random.default_rng(5))
    assert all(np.array_equal(a, b) for a, b in zip(out, again))


def test_direction_finder_from_config_and_validation(paper):
    df = DirectionFinder.from_config(paper.sensor)
    assert (df.sigma_rad, df.p_detect, df.clutter_rate) == (paper.sensor.sigma_rad, paper.sensor.p_detect,
                                                            paper.sensor.clutter_rate)
    for bad in ((0.0, 0.9, 1.0), (0.01, 1.2, 1.0), (0.01, 0.9, -1.0), (float("nan"), 0.9, 1.0)):
        with pytest.raises(ValueError):
            DirectionFinder(*bad)


def test_fixed_scans_one_bearing_per_target_and_sensor_with_sigma():
    sigma = math.radians(1.0)
    rng = np.random.default_rng(6)
    targets = np.array([[300.0, 500.0, 0.0], [700.0, 600.0, 0.0]])
    n = 3000
    resid = []
    for _ in range(n):
        scans = fixed_scans(targets, FIXED_SENSORS_M, sigma, rng)
        assert len(scans) == 3
        for s, pos in zip(scans, FIXED_SENSORS_M):
            assert np.allclose(s.sensor_position[:2], pos)
            assert len(s.bearings) == 2 and all(len(b) == 1 for b in s.bearings)
            resid.extend(float(s.bearings[j][0] - bearing(targets[j], np.array(pos))) for j in range(2))
    resid = np.array(resid)
    m = len(resid)
    assert abs(resid.mean()) <= Z * sigma / math.sqrt(m)
    stat = (m - 1) * resid.var(ddof=1) / sigma**2
    assert stats.chi2.ppf(ALPHA / 2, m - 1) < stat < stats.chi2.ppf(1 - ALPHA / 2, m - 1)
