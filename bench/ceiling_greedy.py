"""The myopic far path of issue 29 as a bench method (``myopic9``), flown on the evaluation's truths.

Each tick the UAV goes to one of 33 points within 9 m (stay, and 16 headings at 4.5 and 9 m),
the admissible one (area, obstacles: ``planning.admissible``) that minimises the summed
Frobenius norm of the targets' position covariances after one ideal bearing from it (EKF form,
``information.kalman_pseudo_update``, with the bound's q), from the predicted particle clouds:
a one-step covariance-norm reward, no acceleration limit (a jump of at most 9 m per tick). The
issue describes the rule, not its code; this is our reading of it. Its bearings run through our
own filter (the evaluation's ``run_method``: same truth, same start).
"""
from __future__ import annotations

import numpy as np

from onboard.config import load_scenario
from onboard.core.information import information_reduction_factor, kalman_pseudo_update
from onboard.core.planning import admissible
from onboard.core.tracking import logsumexp
from sim import evaluation as ev

NAME = "myopic9"


def candidates(uav: np.ndarray, altitude_m: float, reach_m: float = 9.0, n_headings: int = 16) -> np.ndarray:
    """Stay, then n_headings points at reach/2 and at reach: (1 + 2 n, 3)."""
    ang = np.arange(n_headings) * 2.0 * np.pi / n_headings
    ring = np.column_stack([np.cos(ang), np.sin(ang)])
    xy = np.vstack([[0.0, 0.0], 0.5 * reach_m * ring, reach_m * ring]) + np.asarray(uav, float)[:2]
    return np.column_stack([xy, np.full(len(xy), altitude_m)])


def myopic_policy(ctx: ev.PolicyContext) -> np.ndarray:
    s = ctx.setup
    cand = candidates(ctx.uav, s.grid.altitude_m)
    ok = admissible(cand, ctx.uav, s.area_min, s.area_max, s.uav_obstacles)
    if not ok.any():
        return ctx.uav
    covs, means = [], []
    for b in ctx.state.beliefs:
        w = np.exp(b.log_weights - logsumexp(b.log_weights))
        x = b.particles[:, [0, 1, 3, 4]]
        mu = w @ x
        dev = x - mu
        covs.append((w[:, None] * dev).T @ dev)
        means.append(mu[:2])
    q = information_reduction_factor(s.sensor.p_detect, s.sensor.clutter_rate, s.sensor.sigma_rad)
    P = kalman_pseudo_update(np.array(covs)[None], np.array(means)[None], cand[:, None, :2], s.sensor.sigma_rad, q)
    score = np.linalg.norm(P[..., :2, :2], axis=(-2, -1)).sum(axis=1)
    score[~ok] = np.inf
    return cand[int(np.argmin(score))]


def register() -> None:
    ev.register_method(ev.Method(NAME, "single UAV, one-step greedy among 33 points within 9 m, covariance-norm "
                                 "reward (bench/ceiling_greedy.py), Lambda = 1", policy=myopic_policy,
                                 clutter_rate=1.0))


def run_greedy(seed: int, trial: int, d: dict) -> ev.MethodTrace:
    """``myopic9`` on one cached trial (truth, gains, start of ``pmon eval``)."""
    register()
    cfg = ev.make_config(load_scenario("paper"), trial + 1, seed, methods=[NAME])
    return ev.run_method(cfg, cfg.methods[0], trial, d["truth"], d["start"], d["gains"])
