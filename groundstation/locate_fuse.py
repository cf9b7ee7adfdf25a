"""A stationary emitter's position fused over a whole recording, for ``pmon locate`` (docs/LOCATE.md).

Offline, a target that stands still has an exact posterior: its prior times the set likelihood
of every scan of the recording (eq. (10), ``tracking.log_likelihood``: the filter's own sensor
model, clutter and missed detections included), a density over the ground plane. It is evaluated
on a grid that zooms in on where the mass is (``GRID_CELLS`` a side along the posterior's principal axes, each
level's box the cells holding mass at the last one, padded) until the posterior's standard
deviation spans ``RESOLVE_CELLS`` cells along both axes (or the box stops shrinking: a density
with long tails); its mean and covariance are the estimate.

The filter run tick by tick answers a different question: where the target is now, if it may
have moved. Its stationary mode lets the position jitter every tick and its particles are
regularised as they are resampled, so it forgets old bearings, and its covariance is that of a
target that wanders; an emitter that stood still all along is placed better, and its ellipse is
the right size, by the recording as a whole. A re-seed of the filter (its bearings stopped
agreeing for a few scans) changes its last estimate, not this one.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from onboard.core.tracking import filter as tracking
GRID_CELLS = 81  # cells a side of each level's grid
RESOLVE_CELLS = 3.0  # done when the posterior's sd along each axis of the grid spans this many cells
MAX_LEVELS = 12
MASS_FLOOR = 1e-9  # a cell holding less than this share of the largest holds no mass
PAD_CELLS = 2  # the next box: the cells with mass, this many cells more each side
PRIOR_SIGMAS = 5.0  # the first box: the prior's mean +- this many standard deviations


@dataclass(frozen=True)
class Fused:
    mean_m: np.ndarray  # (2,) east, north
    cov_m2: np.ndarray  # (2, 2)
    scans: int  # scans with bearings fused
    levels: int  # grid levels evaluated


def log_posterior(points: np.ndarray, scans, prior_mean: np.ndarray, prior_cov: np.ndarray,
                  sensor: tracking.SensorModel) -> np.ndarray:
    """log p(x | every scan) (up to a constant) at ``points`` (P, 2): the Gaussian prior and each
    scan's set likelihood (``scans``: [(sensor_xy, bearings, clutter_rate or None), ...])."""
    d = points - prior_mean
    out = -0.5 * np.einsum("pi,ij,pj->p", d, np.linalg.inv(prior_cov), d)
    for sensor_xy, bearings, lam in scans:
        m = sensor if lam is None else replace(sensor, clutter_rate=float(lam))
        out += tracking.log_likelihood(points, sensor_xy, bearings, m)
    return out


def _axes(cov: np.ndarray) -> np.ndarray:
    """The principal axes of a 2x2 covariance, as the columns of a rotation."""
    return np.linalg.eigh(cov)[1]


def fuse(scans, prior_mean, prior_cov, sensor: tracking.SensorModel) -> Fused:
    """The posterior mean and covariance of a stationary target's plane position given every scan
    (``log_posterior``), from grids laid along the posterior's principal axes, each over the
    cells that held mass at the last."""
    prior_mean = np.asarray(prior_mean, float)[:2]
    prior_cov = np.asarray(prior_cov, float)[:2, :2]
    scans = [s for s in scans if np.asarray(s[1]).size]
    axes = _axes(prior_cov)
    sd = np.sqrt(np.clip(np.diag(axes.T @ prior_cov @ axes), 0.0, None))
    centre, lo, hi = prior_mean, -PRIOR_SIGMAS * sd, PRIOR_SIGMAS * sd
    u = np.linspace(0.0, 1.0, GRID_CELLS)
    last_step = np.full(2, np.inf)
    for level in range(1, MAX_LEVELS + 1):
        A, B = np.meshgrid(lo[0] + (hi[0] - lo[0]) * u, lo[1] + (hi[1] - lo[1]) * u)
        local = np.column_stack([A.ravel(), B.ravel()])  # along the axes, about the centre
        pts = centre + local @ axes.T
        step = (hi - lo) / (GRID_CELLS - 1)
        logp = log_posterior(pts, scans, prior_mean, prior_cov, sensor)
        w = np.exp(logp - logp.max())
        w /= w.sum()
        mean = w @ pts
        d = pts - mean
        cov = 0.5 * ((d * w[:, None]).T @ d + ((d * w[:, None]).T @ d).T)
        sd_axes = np.sqrt(np.clip(np.diag(axes.T @ cov @ axes), 0.0, None))
        if (sd_axes >= RESOLVE_CELLS * step).all() or level == MAX_LEVELS or (step > 0.5 * last_step).all():
            return Fused(mean, cov, len(scans), level)
        held = pts[w >= MASS_FLOOR * w.max()]
        last_step = step
        # the next grid along this posterior's axes, over the cells that held mass
        axes = _axes(cov) if np.linalg.det(cov) > 0 else axes
        centre = mean
        rel = (held - centre) @ axes
        pad = PAD_CELLS * float(step.max())
        lo, hi = rel.min(axis=0) - pad, rel.max(axis=0) + pad
    raise AssertionError("unreachable")
