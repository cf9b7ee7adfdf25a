"""UAV planners: where the UAV scans next, one abstract class for the role (Stone Soup's style).

A ``Planner`` is chosen once from the configuration (``make_planner``: ``MonitorSetup.planner``
names it) and asked each tick, after the prediction, for the next UAV position:

- ``greedy``: the paper's rule, eq. (12) over S_(t+1) (``planning.choose_next_position``);
- ``lookahead``: the non-myopic route planner (``planning.choose_lookahead``, docs/PLANNING.md);
- the evaluation's baselines, planners like the others: ``hover`` (stays at its start),
  ``orbit`` (a circle around the targets' initial centroid), ``random`` (a uniformly random
  admissible candidate of S_(t+1)).
"""
from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from onboard.core.information import information_reduction_factor
from onboard.core.planning import (Area, Moves, PlanningResult, RouteScoring, candidate_positions, choose_lookahead,
                                   choose_next_position)
from onboard.core.planning_inputs import CandidateGrid, LookaheadParams, UavMotion, UavState

if TYPE_CHECKING:
    from onboard.core.dynamics import MotionModel
    from onboard.core.guidance.predictor import Plan
    from onboard.core.monitor_setup import MonitorSetup
    from onboard.core.tracking import ParticleSet

ORBIT_RADIUS_M = 150.0  # the orbit baseline's circle around the targets' initial centroid


@dataclass(frozen=True, eq=False)
class PlanningInputs:
    """What a planner sees after the prediction of tick t."""

    beliefs: Sequence[ParticleSet]  # per target, the predicted belief bel(x_(t+1))
    plans: Sequence[Plan]  # per target, its guidance plan from the posterior mean
    position: np.ndarray  # (3,) ENU m: where the UAV is (or will be at the next tick)
    velocity: np.ndarray  # (2,) ENU m/s: the UAV's planar velocity there (the vehicle motion)
    acceleration: np.ndarray | None = None  # (2,) ENU m/s^2: the plan's there (continuous acceleration); None: 0
    # per belief, the weight of its score (None: 1 each): with motion modes the lookahead scores
    # a target's likely modes as beliefs of their own, weighted by their probabilities
    weights: np.ndarray | None = None

    @property
    def uav(self) -> UavState:
        """Where the UAV plans from, as the planners take it."""
        return UavState(self.position, self.velocity, self.acceleration)

    @property
    def particles(self) -> np.ndarray:
        """(M, N, 6)"""
        return np.stack([b.particles for b in self.beliefs])

    @property
    def log_weights(self) -> np.ndarray:
        """(M, N)"""
        return np.stack([b.log_weights for b in self.beliefs])


class Planner(ABC):
    """Chooses the UAV's next position from the predicted beliefs."""

    @abstractmethod
    def plan(self, inputs: PlanningInputs, rng: np.random.Generator) -> PlanningResult:
        """The candidates, their scores and the choice (``index`` None: no admissible move, the
        UAV stays). ``rng``: for a planner that draws (the random baseline)."""


@dataclass(frozen=True, eq=False)
class GreedyPlanner(Planner):
    """The paper's one-step rule: the admissible next position whose pseudo-updated beliefs have
    the least summed trace (``objective``: all states or the position), S_(t+1) for the jump
    motion, the one-tick reachable set for the vehicle."""

    grid: CandidateGrid
    area: Area
    sigma_rad: float
    objective: str
    motion: UavMotion
    dt_s: float

    def plan(self, inputs: PlanningInputs, rng: np.random.Generator) -> PlanningResult:
        return choose_next_position(inputs.particles, inputs.log_weights, inputs.uav,
                                    Moves(self.grid, self.area, self.motion), self.sigma_rad, self.objective, self.dt_s)


@dataclass(frozen=True, eq=False)
class LookaheadPlanner(Planner):
    """Receding-horizon routes scored over the next ``steps`` ticks of the targets' plans."""

    steps: int
    grid: CandidateGrid
    area: Area
    motion: UavMotion
    model: MotionModel
    sigma_rad: float
    reduction: float  # information reduction factor q (p_D, clutter)
    params: LookaheadParams

    def plan(self, inputs: PlanningInputs, rng: np.random.Generator) -> PlanningResult:
        paths = np.stack([p.means[:self.steps] for p in inputs.plans])
        return choose_lookahead(inputs.particles, inputs.log_weights, paths, inputs.uav,
                                Moves(self.grid, self.area, self.motion),
                                RouteScoring(self.model, self.sigma_rad, self.reduction, self.params), inputs.weights)


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


def _area(setup: MonitorSetup) -> Area:
    return Area(setup.area_min, setup.area_max, setup.uav_obstacles)


def _greedy(setup: MonitorSetup) -> Planner:
    return GreedyPlanner(setup.grid, _area(setup), setup.sensor.sigma_rad, setup.objective, setup.motion,
                         setup.model.dt_s)


def _lookahead(setup: MonitorSetup) -> Planner:
    s = setup.sensor
    return LookaheadPlanner(setup.lookahead_steps, setup.grid, _area(setup), setup.motion, setup.model,
                            s.sigma_rad, information_reduction_factor(s.p_detect, s.clutter_rate, s.sigma_rad),
                            setup.lookahead)


def orbit_centre(setup: MonitorSetup) -> np.ndarray:
    """The targets' initial centroid (ENU m, planar): the orbit baseline's centre."""
    return np.mean([m[:2] for m in setup.initial_means], axis=0)


PLANNERS: dict[str, Callable[[MonitorSetup], Planner]] = {
    "greedy": _greedy,
    "lookahead": _lookahead,
    "hover": lambda setup: HoverPlanner(),
    "orbit": lambda setup: OrbitPlanner(orbit_centre(setup), ORBIT_RADIUS_M, setup.grid, _area(setup)),
    "random": lambda setup: RandomPlanner(setup.grid, _area(setup)),
}


def make_planner(setup: MonitorSetup) -> Planner:
    """The planner ``setup.planner`` names, built from the setup."""
    if setup.planner not in PLANNERS:
        raise ValueError(f"unknown planner {setup.planner!r} (one of {', '.join(PLANNERS)})")
    return PLANNERS[setup.planner](setup)
