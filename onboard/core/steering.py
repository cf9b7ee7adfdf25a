"""How the prediction steers a target's particles (docs/TRACKING.md)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.core.guidance import Plan


@dataclass(frozen=True, eq=False)
class SideMode:
    """One hypothesis of the side on which a target rounds its obstacles (``PlanSteering.sides``):
    the plan from the weighted mean of the particles labelled with it, held to ``sides`` (K,)
    (``guidance.in_class``: +1 counterclockwise, -1 clockwise, 0 not yet chosen)."""

    plan: Plan
    sides: np.ndarray
    references: tuple[Plan | None, ...] = ()  # its spread reference plans (next tick's warm starts)
