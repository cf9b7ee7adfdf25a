"""UAV planners: where the UAV scans next, one abstract class for the role (Stone Soup's style).

A ``Planner`` is chosen once from the configuration (onboard/core/planner_choice.py:
``MonitorSetup.planner`` names it) and asked each tick, after the prediction, for the next UAV
position. What flies:

- ``greedy``: the paper's rule, eq. (12) over S_(t+1) (``planning.choose_next_position``);
- ``lookahead``: the non-myopic route planner (``planning.choose_lookahead``, docs/PLANNING.md).

Other planners are siblings registered by name (``planner_choice.register_planner``): the
evaluation's baselines hover, orbit and random (sim/evaluation/baselines.py), a bench's own;
``planning.planner`` (what the app flies) accepts only the two above.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from onboard.core.planning.next_position import (Area, Moves, PlanningResult, RouteScoring, choose_lookahead,
                                                 choose_next_position)
from onboard.core.planning.inputs import CandidateGrid, LookaheadParams, UavMotion, UavState

if TYPE_CHECKING:
    from onboard.core.dynamics import MotionModel
    from onboard.core.guidance.predictor import Plan
    from onboard.core.tracking.filter import ParticleSet


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
        UAV stays). ``rng``: for a planner that draws (the evaluation's random baseline)."""


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
