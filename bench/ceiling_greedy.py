"""The myopic far path of issue 29 as a bench method (``myopic9``), flown on the evaluation's truths.

Each tick the UAV goes to one of 33 points within 9 m (stay, and 16 headings at 4.5 and 9 m),
the admissible one (area, obstacles: ``planning.admissible``) that minimises the summed
Frobenius norm of the targets' position covariances after one ideal bearing from it (EKF form,
``information.kalman_pseudo_update``, with the bound's q), from the predicted particle clouds:
a one-step covariance-norm reward, no acceleration limit (a jump of at most 9 m per tick). The
issue describes the rule, not its code; this is our reading of it. It is a planner like the
product's (``onboard.core.planning.planners.Planner``), registered here for the bench only (not a setting
the app accepts); its bearings run through our own filter (the evaluation's ``run_method``: same
truth, same start).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.config import load_scenario
from onboard.core.planning.information import information_reduction_factor, kalman_pseudo_update
from onboard.core.planner_choice import register_planner
from onboard.core.planning.planners import Area, Planner, PlanningInputs
from onboard.core.planning.next_position import PlanningResult
from onboard.core.tracking.filter import logsumexp
from sim.evaluation import trials as ev
from sim.evaluation.methods import PAPER

NAME = "myopic9"


def candidates(uav: np.ndarray, altitude_m: float, reach_m: float = 9.0, n_headings: int = 16) -> np.ndarray:
    """Stay, then n_headings points at reach/2 and at reach: (1 + 2 n, 3)."""
    ang = np.arange(n_headings) * 2.0 * np.pi / n_headings
    ring = np.column_stack([np.cos(ang), np.sin(ang)])
    xy = np.vstack([[0.0, 0.0], 0.5 * reach_m * ring, reach_m * ring]) + np.asarray(uav, float)[:2]
    return np.column_stack([xy, np.full(len(xy), altitude_m)])


@dataclass(frozen=True, eq=False)
class MyopicPlanner(Planner):
    """The 33 points within 9 m, scored by the summed Frobenius norm of the pseudo-updated
    position covariances."""

    altitude_m: float
    area: Area
    sigma_rad: float
    reduction: float  # the bound's information reduction factor q

    def plan(self, inputs: PlanningInputs, rng: np.random.Generator) -> PlanningResult:
        uav = np.asarray(inputs.position, float)
        cand = candidates(uav, self.altitude_m)
        ok = self.area.admissible(cand, uav)
        w = np.exp(inputs.log_weights - logsumexp(inputs.log_weights, axis=1, keepdims=True))  # (M, N)
        x = inputs.particles[:, :, [0, 1, 3, 4]]
        mu = np.einsum("mn,mnd->md", w, x)
        dev = x - mu[:, None]
        covs = np.einsum("mn,mnd,mne->mde", w, dev, dev)
        P = kalman_pseudo_update(covs[None], mu[None, :, :2], cand[:, None, :2], self.sigma_rad, self.reduction)
        traces = np.linalg.norm(P[..., :2, :2], axis=(-2, -1))  # (C, M)
        scores = np.where(ok, traces.sum(axis=1), np.inf)
        index = int(np.argmin(scores)) if ok.any() else None
        return PlanningResult(cand, ok, traces, scores, index)


def _myopic(setup) -> Planner:
    s = setup.sensor
    area = Area(setup.area_min, setup.area_max, setup.uav_obstacles)
    return MyopicPlanner(setup.grid.altitude_m, area, s.sigma_rad,
                         information_reduction_factor(s.p_detect, s.clutter_rate, s.sigma_rad))


def register() -> None:
    register_planner(NAME, _myopic)
    ev.register_method(ev.Method(NAME, "single UAV, one-step greedy among 33 points within 9 m, covariance-norm "
                                 "reward (bench/ceiling_greedy.py), Lambda = 1", planner=NAME, clutter_rate=1.0,
                                 scenario_overrides=PAPER))


def run_greedy(seed: int, trial: int, d: dict) -> ev.MethodTrace:
    """``myopic9`` on one cached trial (truth, gains, start of ``pmon eval``)."""
    register()
    cfg = ev.make_config(load_scenario("paper"), trial + 1, seed, methods=[NAME])
    return ev.run_method(cfg, cfg.methods[0], trial, d["truth"], d["start"], d["gains"])
