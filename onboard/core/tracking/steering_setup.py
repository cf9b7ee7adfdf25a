"""What the particle steering (onboard/core/tracking/steering.py) reads of a mission: the reference plans'
settings (``PlanSteering``, from ``tracking.plan_*``) and the part of the setup it takes
(``SteeringSetup``: ``MonitorSetup`` is one), so the steering needs no setup of its own kind."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from onboard.core.guidance.predictor import FreeLaw, GuidanceParams
from onboard.core.obstacles import Obstacles


@dataclass(frozen=True)
class PlanSteering:
    """How the particles of a target whose plan is constrained are steered (docs/TRACKING.md):
    by the affine law (``LocalLaw``) of the nearest reference plan, the posterior mean's or one
    of ``references`` more (an even number: pairs out to ``spread_sigma`` standard deviations
    either side along the cloud's major axis), if it lies within ``trust_sigma`` standard
    deviations (Mahalanobis, position) of one. A share ``1 - steered_share``, and every particle
    farther out, keeps the mean plan's control (robustness where the target's plan differs from
    all of them). Used while the mean's plan has an active row (rounding an obstacle, or at an
    input or speed limit): elsewhere the free law is exact."""

    references: int
    spread_sigma: float
    steered_share: float
    trust_sigma: float
    max_qp_solves: int  # per reference plan (capped by the guidance's budget, which the mean's has)
    # each particle carries the side of each obstacle its target takes, and each side present has
    # its own mean's plan and spread pairs (``_side_modes``); a side costing P1 d more (relative)
    # than its parent's gets a share 1 / (1 + exp(d / side_temperature)) of its particles at birth
    sides: bool
    side_temperature: float

    @classmethod
    def from_config(cls, tr) -> "PlanSteering | None":
        """From the scenario's ``tracking.plan_*`` (onboard/settings/sections.py declares the defaults)."""
        if not tr.plan_steering:
            return None
        return cls(tr.plan_references, tr.plan_spread_sigma, tr.plan_steered_share, tr.plan_trust_sigma,
                   tr.plan_max_qp_solves, tr.plan_sides, tr.plan_side_temperature)


class SteeringSetup(Protocol):
    """The particle steering's view of the mission's setup (read-only)."""

    @property
    def guidance(self) -> GuidanceParams: ...  # its u_max_n bounds a steered or random control

    @property
    def obstacles(self) -> Obstacles: ...  # as built (the guidance inflates by its own margin)

    @property
    def control_mix(self) -> float: ...  # fraction of particles predicted with a random control

    @property
    def free_steering(self) -> FreeLaw | None: ...  # particles whose own plan is the free optimum

    @property
    def plan_steering(self) -> PlanSteering | None: ...  # the others, while the plan is constrained
