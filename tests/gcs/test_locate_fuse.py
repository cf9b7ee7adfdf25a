"""groundstation/locate_fuse.py: a stationary emitter's posterior over a whole recording, on a
zooming grid, against what it must be: the Gaussian posterior of the linearised bearings
(prior information plus each bearing's Fisher information) where that is exact enough, and a
consistent estimate (NEES) over noisy draws."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from groundstation.locate_fuse import fuse, log_posterior
from onboard.core.bearings import bearing
from onboard.core.tracking.filter import SensorModel

TRUTH = np.array([300.0, 500.0])
SIGMA = np.radians(1.0)
SENSOR = SensorModel(SIGMA, 0.95, 1.0)


def _legs(n: int = 300) -> np.ndarray:
    """A survey line 400-600 m from the emitter, crossing its south."""
    return np.column_stack([np.linspace(0.0, 600.0, n), np.zeros(n)])


def _scans(path, rng, sigma=SIGMA):
    out = []
    for s in path:
        b = bearing(TRUTH[None, :], s)[0] + sigma * rng.standard_normal()
        out.append((s, np.array([b]), None))
    return out


def _linearised(path, prior_cov):
    """(prior^-1 + sum of each bearing's information)^-1 at the truth: the bearing's gradient
    is the unit perpendicular to the line of sight over the range."""
    info = np.linalg.inv(prior_cov)
    for s in path:
        d = TRUTH - s
        r2 = d @ d
        g = np.array([d[1], -d[0]]) / r2
        info += np.outer(g, g) / SIGMA ** 2
    return np.linalg.inv(info)


def test_noise_free_bearings_give_the_truth_and_the_linearised_covariance():
    path = _legs()
    prior_cov = np.diag([100.0 ** 2, 100.0 ** 2])
    scans = [(s, np.array([bearing(TRUTH[None, :], s)[0]]), None) for s in path]
    f = fuse(scans, TRUTH + [60.0, -80.0], prior_cov, SensorModel(SIGMA, 1.0 - 1e-9, 1e-9))
    P = _linearised(path, prior_cov)
    # the prior pulls the mean by its share of the information: well under a tenth of a sigma here
    e = f.mean_m - TRUTH
    assert e @ np.linalg.solve(P, e) < 0.05, (f.mean_m, P)
    ratio = np.linalg.eigvals(np.linalg.solve(P, f.cov_m2)).real
    assert ratio.min() > 0.9 and ratio.max() < 1.1, ratio
    assert f.scans == len(path) and 2 <= f.levels <= 8


def test_the_fused_estimate_is_consistent_over_noisy_recordings():
    rng = np.random.default_rng(5)
    path = _legs(80)
    prior_cov = np.diag([100.0 ** 2, 100.0 ** 2])
    nees = []
    for _ in range(24):
        prior = TRUTH + 100.0 * rng.standard_normal(2)
        f = fuse(_scans(path, rng), prior, prior_cov, SENSOR)
        e = f.mean_m - TRUTH
        nees.append(e @ np.linalg.solve(f.cov_m2, e))
    lo, hi = chi2.ppf([0.0005, 0.9995], 2 * len(nees)) / len(nees)
    assert lo <= np.mean(nees) <= hi, np.mean(nees)


def test_without_bearings_the_prior_is_the_answer():
    prior_cov = np.array([[400.0, 100.0], [100.0, 900.0]])
    f = fuse([(np.zeros(2), np.empty(0), None)], [10.0, 20.0], prior_cov, SENSOR)
    assert f.scans == 0
    assert f.mean_m == pytest.approx([10.0, 20.0], abs=0.2)
    assert f.cov_m2 == pytest.approx(prior_cov, rel=0.05)


def test_log_posterior_is_the_prior_plus_each_scans_likelihood_at_its_own_clutter_rate():
    from dataclasses import replace

    from onboard.core.tracking.filter import log_likelihood

    pts = np.array([[300.0, 500.0], [310.0, 480.0], [250.0, 520.0]])
    scans = [(np.zeros(2), np.array([0.5]), None), (np.array([100.0, 0.0]), np.array([0.3, -1.0]), 4.0)]
    prior_cov = np.diag([1e4, 4e4])
    got = log_posterior(pts, scans, TRUTH, prior_cov, SENSOR)
    d = pts - TRUTH
    want = (-0.5 * (d[:, 0] ** 2 / 1e4 + d[:, 1] ** 2 / 4e4) + log_likelihood(pts, scans[0][0], scans[0][1], SENSOR)
            + log_likelihood(pts, scans[1][0], scans[1][1], replace(SENSOR, clutter_rate=4.0)))
    assert got - got[0] == pytest.approx(want - want[0], abs=1e-9)
