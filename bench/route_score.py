"""The lookahead's multi-step EKF route score against a particle rollout of the same routes.

    python bench/route_score.py [--ticks 10,25,40,60,80] [--particles 2000] [--motion jump]
                                [--seed 1] [--set KEY=VALUE ...]

The planner (docs/PLANNING.md, "The route planner") scores each of its ~150 routes over H = 50 ticks with a
Gaussian (EKF) pseudo-update per tick; the one-step form is checked against the paper's particle
pseudo-update in tests/core/test_information.py. This bench checks the whole score. It flies the
closed loop of bench/planner.py (the paper scenario, lookahead planner). At each tick named, it
takes the inputs of that tick's plan: the predicted particles of every target, the guidance
plans and the candidate routes with their EKF scores. It then scores the same routes with
particles. Each target's cloud is propagated about its plan with the planar model,
x_k = mu_k + A (x_(k-1) - mu_(k-1)) + w, w ~ N(0, Q), which is the EKF's own linearisation. It
is re-weighted at each tick by the ideal bearing from the route's position at k to mu_k (variance
sigma^2 / q, as the EKF), and resampled (systematic) when its effective size falls under half.
Route score: the sum over ticks and targets of the weighted position variance. Every route sees
the same noise draws (common random numbers).

The particle score is the mean of ``--rollouts`` independent rollouts. Printed per tick: the
Spearman rank correlation of the EKF and particle scores over the admissible routes, and, as its
noise floor, that of two rollouts with each other (many routes score within a few per cent of
each other, so the rollout's own Monte Carlo noise reorders them); where the EKF's chosen route
ranks among the particle scores; the particle score of the EKF's choice over the particle
optimum minus 1 (the regret of planning with the EKF, as a share); and the median EKF / particle
score ratio (the EKF is conservative close in, docs/PLANNING.md). Last line: JSON figures.
"""
from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402
from scipy.special import logsumexp  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench import add_set_option, closed_loop, set_label, set_overrides  # noqa: E402
from onboard.config import load_scenario, override  # noqa: E402
from onboard.core.bearings import bearing, wrap  # noqa: E402
from onboard.core.dynamics import PLANAR  # noqa: E402
from onboard.core.information import information_reduction_factor, planar_model  # noqa: E402
from onboard.core.monitor import MonitorSetup  # noqa: E402
from onboard.core.tracking import systematic_indices  # noqa: E402
from onboard.policy import with_policy  # noqa: E402


def particle_route_scores(particles: np.ndarray, log_weights: np.ndarray, plans: np.ndarray,
                          routes: np.ndarray, A: np.ndarray, Q: np.ndarray, sigma_rad: float,
                          reduction: float, rng: np.random.Generator) -> np.ndarray:
    """Sum over the horizon of the weighted position variance of each target's particle cloud,
    per route and target: (C, M).

    particles (M, N, 4) planar, log_weights (M, N): the predicted beliefs at t+1; plans (M, H, 4):
    mu_(t+1..t+H); routes (C, H, 2): the sensor's positions at t+1..t+H.
    """
    M, N, _ = particles.shape
    C, H, _ = routes.shape
    x = np.broadcast_to(particles, (C, M, N, 4)).copy()
    logw = np.broadcast_to(log_weights - logsumexp(log_weights, axis=1, keepdims=True), (C, M, N)).copy()
    L = np.linalg.cholesky(Q + 1e-12 * np.eye(4))
    total = np.zeros((C, M))
    for k in range(H):
        if k:  # linear about the plan, the same noise for every route (common random numbers)
            w = rng.standard_normal((M, N, 4)) @ L.T
            x = plans[None, :, k, None] + (x - plans[None, :, k - 1, None]) @ A.T + w[None]
        s = routes[:, None, k]  # (C, 1, 2)
        z = bearing(plans[None, :, k, :2], s)  # (C, M) ideal bearings to the planned positions
        pred = bearing(x[..., :2], s[:, :, None])  # (C, M, N)
        logw += -0.5 * reduction * (wrap(z[..., None] - pred) / sigma_rad) ** 2
        logw -= logsumexp(logw, axis=2, keepdims=True)
        wt = np.exp(logw)
        m1 = np.einsum("cmn,cmnd->cmd", wt, x[..., :2])
        m2 = np.einsum("cmn,cmnd->cmd", wt, x[..., :2] ** 2)
        total += np.sum(m2 - m1 ** 2, axis=2)
        ess = 1.0 / np.sum(wt ** 2, axis=2)  # (C, M)
        xf, lf, wf = x.reshape(C * M, N, 4), logw.reshape(C * M, N), wt.reshape(C * M, N)  # views
        for r in np.flatnonzero(ess.ravel() < 0.5 * N):
            xf[r] = xf[r][systematic_indices(wf[r], rng)]
            lf[r] = -np.log(N)
    return total


def snapshots(setup: MonitorSetup, ticks: set[int], seed: int, start_xy=(150.0, 200.0)):
    """bench.closed_loop from the UAV at start_xy (m, ENU); yields, at each tick in ticks,
    (tick, particles (M, N, 4), log_w, plans (M, H, 4), planning, uav) of that tick's plan."""
    for k, state, res, uav in closed_loop(setup, max(ticks) + 1, seed, start_xy):
        p = res.planning
        if k in ticks and p is not None and p.paths is not None:
            yield (k, np.stack([b.particles[:, PLANAR] for b in state.beliefs]),
                   np.stack([b.log_weights for b in state.beliefs]),
                   np.stack([pl.means[:setup.lookahead_steps][:, PLANAR] for pl in res.plans]), p, uav)


def compare_routes(setup: MonitorSetup, particles: np.ndarray, log_w: np.ndarray, plans: np.ndarray,
                   planning, rollouts: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The EKF scores of the admissible routes of ``planning`` (C,) and their particle scores
    summed over targets from ``rollouts`` independent rollouts (rollouts, C), on a snapshot."""
    A, _, Q = planar_model(setup.model)
    q = information_reduction_factor(setup.sensor.p_detect, setup.sensor.clutter_rate, setup.sensor.sigma_rad)
    ok = np.flatnonzero(planning.admissible)
    runs = [particle_route_scores(particles, log_w, plans, planning.paths[ok, :, :2], A, Q, setup.sensor.sigma_rad,
                                  q, rng).sum(axis=1) for _ in range(rollouts)]
    return planning.scores[ok], np.array(runs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ticks", default="10,25,40,60,80", help="ticks of the closed loop to compare at")
    ap.add_argument("--particles", type=int, default=2000, help="particles per target in the rollout")
    ap.add_argument("--rollouts", type=int, default=2,
                    help="independent particle rollouts averaged (two or more also give their noise floor)")
    ap.add_argument("--motion", choices=("jump", "vehicle"), default="jump")
    ap.add_argument("--seed", type=int, default=1)
    add_set_option(ap)
    args = ap.parse_args()
    try:
        ticks = {int(t) for t in args.ticks.split(",")}
    except ValueError:
        ap.error(f"--ticks: comma-separated integers, got {args.ticks!r}")
    if min(ticks) < 1:
        ap.error("--ticks: from 1 (the first tick has no plan to compare yet)")
    if args.particles < 100 or args.rollouts < 1:
        ap.error("--particles: at least 100; --rollouts: at least 1")
    sc = load_scenario("paper", set_overrides(ap, args))
    setup = MonitorSetup.from_scenario(override(with_policy(sc, "paper"),  # the paper's filter
                                                {"planning.planner": "lookahead", "planning.motion": args.motion}))
    rng = np.random.default_rng(args.seed + 1000)
    print(f"paper scenario{set_label(args)}, lookahead/{args.motion}, H = {setup.lookahead_steps}, "
          f"{args.rollouts} rollouts of {args.particles} particles per target, seed {args.seed}")
    print(f"{'tick':>4s} {'routes':>6s} {'range m':>8s} {'spearman':>8s} {'floor':>6s} {'EKF pick rank':>13s} "
          f"{'regret':>7s} {'EKF/particle':>12s}")
    out = []
    for k, particles, log_w, plans, p, uav in snapshots(setup, ticks, args.seed):
        n = particles.shape[1]
        if args.particles < n:  # a uniform subsample of the particles, weights kept
            keep = rng.choice(n, args.particles, replace=False)
            particles, log_w = particles[:, keep], log_w[:, keep]
        ekf, runs = compare_routes(setup, particles, log_w, plans, p, args.rollouts, rng)
        part = runs.mean(axis=0)
        floor = float(stats.spearmanr(runs[0], runs[1]).statistic) if len(runs) > 1 else float("nan")
        rho = float(stats.spearmanr(ekf, part).statistic)
        pick = int(np.argmin(ekf))
        rank = int(np.sum(part < part[pick])) + 1
        regret = float(part[pick] / part.min() - 1.0)
        ratio = float(np.median(ekf / part))
        rng_m = float(np.mean(np.linalg.norm(plans[:, 0, :2] - uav[:2], axis=1)))
        print(f"{k:4d} {len(ekf):6d} {rng_m:8.0f} {rho:8.3f} {floor:6.3f} {rank:>9d}/{len(ekf):<3d} "
              f"{100 * regret:6.1f}% {ratio:12.2f}")
        out.append({"tick": k, "routes": len(ekf), "range_m": round(rng_m, 1), "spearman": round(rho, 4),
                    "rollout_spearman": round(floor, 4), "ekf_pick_rank": rank, "regret": round(regret, 4),
                    "ekf_over_particle_median": round(ratio, 3)})
    print(json.dumps({"motion": args.motion, "particles": args.particles, "rollouts": args.rollouts,
                      "snapshots": out}))


if __name__ == "__main__":
    main()
