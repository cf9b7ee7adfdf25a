"""The evaluation's baseline planners, planners like the flight ones (``onboard.core.planning.planners.Planner``)
that nothing flies: ``hover`` (stays at its start), ``orbit`` (a circle around the targets'
initial centroid), ``random`` (a uniformly random admissible candidate of S_(t+1)).

``register_baselines`` puts them in the planner registry (``onboard.core.planner_choice.register_planner``)
under those names; sim/evaluation/methods.py does so before it declares the methods that name them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from onboard.core.planner_choice import area_of, register_planner
from onboard.core.planning.planners import Planner, PlanningInputs
from onboard.core.planning.next_position import Area, PlanningResult, candidate_positions
from onboard.core.planning.inputs import CandidateGrid

if TYPE_CHECKING:
    from onboard.core.monitor_setup import MonitorSetup

ORBIT_RADIUS_M = 150.0  # the orbit baseline's circle around the targets' initial centroid


def _chosen(candidates: np.ndarray, ok: np.ndarray, index: int | None, n_targets: int) -> PlanningResult:
    """A baseline's result: its candidates, unscored (0 where admissible), and its choice."""
    return PlanningResult(candidates, ok, np.zeros((len(candidates), n_targets)), np.where(ok, 0.0, np.inf), index)


class HoverPlanner(Planner):
    """Stays where it is."""

    def plan(self, inputs: PlanningInputs, rng: np.random.Generator) -> PlanningResult:
        here = np.asarray(inputs.position, float)
        return _chosen(here[None], np.ones(1, dtype=bool), 0, len(inputs.beliefs))


@dataclass(frozen=True, eq=False)
class RandomPlanner(Planner):
    """A uniformly random admissible candidate of S_(t+1) ("stay" included), drawn from ``rng``."""

    grid: CandidateGrid
    area: Area

    def plan(self, inputs: PlanningInputs, rng: np.random.Generator) -> PlanningResult:
        cand = candidate_positions(inputs.position, self.grid)
        ok = self.area.admissible(cand, inputs.position)
        index = None if not ok.any() else int(rng.choice(np.flatnonzero(ok)))
        return _chosen(cand, ok, index, len(inputs.beliefs))


@dataclass(frozen=True, eq=False)
class OrbitPlanner(Planner):
    """Counter-clockwise circle of ``radius_m`` around ``centre`` (ENU m, planar), at the UAV's
    speed limit N_r Delta_r per tick.

    Far from the circle the UAV flies straight to its nearest point; on it, it advances by one
    step of arc. The move goes where it should when that is admissible (area, obstacles), else
    to the admissible grid candidate nearest to that point: the same limits as every planner.
    """

    centre: np.ndarray
    radius_m: float
    grid: CandidateGrid
    area: Area

    def plan(self, inputs: PlanningInputs, rng: np.random.Generator) -> PlanningResult:
        here = np.asarray(inputs.position, float)
        M = len(inputs.beliefs)
        want = self._toward_circle(here[:2])
        want3 = np.array([want[0], want[1], self.grid.altitude_m])
        if self.area.admissible(want3[None], here)[0]:
            return _chosen(want3[None], np.ones(1, dtype=bool), 0, M)
        cand = candidate_positions(here, self.grid)
        ok = self.area.admissible(cand, here)
        if not ok.any():
            return _chosen(cand, ok, None, M)
        dist_c = np.where(ok, np.linalg.norm(cand[:, :2] - want, axis=1), np.inf)
        return _chosen(cand, ok, int(np.argmin(dist_c)), M)

    def _toward_circle(self, p: np.ndarray) -> np.ndarray:
        c, r = self.centre, self.radius_m
        step = self.grid.n_radial * self.grid.step_m
        d = p - c
        dist = float(np.hypot(*d))
        if dist < 1e-9:
            d, dist = np.array([1.0, 0.0]), 1.0
        if abs(dist - r) > step:
            target = c + r * d / dist
        else:
            ang = math.atan2(d[1], d[0]) + step / r
            target = c + r * np.array([math.cos(ang), math.sin(ang)])
        move = target - p
        n = float(np.hypot(*move))
        return p + (move if n <= step else move * (step / n))


def orbit_centre(setup: MonitorSetup) -> np.ndarray:
    """The targets' initial centroid (ENU m, planar): the orbit baseline's centre."""
    return np.mean([m[:2] for m in setup.initial_means], axis=0)


def register_baselines() -> None:
    """``hover``, ``orbit`` and ``random`` in the planner registry (a setup naming one builds it)."""
    register_planner("hover", lambda setup: HoverPlanner())
    register_planner("orbit", lambda setup: OrbitPlanner(orbit_centre(setup), ORBIT_RADIUS_M, setup.grid,
                                                         area_of(setup)))
    register_planner("random", lambda setup: RandomPlanner(setup.grid, area_of(setup)))
