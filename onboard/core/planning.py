"""Next UAV position: candidate set S_(t+1) (eq:controlVectors), pseudo-posteriors from ideal
bearings (eq:measurement_model2) and the argmin of summed traces (eq:optimization).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from onboard.core.bearings import bearing, wrap
from onboard.core.obstacles import Obstacles

OBJECTIVES = ("trace", "position_trace")


@dataclass(frozen=True)
class CandidateGrid:
    step_m: float  # Delta_r
    n_radial: int  # N_r
    n_heading: int  # N_theta
    altitude_m: float  # h

    @classmethod
    def from_config(cls, u) -> "CandidateGrid":
        return cls(u.step_m, u.n_radial, u.n_heading, u.altitude_m)


def candidate_positions(center: np.ndarray, grid: CandidateGrid) -> np.ndarray:
    """S_(t+1) around center: "stay" first, then lambda = 1..N_r x kappa = 1..N_theta; (C, 3).

    Headings follow the paper: x += lambda Dr cos(kappa Dtheta), y += lambda Dr sin(kappa Dtheta).
    """
    lam = np.repeat(np.arange(1, grid.n_radial + 1), grid.n_heading)
    kap = np.tile(np.arange(1, grid.n_heading + 1), grid.n_radial)
    ang = kap * 2.0 * np.pi / grid.n_heading
    xy = np.stack([lam * grid.step_m * np.cos(ang), lam * grid.step_m * np.sin(ang)], axis=1)
    xy = np.vstack([[0.0, 0.0], xy]) + np.asarray(center, float)[:2]
    return np.column_stack([xy, np.full(len(xy), grid.altitude_m)])


def admissible(candidates: np.ndarray, start: np.ndarray, area_min, area_max,
               uav_obstacles: Obstacles) -> np.ndarray:
    """(C,) bool: inside the area and the straight path start -> candidate clears every obstacle
    (already inflated by the UAV's margin)."""
    c = np.asarray(candidates, float)
    inside = np.all((c >= np.asarray(area_min)) & (c <= np.asarray(area_max)), axis=1)
    if len(uav_obstacles):
        starts = np.broadcast_to(np.asarray(start, float), c.shape)
        blocked = uav_obstacles.segments_cross(starts, c).any(axis=1) | uav_obstacles.contains(c).any(axis=1)
        inside &= ~blocked
    return inside


def pseudo_posterior_traces(particles: np.ndarray, log_weights: np.ndarray, candidates: np.ndarray,
                            sigma_rad: float, objective: str = "trace") -> np.ndarray:
    """tr(Sigma~_j(s)) for every candidate s and target j: (C, M).

    particles (M, N, 6) and log_weights (M, N) are the predicted beliefs bel(x_(t+1)); the ideal
    bearing z = l(mu_pos, s) is taken to each target's predicted mean and the particles are
    re-weighted with N(z; l(x, s), sigma^2), without clutter (the paper's pseudo-update).
    Only the diagonal of each covariance is needed: tr = sum_d E[x_d^2] - E[x_d]^2.
    """
    if objective not in OBJECTIVES:
        raise ValueError(f"objective must be one of {OBJECTIVES}, got {objective!r}")
    dims = slice(0, 6) if objective == "trace" else slice(0, 2)
    w = np.exp(log_weights - logsumexp(log_weights, axis=1, keepdims=True))  # (M, N)
    mu = np.einsum("mn,mnd->md", w, particles[:, :, :2])  # predicted mean positions (M, 2)
    s = np.asarray(candidates, float)[:, None, None, :2]  # (C, 1, 1, 2)
    z = bearing(mu[None, :, :], s[:, :, 0, :])  # (C, M) ideal bearings
    pred = bearing(particles[None, :, :, :2], s)  # (C, M, N)
    log_post = -0.5 * (wrap(z[:, :, None] - pred) / sigma_rad) ** 2 + log_weights[None]
    log_post -= log_post.max(axis=2, keepdims=True)
    wp = np.exp(log_post)
    wp /= wp.sum(axis=2, keepdims=True)  # (C, M, N); the max term is 1, so the sum is >= 1
    x = particles[:, :, dims]  # (M, N, D)
    wm = wp.transpose(1, 0, 2)  # (M, C, N): one matrix product per target
    m1 = np.matmul(wm, x)
    m2 = np.matmul(wm, x * x)
    return np.sum(m2 - m1 * m1, axis=2).T


@dataclass(frozen=True, eq=False)
class PlanningResult:
    candidates: np.ndarray  # (C, 3)
    admissible: np.ndarray  # (C,) bool
    traces: np.ndarray  # (C, M): tr(Sigma~_j) per candidate and target
    scores: np.ndarray  # (C,): sum over targets; inf where not admissible
    index: int | None  # chosen candidate, None when no candidate is admissible

    @property
    def position(self) -> np.ndarray | None:
        return None if self.index is None else self.candidates[self.index]


def choose_next_position(particles: np.ndarray, log_weights: np.ndarray, center: np.ndarray,
                         grid: CandidateGrid, sigma_rad: float, area_min, area_max,
                         uav_obstacles: Obstacles, objective: str = "trace") -> PlanningResult:
    """eq:optimization over the admissible part of S_(t+1) around ``center``."""
    cand = candidate_positions(center, grid)
    start = np.array([center[0], center[1], grid.altitude_m])
    ok = admissible(cand, start, area_min, area_max, uav_obstacles)
    traces = pseudo_posterior_traces(particles, log_weights, cand, sigma_rad, objective)
    scores = np.where(ok, traces.sum(axis=1), np.inf)
    index = int(np.argmin(scores)) if ok.any() else None
    return PlanningResult(cand, ok, traces, scores, index)
