"""The evaluation's statistics (``sim.evaluation.trials`` runs the trials and ``summarise``s them with
these; its module docstring defines every metric): NEES band, t-intervals, the paired bootstrap
ratio, the PCRB along a flown path, how a UAV moved, and the types of a trial's traces and of the
summary."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from onboard.core.planning.information import PLANAR, bearing_information, planar_model

REFERENCE = "greedy_l1"  # paired differences are taken against this method
FIXED = "fixed3"
BOOTSTRAP_RESAMPLES = 2000


def seeded_rng(seed: int, *key: int) -> np.random.Generator:
    """The generator of (seed, key): ``numpy.random.SeedSequence`` with ``key`` as spawn key."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=tuple(int(k) for k in key)))


def nees_band(n_trials: int, dof: int = 2, level: float = 0.95) -> tuple[float, float]:
    """95 % band of the average of n_trials NEES values of a consistent filter (dof each)."""
    a = (1.0 - level) / 2.0
    return (float(stats.chi2.ppf(a, dof * n_trials) / n_trials), float(stats.chi2.ppf(1 - a, dof * n_trials) / n_trials))


def t_interval(x: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """Mean and its two-sided t confidence interval (nan for fewer than two values)."""
    x = np.asarray(x, float)
    m = float(x.mean()) if x.size else float("nan")
    if x.size < 2:
        return m, float("nan"), float("nan")
    half = float(stats.t.ppf(0.5 + level / 2, x.size - 1) * x.std(ddof=1) / math.sqrt(x.size))
    return m, m - half, m + half


def pcrb(J0: np.ndarray, F: np.ndarray, Q: np.ndarray, info: np.ndarray) -> np.ndarray:
    """Posterior Cramer-Rao bound recursion for x_k = F_k x_(k-1) + w, w ~ N(0, Q), with
    measurement information info_k (Tichavsky et al. 1998, additive Gaussian noise form):

        J_k = (F_k J_(k-1)^-1 F_k^T + Q)^-1 + info_k

    J0 (4, 4): the prior information at step 0 (Sigma_0^-1); F (K, 4, 4) the (closed-loop)
    transition Jacobians at steps 1..K; info (K+1, 4, 4) the expected measurement information
    at steps 0..K. Returns the bounds J_k^-1 for k = 0..K: (K+1, 4, 4).
    """
    J = J0 + info[0]
    out = [np.linalg.inv(J)]
    for k in range(len(F)):
        P = F[k] @ out[-1] @ F[k].T + Q
        J = np.linalg.inv(P) + info[k + 1]
        out.append(np.linalg.inv(J))
    return np.array(out)


def pcrb_position(model, initial_cov: np.ndarray, truth: np.ndarray, gains: np.ndarray, sensors: np.ndarray,
                  sigma_rad: float, reduction: float = 1.0) -> np.ndarray:
    """Posterior Cramer-Rao bound of each target's horizontal position along a trial: (K, M),
    the trace of the (x, y) block of the bound, m^2.

    ``pcrb`` on the planar state [px, py, vx, vy] with, per step, the
    closed-loop transition Jacobian F_k = A + B du/dx of the target's guidance at its true state
    (``gains`` (K-1, M, 3, 6) from ``sim.truth.world``: the targets steer by feedback toward a known
    goal, so treating the control as a known input would give a bound above what a filter that
    knows the policy achieves), process noise Q, prior Sigma_0, and the measurement information
    of one bearing per sensor and tick, q h h^T / sigma^2 at the true position (``reduction`` q:
    p_D and clutter, ``information_reduction_factor``). truth (K, M, 6); sensors (K, S, 2) the
    sensor positions at each tick (the flown UAV path, or the fixed DFs repeated).
    """
    A, B, Q = planar_model(model)
    P0 = np.asarray(initial_cov, float)[np.ix_(PLANAR, PLANAR)]
    K, M = truth.shape[:2]
    out = np.zeros((K, M))
    for j in range(M):
        info = bearing_information(truth[:, None, j, :2], sensors[:, :, :2], sigma_rad, reduction).sum(axis=1)
        F = A[None] + B[None] @ np.asarray(gains, float)[:K - 1, j, :2][:, :, PLANAR]  # (K-1, 4, 4)
        bound = pcrb(np.linalg.inv(P0), F, Q, info)
        out[:, j] = bound[:, 0, 0] + bound[:, 1, 1]
    return out


@dataclass(frozen=True, eq=False)
class MethodTrace:
    """One method on one trial: (K, M) arrays over ticks and targets unless stated."""

    error_m: np.ndarray  # horizontal position error |x^ - x|
    nees: np.ndarray  # 2-D position NEES
    estimate_xy: np.ndarray  # (K, M, 2) posterior mean positions
    uav: np.ndarray | None  # (K, 3) where each scan was taken (None: fixed sensors)
    degenerate: int  # updates that left no finite weight (prior kept)
    tick_s: float  # mean wall time of a tick
    bound_m2: np.ndarray | None = None  # (K, M) PCRB of the position (trace, m^2) along this path
    # a flown method (Method's docstring): per tick k < K-1, the flown position at k+1 from the
    # planned one (m), the plan's speed at k+1 (m/s); per tick, the vehicle's speed (m/s)
    plan_miss_m: np.ndarray | None = None
    plan_speed_mps: np.ndarray | None = None
    speed_mps: np.ndarray | None = None
    # a filter with motion modes: per tick and target, the posterior probability of what the target
    # really does (its true goal's mode, or stationary; NaN where no mode is its truth)
    true_mode_prob: np.ndarray | None = None
    reseeds: np.ndarray | None = None  # (K, M) bool: re-seeded along the bearings at that tick


@dataclass(frozen=True, eq=False)
class TrialResult:
    trial: int
    start: np.ndarray  # (3,) the UAV start of this trial
    truth: np.ndarray  # (K, M, 6) true states at the ticks
    traces: dict[str, MethodTrace]
    wall_s: float
    gains: np.ndarray | None = None  # (K-1, M, 3, 6) closed-loop guidance gains at the true states


@dataclass(frozen=True, eq=False)
class MethodSummary:
    name: str
    description: str
    rmse_t: np.ndarray  # (K, M) eps_t per target
    rmse_t_mean: np.ndarray  # (K,) averaged over targets
    rmse_mean_m: float  # time average of rmse_t_mean over the window
    rmse_target_m: np.ndarray  # (M,) time average per target over the window
    per_trial_rmse: np.ndarray  # (N,) r_n over the window
    anees_t: np.ndarray  # (K, M)
    nees_mean: float
    nees_in_band: float  # fraction of (step, target) cells in the N-trial band
    diff_vs_ref: tuple[float, float, float] | None  # mean, lo, hi of r_n - r_n(ref)
    ratio_vs_ref: tuple[float, float, float] | None  # rmse_mean_m(ref) / rmse_mean_m, 95 % bootstrap CI
    motion: dict  # UAV motion statistics (empty for fixed sensors)
    tick_ms: float
    degenerate: int
    bound_mean_m: float = float("nan")  # the PCRB, averaged like rmse_mean_m (sqrt of the trial mean)
    bound_t_mean: np.ndarray | None = None  # (K,) the bound per step, averaged over targets
    # vehicle method whose jump twin ran: (twin, rmse_mean_m / twin's with its 95 % paired CI)
    vs_jump: tuple[str, tuple[float, float, float]] | None = None
    flown: dict = field(default_factory=dict)  # a flown method: how the vehicle flew its plans (_flown_stats)
    truth: dict = field(default_factory=dict)  # how far off and how sure on the truth (truth_stats)

    @property
    def rmse_over_bound(self) -> float:
        return self.rmse_mean_m / self.bound_mean_m


@dataclass(frozen=True, eq=False)
class Summary:
    config: Any  # sim.evaluation.trials.EvalConfig
    methods: dict[str, MethodSummary]
    nees_band: tuple[float, float]
    ratio: float | None  # greedy_l1 / fixed3
    ratio_ci: tuple[float, float] | None
    wall_s: float
    n_trials: int
    target_speed_10s: tuple[float, ...] = ()  # the true targets' mean speed per 10 s of mission, m/s
    # the flight default (a method named flight, flight@..., flight~...) against every other method
    # of the run: {(flight method, other): ((ratio, lo, hi) of RMSEs, (mean, lo, hi) of per-trial
    # differences)}, paired over the trials
    pairs: dict = field(default_factory=dict)
    # a run with a bound-only method (the clairvoyant ceiling): {"name": its name, "limits": {method:
    # the motion it planned with, text}, "ratios": {UAV method: ((ratio, lo, hi) of the PCRBs, method /
    # ceiling, paired bootstrap CI; per-trial ratios of the window PCRBs (N,))}}
    ceiling: dict = field(default_factory=dict)


def is_flight(name: str) -> bool:
    """The flight default, with its autopilot (``@``) or a variant of it (``~``)."""
    return name.partition("@")[0].partition("~")[0] == "flight"


def paired_ratio(a: np.ndarray, b: np.ndarray, w0: int, seed: int) -> tuple[float, float, float]:
    """rmse_mean_m(a) / rmse_mean_m(b) for error arrays (N, K, M) of the same trials, with a 95 %
    paired percentile bootstrap CI (trials resampled with replacement, both methods together)."""
    ratio = window_mean_rmse(a, w0) / window_mean_rmse(b, w0)
    N = len(a)
    if N < 2:
        return ratio, float("nan"), float("nan")
    boot_rng = seeded_rng(seed, 2**31 - 2)  # its own stream: does not touch any trial's
    rs = [window_mean_rmse(a[idx], w0) / window_mean_rmse(b[idx], w0)
          for idx in (boot_rng.integers(0, N, N) for _ in range(BOOTSTRAP_RESAMPLES))]
    return ratio, float(np.percentile(rs, 2.5)), float(np.percentile(rs, 97.5))


def bound_window(b: np.ndarray, w0: int) -> float:
    """bounds (N, K, M) m^2 -> the PCRB as ``bound_summary`` averages it (sqrt of the trial mean,
    over targets, over the window), m."""
    return float(np.sqrt(np.mean(b, axis=0)).mean(axis=1)[w0:].mean())


def paired_bound_ratio(a: np.ndarray, b: np.ndarray, w0: int, seed: int) -> tuple[float, float, float]:
    """PCRB(a) / PCRB(b) for bounds (N, K, M) of the same trials, with the 95 % paired percentile
    bootstrap CI of ``paired_ratio`` (the same resamples)."""
    ratio = bound_window(a, w0) / bound_window(b, w0)
    N = len(a)
    if N < 2:
        return ratio, float("nan"), float("nan")
    boot_rng = seeded_rng(seed, 2**31 - 2)
    rs = [bound_window(a[idx], w0) / bound_window(b[idx], w0)
          for idx in (boot_rng.integers(0, N, N) for _ in range(BOOTSTRAP_RESAMPLES))]
    return ratio, float(np.percentile(rs, 2.5)), float(np.percentile(rs, 97.5))


def bound_summary(bounds: list, w0: int) -> tuple[float, np.ndarray | None]:
    if any(b is None for b in bounds):
        return float("nan"), None
    b = np.sqrt(np.mean(np.stack(bounds), axis=0)).mean(axis=1)  # (K,): like eps_t, over targets
    return float(b[w0:].mean()), b


def window_mean_rmse(err: np.ndarray, w0: int) -> float:
    """err (N, K, M) -> time average over the window of the target-averaged eps_t."""
    eps = np.sqrt(np.mean(err ** 2, axis=0))  # (K, M)
    return float(eps[w0:].mean())


def motion_stats(trace: MethodTrace, truth: np.ndarray) -> dict:
    """How a UAV moved: step lengths, and the step's component toward/away from and across the
    lines of sight to the true targets (averaged over targets)."""
    u = trace.uav[:, :2]
    move = np.diff(u, axis=0)  # (K-1, 2)
    length = np.linalg.norm(move, axis=1)
    los = truth[:-1, :, :2] - u[:-1, None, :]  # (K-1, M, 2) UAV -> target
    rng_m = np.linalg.norm(los, axis=2)
    unit = los / np.maximum(rng_m, 1e-9)[..., None]
    along = np.einsum("kd,kmd->km", move, unit)  # + toward the target
    across = np.abs(unit[..., 0] * move[:, None, 1] - unit[..., 1] * move[:, None, 0])
    return dict(step_m=length, away_m=-along.mean(axis=1), across_m=across.mean(axis=1),
                range_m=np.linalg.norm(truth[:, :, :2] - u[:, None, :], axis=2).mean(axis=1))


FAR_M = 100.0  # a target estimated farther off than this is lost
MODE_AT_S = 40.0  # when the true mode's probability is read


def truth_stats(traces, w0: int, dt_s: float) -> dict:
    """Over the trials' traces of one method: the share of (tick, target) cells from tick ``w0``
    more than FAR_M off, the targets more than FAR_M off at the last tick (count, of how many),
    and, for a filter with modes, the share of targets whose true mode holds >= 0.9 at MODE_AT_S."""
    err = np.stack([t.error_m for t in traces])  # (N, K, M)
    out = {"far_fraction": float(np.mean(err[:, w0:] > FAR_M)), "lost_at_end": int(np.sum(err[:, -1] > FAR_M)),
           "targets": int(err.shape[0] * err.shape[2])}
    if traces[0].reseeds is not None:
        out["reseeds"] = int(sum(int(t.reseeds.sum()) for t in traces))
    probs = [t.true_mode_prob for t in traces if t.true_mode_prob is not None]
    k = int(round(MODE_AT_S / dt_s))
    if probs and k < probs[0].shape[0]:
        at = np.stack([p[k] for p in probs])  # (N, M)
        if np.isfinite(at).any():
            out["true_mode_p90_at_40s"] = float(np.mean(at[np.isfinite(at)] >= 0.9))
            out["true_mode_mean_at_40s"] = float(np.nanmean(at))
    return out


NEAR_M = 60.0  # a target this close to an obstacle box (m, plan view) counts as rounding it


def error_split(cfg, results, m: str) -> dict:
    """Where a UAV method's window error lies: its RMS along and across each target's line of
    sight from the UAV (m; along: the range error a bearing cannot see), for the ticks a target
    is within ``NEAR_M`` of an obstacle (rounding it: the side the filter may not know) and the
    rest, with each part's share of the squared error and its mean range (m)."""
    boxes = [(np.asarray(b.center_m[:2], float), np.asarray(b.size_m[:2], float) / 2) for b in cfg.scenario.obstacles]
    w = slice(cfg.window_start, None)
    parts = {"near": [], "free": []}
    for r in results:
        t = r.truth[w, :, :2]  # (K, M, 2)
        e = r.traces[m].estimate_xy[w] - t
        los = t - r.traces[m].uav[w, None, :2]
        rng_m = np.linalg.norm(los, axis=2)
        u = los / np.maximum(rng_m, 1e-9)[..., None]
        along = np.sum(e * u, axis=2)
        across = e[..., 1] * u[..., 0] - e[..., 0] * u[..., 1]
        d = np.min([np.linalg.norm(np.maximum(np.abs(t - c) - h, 0.0), axis=2) for c, h in boxes], axis=0) \
            if boxes else np.full(rng_m.shape, np.inf)
        for key, sel in (("near", d < NEAR_M), ("free", d >= NEAR_M)):
            parts[key].append(np.stack([along[sel], across[sel], rng_m[sel]]))
    total = sum(float(np.sum(np.hstack(v)[:2] ** 2)) for v in parts.values())
    out = {}
    for key, v in parts.items():
        a = np.hstack(v)
        if a.shape[1]:
            out[key] = {"share": round(float(np.sum(a[:2] ** 2)) / total, 2), "cells": int(a.shape[1]),
                        "along_m": round(float(np.sqrt(np.mean(a[0] ** 2))), 1),
                        "across_m": round(float(np.sqrt(np.mean(a[1] ** 2))), 1),
                        "range_m": round(float(np.mean(a[2])))}
    return out
