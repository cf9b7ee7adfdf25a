"""Problem P1's settings (``GuidanceParams``): a leaf every part of the guidance reads."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class GuidanceParams:
    """Problem P1's settings, each from the scenario (onboard/settings/sections.py ``Guidance`` declares
    their defaults, units and ranges; no defaults here that could disagree)."""

    horizon: int
    u_max_n: float
    speed_max_mps: float
    speed_polygon_sides: int
    terminal_weight: float  # per m^2
    stage_weight: float  # per m^2
    smooth_weight: float  # per kN^2
    obstacle_margin_m: float
    max_qp_solves: int
    max_solve_time_s: float | None  # per plan; None: no limit (deterministic, for evaluation)

    @classmethod
    def from_config(cls, g) -> "GuidanceParams":
        return cls(g.horizon, g.u_max_n, g.speed_max_mps, g.speed_polygon_sides, g.terminal_weight,
                   g.stage_weight, g.smooth_weight, g.obstacle_margin_m, g.max_qp_solves,
                   g.max_solve_time_s)
