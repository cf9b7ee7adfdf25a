"""The UAV planner a mission flies, by name (``MonitorSetup.planner``): the flight planners of
onboard/core/planning/planners.py, built from the setup, and any other a caller registers
(``register_planner``: the evaluation's baselines, a bench's own)."""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from onboard.core.planning.information import information_reduction_factor
from onboard.core.planning.planners import GreedyPlanner, LookaheadPlanner, Planner
from onboard.core.planning.next_position import Area

if TYPE_CHECKING:
    from onboard.core.monitor_setup import MonitorSetup


def area_of(setup: MonitorSetup) -> Area:
    """Where the setup's UAV may go: its area and its inflated obstacles."""
    return Area(setup.area_min, setup.area_max, setup.uav_obstacles)


def _greedy(setup: MonitorSetup) -> Planner:
    return GreedyPlanner(setup.grid, area_of(setup), setup.sensor.sigma_rad, setup.objective, setup.motion,
                         setup.model.dt_s)


def _lookahead(setup: MonitorSetup) -> Planner:
    s = setup.sensor
    return LookaheadPlanner(setup.lookahead_steps, setup.grid, area_of(setup), setup.motion, setup.model,
                            s.sigma_rad, information_reduction_factor(s.p_detect, s.clutter_rate, s.sigma_rad),
                            setup.lookahead)


PLANNERS: dict[str, Callable[[MonitorSetup], Planner]] = {
    "greedy": _greedy,
    "lookahead": _lookahead,
}


def register_planner(name: str, build: Callable[[MonitorSetup], Planner]) -> None:
    """Add (or replace) a planner by name; a setup whose ``planner`` names it then flies it."""
    PLANNERS[name] = build


def make_planner(setup: MonitorSetup) -> Planner:
    """The planner ``setup.planner`` names, built from the setup."""
    if setup.planner not in PLANNERS:
        raise ValueError(f"unknown planner {setup.planner!r} (one of {', '.join(PLANNERS)})")
    return PLANNERS[setup.planner](setup)
