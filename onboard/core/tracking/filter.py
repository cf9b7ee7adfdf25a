"""Per-target particle filter with the clutter-aware set likelihood (eqs. (9) and (10) of the paper).

Weights are kept as normalised log-weights so that no underflow turns into NaN.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from onboard.core.bearings import bearing, wrap
from onboard.core.dynamics import PLANAR, MotionModel
from onboard.core.tracking.intent import explained

LOG_2PI = np.log(2.0 * np.pi)


@dataclass(frozen=True)
class SensorModel:
    """Direction finder: bearing noise sigma (rad), detection probability, clutter.

    Clutter: Poisson(clutter_rate) false bearings per scan, uniform on (-pi, pi] (density 1/2pi).
    """

    sigma_rad: float
    p_detect: float
    clutter_rate: float

    @classmethod
    def from_config(cls, s) -> "SensorModel":
        return cls(s.sigma_rad, s.p_detect, s.clutter_rate)

    @property
    def clutter_density(self) -> float:
        return 1.0 / (2.0 * np.pi)


@dataclass(frozen=True, eq=False)
class ParticleSet:
    particles: np.ndarray  # (N, 6)
    log_weights: np.ndarray  # (N,), logsumexp == 0
    # (N,) int, or None: which side of an obstacle each particle's target takes (the monitor's
    # plan_sides; -1 none); carried through prediction, update and resampling
    labels: np.ndarray | None = None
    # (N,) int, or None: each particle's motion mode (onboard/core/tracking/intent.py: a goal's index,
    # STATIONARY or FREE); carried like the labels
    modes: np.ndarray | None = None
    # (N, 2) ENU m, or None: where each particle of the intent's AIMED mode is heading (its own
    # destination); carried like the modes
    aims: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.log_weights)

    @property
    def weights(self) -> np.ndarray:
        return np.exp(self.log_weights)


def initialise(mean: np.ndarray, cov: np.ndarray, n: int, rng: np.random.Generator) -> ParticleSet:
    """n particles drawn from N(mean, cov), equal weights."""
    particles = rng.multivariate_normal(np.asarray(mean, float), np.asarray(cov, float), size=n,
                                        method="cholesky")
    return ParticleSet(particles, np.full(n, -np.log(n)))


def predict(ps: ParticleSet, model: MotionModel, control: np.ndarray, rng: np.random.Generator) -> ParticleSet:
    """Eq. (9a): x' = A x + B u + nu, nu ~ N(0, Q), per particle; control (3,) for all
    particles or (N, 3), one per particle (N)."""
    noise = rng.standard_normal(ps.particles.shape) * model.Q_sqrt
    particles = ps.particles @ model.A.T + np.asarray(control, float) @ model.B.T + noise
    return replace(ps, particles=particles)


def logsumexp(a: np.ndarray, axis: int | None = None, keepdims: bool = False) -> np.ndarray | float:
    """log(sum(exp(a))) along ``axis``, shifted by the maximum; -inf where every entry is -inf.
    (scipy.special.logsumexp does the same with several times the call overhead, which the
    filter pays thousands of times per tick.)"""
    a = np.asarray(a, dtype=float)
    m = np.max(a, axis=axis, keepdims=True)
    m = np.where(np.isfinite(m), m, 0.0)
    with np.errstate(divide="ignore"):
        out = np.log(np.sum(np.exp(a - m), axis=axis, keepdims=True)) + m
    return out if keepdims else (out.item() if axis is None else np.squeeze(out, axis=axis))


def log_likelihood(positions: np.ndarray, sensor_xy: np.ndarray, bearings: np.ndarray,
                   model: SensorModel) -> np.ndarray:
    """log g(Phi | x, s) of eq. (10) for particle positions (N, >=2), up to a constant.

    With uniform clutter density kappa, eq. (10) factorises as
        g = e^-Lambda (Lambda kappa)^(n-1) [ (1 - p_D) Lambda kappa + p_D sum_i c(phi_i) ],
    and the prefactor does not depend on the target state, so it cancels in normalisation.
    With no bearing at all the likelihood is constant: the posterior equals the prior.
    """
    b = np.asarray(bearings, dtype=float).reshape(-1)
    n_pos = len(positions)
    if b.size == 0:
        return np.zeros(n_pos)
    if not np.isfinite(b).all():  # a corrupt set carries no likelihood: update() keeps the prior, flagged
        return np.full(n_pos, np.nan)
    predicted = bearing(positions, sensor_xy)  # (N,)
    resid = wrap(b[None, :] - predicted[:, None])  # (N, n)
    log_c = -0.5 * (resid / model.sigma_rad) ** 2 - np.log(model.sigma_rad) - 0.5 * LOG_2PI
    with np.errstate(divide="ignore"):
        log_detect = np.log(model.p_detect) + logsumexp(log_c, axis=1)
        log_miss = np.log((1.0 - model.p_detect) * model.clutter_rate * model.clutter_density)
    return np.logaddexp(log_detect, log_miss)


@dataclass(frozen=True)
class UpdateResult:
    particles: ParticleSet
    degenerate: bool  # every weight underflowed or was not finite: the prior was kept
    # per scan, how much better the belief explains it than a missed target (``intent.explained``,
    # log); NaN for a scan without bearings
    explained: tuple[float, ...] = ()


def log_missed(model: SensorModel) -> float:
    """``log_likelihood``'s value (same constant) for a target that was missed: every bearing clutter."""
    with np.errstate(divide="ignore"):
        return float(np.log((1.0 - model.p_detect) * model.clutter_rate * model.clutter_density))


def update(ps: ParticleSet, scans, model: SensorModel) -> UpdateResult:
    """Eq. (9b) with one or more scans [(sensor_xy, bearings), ...], their likelihoods multiplied.
    A scan may carry a third item, its own clutter rate Lambda (None: the model's).

    If the update leaves no finite weight (a set impossible under the model, e.g. p_D = 1 with
    the target far from every bearing, or a scan holding a non-finite bearing), the prior weights
    are kept and ``degenerate`` is set.
    """
    logw = ps.log_weights.copy()
    told = []
    for scan in scans:
        sensor_xy, bearings = scan[0], scan[1]
        lam = scan[2] if len(scan) > 2 else None
        m = model if lam is None else replace(model, clutter_rate=float(lam))
        ll = log_likelihood(ps.particles[:, :2], sensor_xy, bearings, m)
        if np.asarray(bearings).size and np.isfinite(ll).all() and np.isfinite(logw).any():
            told.append(explained(logw - logsumexp(logw), ll, log_missed(m)))
        else:
            told.append(float("nan"))
        logw = logw + ll
    total = logsumexp(logw) if np.isfinite(logw).any() else -np.inf
    if not np.isfinite(total):
        return UpdateResult(ps, True, tuple(told))
    logw = logw - total
    logw[~np.isfinite(logw)] = -np.inf
    return UpdateResult(replace(ps, log_weights=logw), False, tuple(told))


@dataclass(frozen=True)
class Recovery:
    """How a lost target is found again (docs/TRACKING.md "Recovery").

    The predicted belief f becomes the mixture (1 - prior) f + prior u: with probability ``prior``
    the target left what the motion model predicts (it took a side or a turn no particle took),
    and u = N(f's mean, f's position covariance + sigma_m^2 I) in the plane: near the
    prediction, wider than it. u is represented by ``share`` x N particles drawn along the scan's
    bearings within 3 standard deviations of u, weighted u / q (importance sampling; q the density
    they are drawn from), so they gain weight only when the bearings fit them better than f's
    particles, and ``trim`` keeps the N heaviest after the update. A jump model with a
    measurement-driven proposal: Thrun, Burgard and Fox, Probabilistic Robotics (2005), section
    8.3.5 (random particles, sensor resetting), with the weights of a proper mixture prior
    instead of a heuristic injection rate.
    """

    prior: float
    share: float
    sigma_m: float

    @classmethod
    def from_config(cls, tr) -> "Recovery | None":
        """From the scenario's ``tracking.recovery_*`` (onboard/settings/sections.py declares the defaults)."""
        if tr.recovery_prior <= 0.0 or tr.recovery_share <= 0.0:
            return None
        return cls(tr.recovery_prior, tr.recovery_share, tr.recovery_sigma_m)


def _ray_in_disc(sensor_xy: np.ndarray, bearings: np.ndarray, centre: np.ndarray, radius: float):
    """Ranges [r1, r2] (m, r1 >= 0) along each bearing (rad from north) inside the disc; NaN
    where the ray misses it."""
    d = np.stack([np.sin(bearings), np.cos(bearings)], axis=-1)  # (n, 2) east, north
    rel = centre - sensor_xy
    along = d @ rel
    disc = along ** 2 - (rel @ rel - radius ** 2)
    with np.errstate(invalid="ignore"):
        half = np.sqrt(disc)
    r1, r2 = np.maximum(along - half, 0.0), along + half
    miss = ~(disc > 0.0) | ~(r2 > 0.0)
    return np.where(miss, np.nan, r1), np.where(miss, np.nan, r2)


def recover(ps: ParticleSet, sensor_xy: np.ndarray, bearings: np.ndarray, rec: Recovery, sigma_rad: float,
            rng: np.random.Generator, new_modes: Callable[[int], np.ndarray] | None = None) -> ParticleSet:
    """The predicted belief with ``rec``'s mixture component added: K = ceil(share N) particles
    drawn along ``bearings`` (one scan's, from ``sensor_xy``, ENU m) within 3 standard deviations
    (the largest) of u, their velocities, heights and modes those of particles drawn from ps (the
    modes from ``new_modes(K)`` when given); N + K particles, log-weights of the mixture. ps
    unchanged (N particles) when no bearing passes there."""
    b = np.asarray(bearings, dtype=float).reshape(-1)
    b = b[np.isfinite(b)]
    s = np.asarray(sensor_xy, float)[:2]
    w = ps.weights
    centre = w @ ps.particles[:, :2]
    d = ps.particles[:, :2] - centre
    cov = (d * w[:, None]).T @ d + rec.sigma_m ** 2 * np.eye(2)
    r1, r2 = _ray_in_disc(s, b, centre, 3.0 * float(np.sqrt(np.linalg.eigvalsh(cov)[-1])))
    use = np.isfinite(r1)
    if not use.any():
        return ps
    b, r1, r2 = b[use], r1[use], r2[use]
    n = len(ps)
    k = int(np.ceil(rec.share * n))
    pick = rng.integers(len(b), size=k)
    theta = b[pick] + sigma_rad * rng.standard_normal(k)
    r = r1[pick] + (r2[pick] - r1[pick]) * rng.random(k)
    source = rng.choice(n, size=k, p=w / w.sum())
    new = ps.particles[source].copy()
    new[:, 0] = s[0] + r * np.sin(theta)
    new[:, 1] = s[1] + r * np.cos(theta)
    # q(x): the draw's density in the plane (polar density / r), over every bearing that could have drawn x
    rng_x = np.maximum(np.hypot(new[:, 0] - s[0], new[:, 1] - s[1]), 1e-9)
    ang = wrap(bearing(new[:, :2], s)[:, None] - b[None, :])
    inside = (rng_x[:, None] >= r1[None, :]) & (rng_x[:, None] <= r2[None, :])
    dens = np.exp(-0.5 * (ang / sigma_rad) ** 2) / (sigma_rad * np.sqrt(2.0 * np.pi)) * inside / (r2 - r1)[None, :]
    q = dens.mean(axis=1) / rng_x
    e = new[:, :2] - centre
    log_u = -0.5 * np.einsum("ki,ij,kj->k", e, np.linalg.inv(cov), e) - 0.5 * np.log(np.linalg.det(cov)) - LOG_2PI
    with np.errstate(divide="ignore"):
        log_new = np.log(rec.prior) + log_u - np.log(q) - np.log(k)
    logw = np.concatenate([np.log1p(-rec.prior) + ps.log_weights, log_new])
    logw = logw - logsumexp(logw)
    labels = None if ps.labels is None else np.concatenate([ps.labels, np.full(k, -1)])
    modes = None if ps.modes is None else np.concatenate([ps.modes, ps.modes[source] if new_modes is None
                                                          else new_modes(k)])
    aims = None if ps.aims is None else np.concatenate([ps.aims, ps.aims[source]])
    return ParticleSet(np.vstack([ps.particles, new]), logw, labels, modes, aims)


def trim(ps: ParticleSet, n: int) -> ParticleSet:
    """The n heaviest particles, renormalised (``recover``'s set back to N after the update)."""
    if len(ps) <= n:
        return ps
    keep = np.sort(np.argsort(-ps.log_weights, kind="stable")[:n])
    logw = ps.log_weights[keep]
    logw = logw - logsumexp(logw)
    return ParticleSet(ps.particles[keep], logw, *carried(ps, keep))


def carried(ps: ParticleSet, idx: np.ndarray) -> tuple:
    """The per-particle arrays a particle carries besides its state (labels, modes, aims), at ``idx``."""
    return tuple(None if a is None else a[idx] for a in (ps.labels, ps.modes, ps.aims))


def effective_sample_size(ps: ParticleSet) -> float:
    return float(np.exp(-logsumexp(2.0 * ps.log_weights)))


def systematic_indices(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Systematic resampling (as filterpy.monte_carlo.systematic_resample, which draws from
    numpy's global RNG; the core takes every random number from an explicit Generator)."""
    n = len(weights)
    positions = (rng.random() + np.arange(n)) / n
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    return np.searchsorted(cumulative, positions, side="right")


def resample_if_needed(ps: ParticleSet, threshold_fraction: float, rng: np.random.Generator,
                       bandwidth: float = 0.0, cov: np.ndarray | None = None) -> ParticleSet:
    """Resample systematically when the effective sample size falls below threshold * N.

    bandwidth h > 0 regularises (Musso et al.'s regularised particle filter): each resampled
    particle moves by N(0, h^2 C) in the planar states, C the weighted covariance before
    resampling (``cov``, (6, 6), when the caller has it already), so copies of one particle do not stay identical (sample impoverishment makes a
    filter with informative bearings confidently wrong). It widens the cloud by a factor
    (1 + h^2) in variance at each resampling.
    """
    n = len(ps)
    if effective_sample_size(ps) >= threshold_fraction * n:
        return ps
    idx = systematic_indices(ps.weights, rng)
    particles = ps.particles[idx]
    if bandwidth > 0.0:
        cov = estimate(ps)[1] if cov is None else cov
        C = cov[np.ix_(PLANAR, PLANAR)]
        try:
            L = np.linalg.cholesky(C + 1e-9 * np.eye(4))
        except np.linalg.LinAlgError:
            L = None
        if L is not None and np.all(np.isfinite(L)):
            particles = particles.copy()
            particles[:, PLANAR] += bandwidth * rng.standard_normal((n, 4)) @ L.T
    return ParticleSet(particles, np.full(n, -np.log(n)), *carried(ps, idx))


def estimate(ps: ParticleSet) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mean (6,) and covariance (6, 6)."""
    w = ps.weights
    mean = w @ ps.particles
    d = ps.particles - mean
    cov = (d * w[:, None]).T @ d
    return mean, 0.5 * (cov + cov.T)
