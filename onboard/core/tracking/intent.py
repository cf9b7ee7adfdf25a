"""What a target intends: a discrete motion mode per particle (docs/TRACKING.md "Intent").

A target's belief is a multiple-model particle filter: each particle carries a mode,

* ``k >= 0``   heading for candidate goal k with the P1 guidance (the paper's model, eq. (1)-(3)
               with the goal G_o replaced by the k-th candidate),
* ``STATIONARY`` standing still (a transmitter being hunted, a target that stopped),
* ``FREE``     drifting: the model's motion with no control (friction slows it) and a random
               acceleration, speed-bounded, kept in the area and out of the obstacles (a target
               that stopped commanding, wanders, or has arrived),
* ``AIMED``    heading for a destination of its own, drawn uniformly over the area when the
               particle takes the mode: the guidance's unconstrained optimum toward it (its free
               law, inputs clipped to P1's box, speed to its bound), so a target heading somewhere
               nobody named moves as the model's targets do,

and the modes switch by a Markov chain: each tick a target keeps its mode with probability
1 - p_switch, else takes one drawn from its prior (``mix_resample``). The mode probabilities
are the particle weights summed per mode, so the bearings estimate them (a jump-Markov / multiple-model particle
filter: Ristic, Arulampalam and Gordon, Beyond the Kalman Filter (2004), ch. 3 and 11;
McGinnity and Irwin, "Multiple model bootstrap filter for maneuvering target tracking", IEEE
TAES 36(3), 2000). Intent inference with one model per destination follows Ahmad, Godsill et al.,
"Bayesian intent prediction in object tracking using bridging distributions", IEEE Trans.
Cybernetics 48(1), 2018, in its simplest discrete form.

Pure numpy: every random number from the caller's Generator.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from onboard.core.dynamics import MotionModel
from onboard.core.obstacles import Obstacles

STATIONARY = -1
FREE = -2
AIMED = -3
MOTION_MODES = ("stationary", "free", "elsewhere")  # the operator's names of STATIONARY, FREE, AIMED

# The innovation monitor (docs/TRACKING.md "Honest when surprised"): a scan is unexplained when no
# bearing falls where the belief predicts one (``explained`` < EXPLAINED_MIN: the best bearing
# off the cloud by about 3 of its spreads); a target with SURPRISE_COUNT unexplained of its last
# SURPRISE_WINDOW scans with bearings is re-seeded. A missed detection (1 - p_D = 5 % a scan) makes
# one; four of six by chance is a 1e-4 event a tick.
EXPLAINED_MIN = 2.0
SURPRISE_WINDOW = 6
SURPRISE_COUNT = 4
RESEED_SHARE = 0.3  # the share of the particles re-drawn along the bearings
RESEED_SIGMA_M = 300.0  # the re-seed's width about the estimate: most of a 1 km area
RESEED_PRIOR = 0.5  # the re-seed's weight in the predicted mixture
RESEED_SPEED_MPS = 5.0  # a re-seeded free particle's velocity spread, per axis
MIN_MODE_SHARE = 0.05  # of the particles, every mode keeps at least this share (``mix_resample``)
AIM_REDRAW = 0.05  # per tick, the share of AIMED particles that take a new destination
STATIONARY_SIGMA_M = 0.5  # a stationary particle's position jitter per tick


@dataclass(frozen=True, eq=False)
class Intent:
    """What the scenario says one target may do: candidate goals (K, 3) ENU m with their names,
    and the prior over its modes, (K + 3,): the goals', then STATIONARY's, FREE's and AIMED's
    (sums to 1)."""

    goals: np.ndarray
    names: tuple[str, ...]
    prior: np.ndarray

    def __post_init__(self):
        if len(self.prior) != len(self.goals) + 3 or not np.isclose(self.prior.sum(), 1.0):
            raise ValueError("an intent's prior has one entry per goal, then stationary, free and aimed, "
                             "summing to 1")

    @property
    def n_goals(self) -> int:
        return len(self.goals)

    def label(self, column: int) -> str:
        """The operator's name of a mode column: a goal's name, or one of ``MOTION_MODES``."""
        return self.names[column] if column < self.n_goals else MOTION_MODES[column - self.n_goals]


@dataclass(frozen=True)
class IntentParams:
    """How the modes move and switch (onboard/settings/sections.py ``tracking.intent_*`` declares the values)."""

    switch_prob: float  # per tick: a target takes a mode drawn from its prior
    free_accel_sigma_mps2: float  # FREE: white acceleration, per axis
    speed_max_mps: float  # FREE: speed bound (the guidance's)
    stationary_sigma_m: float  # STATIONARY: position jitter per tick, per axis
    recovery_prior_raise: float = 0.0  # the recovery's prior raised by this x the unpredicted weight
    recovery_sigma_raise_m: float = 0.0  # and its width (m) by this x that weight
    start_speed_mps: float = 0.0  # a particle leaving STATIONARY: velocity N(0, this^2) per axis
    goal_switch_share: float = 1.0  # a goal particle's switch to another candidate goal at this share of the prior


def unpredicted_weight(ps) -> float:
    """The share of a belief's weight in FREE and AIMED: motion no named goal or standing predicts."""
    if ps.modes is None:
        return 0.0
    w = np.exp(ps.log_weights - np.max(ps.log_weights))
    return float(w[(ps.modes == FREE) | (ps.modes == AIMED)].sum() / w.sum())


def raised_recovery(rec, unpredicted: float, params: IntentParams):
    """``rec`` (``tracking.Recovery``) for a target whose weight ``unpredicted`` lies in FREE and
    AIMED: its prior raised by ``recovery_prior_raise`` and its width by ``recovery_sigma_raise_m``
    times that weight (prior capped at 0.5). Along the line of sight the bearings of one platform
    say little, so a belief whose motion no goal explains is searched for along the whole bearing;
    one the bearings place on a goal keeps the configured recovery and its accuracy."""
    if unpredicted <= 0.0 or (params.recovery_prior_raise <= 0.0 and params.recovery_sigma_raise_m <= 0.0):
        return rec
    return replace(rec, prior=min(0.5, rec.prior + params.recovery_prior_raise * unpredicted),
                   sigma_m=rec.sigma_m + params.recovery_sigma_raise_m * unpredicted)


def columns(modes: np.ndarray, n_goals: int) -> np.ndarray:
    """Mode codes (n,) to columns 0..K+2 of ``Intent.prior``: goal k -> k, STATIONARY -> K, FREE -> K+1,
    AIMED -> K+2."""
    modes = np.asarray(modes)
    return np.where(modes >= 0, modes, n_goals - 1 - modes)


def codes(cols: np.ndarray, n_goals: int) -> np.ndarray:
    """Columns back to mode codes (``columns``' inverse)."""
    cols = np.asarray(cols)
    return np.where(cols < n_goals, cols, n_goals - 1 - cols)


def draw(intent: Intent, n: int, rng: np.random.Generator) -> np.ndarray:
    """n mode codes from the intent's prior."""
    return codes(rng.choice(len(intent.prior), size=n, p=intent.prior), intent.n_goals)


def probabilities(log_weights: np.ndarray, modes: np.ndarray, n_goals: int) -> np.ndarray:
    """(K + 3,) the posterior probability of each mode column (weights summed per mode)."""
    w = np.exp(log_weights - np.max(log_weights))
    p = np.bincount(columns(modes, n_goals), weights=w, minlength=n_goals + 3)
    return p / p.sum()


@dataclass(frozen=True, eq=False)
class Mixed:
    """``mix_resample``'s result: each new particle's source index, mode, and log-weight."""

    source: np.ndarray  # (n,) index into the posterior's particles
    modes: np.ndarray  # (n,) mode codes
    log_weights: np.ndarray  # (n,)
    switched: np.ndarray  # (n,) bool: the particle took another mode than its source's


def mix_resample(log_weights: np.ndarray, modes: np.ndarray, intent: Intent, p_switch: float, n: int,
                 min_share: float, rng: np.random.Generator, goal_share: float = 1.0) -> Mixed:
    """The modes' interaction and the resampling of one tick, at the mode level (the particle
    filter form of the IMM's mixing: Blom and Bar-Shalom, IEEE TAC 33(8), 1988; Boers and
    Driessen, IEE Proc. Radar Sonar Navig. 150(5), 2003):

    1. the predicted mode probabilities p'_c = sum_i T_ic p_i (p_i: the posterior's), with the
       Markov chain T_ic = (1 - s) [i = c] + s prior_c f_ic + [i = c] s sum_j prior_j (1 - f_ij):
       a target redraws its mode from the prior at s a tick, except that a switch from one
       candidate goal to another is taken at ``goal_share`` (f_ij, 1 elsewhere) and otherwise
       keeps its goal (a target heading somewhere rarely changes its mind for another exit; it
       stops, wanders or heads off more often);
    2. each mode with p'_c > 0 gets a count of particles: at least ``min_share`` n (so a mode the
       bearings do not favour yet is ready, densely sampled, when they do; at most half the set
       in all), the rest in proportion to p'_c;
    3. mode c's particles are drawn, in the share T_cc p_c / p'_c (its keeping share, less a
       redraw of c itself), from its own posterior particles by weight, and in the rest from the
       whole posterior (particles switching into c: where the target is, whatever its mode was;
       drawn by f too, a goal's switch-ins would come from the standing and free particles alone);
       each weighs p'_c / count_c, so the mode probabilities stay p'.
    """
    K = intent.n_goals
    C = K + 3
    w = np.exp(log_weights - np.max(log_weights))
    w /= w.sum()
    cols = columns(modes, K)
    p = np.bincount(cols, weights=w, minlength=C)
    f = np.ones((C, C))
    f[:K, :K] = goal_share
    np.fill_diagonal(f, 1.0)
    keep = (1.0 - p_switch) + p_switch * ((1.0 - f) @ intent.prior)  # (C,) the share of c that stays c
    pred = keep * p + p_switch * intent.prior * (1.0 if goal_share == 1.0 or K < 2 else p @ f)  # one goal: as 1
    live = pred > 0.0
    floor = min(min_share * n, 0.5 * n / max(1, live.sum()))
    target = np.where(live, floor + (n - floor * live.sum()) * pred / pred.sum(), 0.0)
    counts = np.floor(target).astype(int)
    short = n - counts.sum()
    if short > 0:  # largest remainders
        counts[np.argsort(-(target - counts), kind="stable")[:short]] += 1
    src, out_modes, logw, switched = [], [], [], []
    for c in np.flatnonzero(counts):
        m = counts[c]
        own_w = np.where(cols == c, w, 0.0)
        own_share = keep[c] * p[c] / pred[c]
        n_own = int(round(m * own_share)) if own_w.sum() > 0 else 0
        idx = np.empty(0, dtype=int)
        if n_own:
            idx = _systematic(own_w / own_w.sum(), n_own, rng)
        if m - n_own:
            idx = np.r_[idx, _systematic(w, m - n_own, rng)]
        src.append(idx)
        out_modes.append(np.full(m, codes(c, K)))
        logw.append(np.full(m, np.log(pred[c] / m)))
        switched.append(cols[idx] != c)
    return Mixed(np.concatenate(src), np.concatenate(out_modes), np.concatenate(logw), np.concatenate(switched))


def _systematic(weights: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """m indices drawn systematically by ``weights`` (summing to 1)."""
    cumulative = np.cumsum(weights)
    cumulative[-1] = 1.0
    return np.searchsorted(cumulative, (rng.random() + np.arange(m)) / m, side="right")


def predict_stationary(particles: np.ndarray, params: IntentParams, rng: np.random.Generator) -> np.ndarray:
    """STATIONARY particles one tick on: velocity zero, the plane position jittered."""
    out = particles.copy()
    out[:, 3:] = 0.0
    out[:, :2] += params.stationary_sigma_m * rng.standard_normal((len(out), 2))
    return out


def predict_free(particles: np.ndarray, model: MotionModel, params: IntentParams, obstacles: Obstacles,
                 area_min: np.ndarray, area_max: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """FREE particles one tick on: eq. (1) with no control (the paper's target when it commands
    nothing: friction slows it) and, besides the noise Q, a white acceleration of sigma_a per axis;
    then the speed bound, and held in the area and out of the obstacles (``_bounded``; the
    ground-plane obstacles: ``Obstacles.extruded``)."""
    n = len(particles)
    out = particles @ model.A.T + rng.standard_normal(particles.shape) * model.Q_sqrt
    out[:, 3:5] += params.free_accel_sigma_mps2 * model.dt_s * rng.standard_normal((n, 2))
    return _bounded(particles, out, params, obstacles, area_min, area_max)


def draw_aims(n: int, area_min: np.ndarray, area_max: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(n, 2) destinations uniform over the area's ground plane."""
    lo, hi = np.asarray(area_min, float)[:2], np.asarray(area_max, float)[:2]
    return lo + (hi - lo) * rng.random((n, 2))


@dataclass(frozen=True, eq=False)
class Ground:
    """Where a target may move: the ground-plane obstacles (``Obstacles.extruded``) and the
    area's box, its corners ``minimum`` and ``maximum`` (3,) m."""

    obstacles: Obstacles
    minimum: np.ndarray
    maximum: np.ndarray


def predict_aimed(particles: np.ndarray, aims: np.ndarray, model: MotionModel, law_gain: np.ndarray,
                  u_max_n: float, params: IntentParams, ground: Ground, rng: np.random.Generator) -> np.ndarray:
    """AIMED particles one tick on: eq. (1) with the control of P1's unconstrained optimum toward
    each particle's own destination (``law_gain``: ``FreeLaw.gain``, the optimum being linear in
    the state relative to the goal), clipped to the input box (``u_max_n``), then the speed bound,
    the area and the obstacles (``ground``) as ``predict_free``."""
    rel = particles.copy()
    rel[:, :2] -= aims
    u = rel @ law_gain.T
    u[:, :2] = np.clip(u[:, :2], -u_max_n, u_max_n)
    u[:, 2] = 0.0
    out = particles @ model.A.T + u @ model.B.T + rng.standard_normal(particles.shape) * model.Q_sqrt
    return _bounded(particles, out, params, ground.obstacles, ground.minimum, ground.maximum)


def _bounded(before: np.ndarray, after: np.ndarray, params: IntentParams, obstacles: Obstacles,
             area_min: np.ndarray, area_max: np.ndarray) -> np.ndarray:
    """``after`` with its planar speed capped, held in the area (the velocity component reversed at
    an edge) and, where it would enter an obstacle, stopped where it was (``before``)."""
    out = after.copy()
    v = out[:, 3:5]
    speed = np.linalg.norm(v, axis=1)
    over = speed > params.speed_max_mps
    v[over] *= (params.speed_max_mps / speed[over])[:, None]
    lo, hi = np.asarray(area_min, float)[:2], np.asarray(area_max, float)[:2]
    pos = out[:, :2]
    outside = (pos < lo) | (pos > hi)
    v[outside] = -v[outside]
    np.clip(pos, lo, hi, out=pos)
    if len(obstacles):
        hit = obstacles.contains(np.column_stack([pos, before[:, 2]])).any(axis=1)
        pos[hit] = before[hit, :2]
        v[hit] = 0.0
    out[:, 2], out[:, 5] = before[:, 2], 0.0
    return out


def explained(log_weights: np.ndarray, log_lik: np.ndarray, log_miss: float) -> float:
    """log of how much better the predicted belief explains a scan than "the target was missed and
    every bearing is clutter": log( sum_i w_i g(Z | x_i) / g(Z | missed) ), with ``log_lik`` the
    set likelihood of each particle (``tracking.log_likelihood``, same constant) and ``log_miss``
    its value for a missed target. About log(p_D c / ((1 - p_D) Lambda kappa)) when a bearing falls
    in the cloud's bearing spread, about 0 when none does (a miss, or a target elsewhere)."""
    a = log_weights + log_lik
    m = np.max(a)
    if not np.isfinite(m):
        return 0.0
    return float(m + np.log(np.sum(np.exp(a - m))) - log_miss)


def motion_path(mean: np.ndarray, mode: int, steps: int, model: MotionModel) -> np.ndarray:
    """(steps, 6) the path a STATIONARY or FREE mode predicts from its mean: standing, or constant
    velocity (the planner's view of a target heading nobody knows where)."""
    x = np.asarray(mean, float)
    t = model.dt_s * np.arange(1, steps + 1)[:, None]
    out = np.tile(x, (steps, 1))
    if mode == STATIONARY:
        out[:, 3:] = 0.0
    else:
        out[:, :3] = x[:3] + t * x[3:]
    return out
