"""The lookahead's multi-step EKF route score against a particle rollout of the same routes.

    python -m bench.route_score [--ticks 10,25,40,60,80] [--particles 2000] [--motion jump]
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

from sim.evaluation.workers import one_blas_thread  # no numpy import

one_blas_thread()  # before numpy loads: one core's figures

import argparse
import json

import numpy as np
from scipy import stats

from bench import add_set_option, set_label, set_overrides
from onboard.config import load_scenario, override
from onboard.core.monitor import MonitorSetup
from sim.evaluation.route_score import compare_routes, snapshots
from onboard.policy import with_policy


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
