"""Flight policies: how the app decides where to fly, as changes of a scenario's settings
(keys and values as onboard/settings/sections.py declares them, applied by ``onboard.config.override``
and so checked as a file is).

- ``flight`` (the default of ``pmon run`` and ``pmon demo``): no changes. The declared defaults
  are what flies, the best measured: the lookahead planner on the vehicle motion, the side-aware
  filter with recovery and motion modes; each value's why: docs/PLANNING.md, 'What flies' and
  docs/TRACKING.md, 'Intent' (measurements: docs/LOG.md).
- ``paper``: the overlay that reproduces the paper's method bit for bit: the one-step greedy rule
  on the jump model with the paper's filter (what ``pmon eval paper`` evaluates as greedy_l1; the
  evaluation's paper methods start from it, sim/evaluation/methods.py).

The vehicle's speed, acceleration and jerk limits are the autopilot's own, read by the app at
connection (WPNAV_SPEED / WPNAV_ACCEL / PSC_JERK_XY on ArduPilot; PX4's OFFBOARD shapes no jerk),
capped by ``planning.speed_max_mps``, ``planning.accel_max_mps2`` and ``planning.jerk_max_mps3``
(what the airframe can fly).
"""
from __future__ import annotations

import math
from typing import Any

from onboard.core.planning.inputs import UavMotion

POLICIES: dict[str, dict[str, Any]] = {
    "flight": {},
    "paper": {"planning.planner": "greedy", "planning.motion": "jump",
              "planning.speed_max_mps": 10.0, "planning.jerk_max_mps3": 0.0,
              "tracking.plan_steering": False, "tracking.plan_sides": False, "tracking.recovery_prior": 0.0,
              "tracking.intent": False},
}
DEFAULT = "flight"


def with_policy(sc, name: str):
    """Scenario ``sc`` flown under policy ``name``: the policy's settings beneath the scenario's
    own changes (a user's ``--set`` wins over the policy)."""
    from onboard.config import override

    return override(sc, POLICIES[name], beneath=True)


def vehicle_motion(planning, speed_mps: float, accel_mps2: float, jerk_mps3: float = math.inf) -> UavMotion:
    """The vehicle motion the planner plans with: the autopilot's own limits (``speed_mps``,
    ``accel_mps2``, ``jerk_mps3``: WPNAV_SPEED, WPNAV_ACCEL and the jerk ArduCopter shapes guided
    targets with, in SI; inf where unknown), capped by what the airframe flies
    (``planning.speed_max_mps``, ``accel_max_mps2``, ``jerk_max_mps3`` of the scenario with its
    policy). A ``jerk_max_mps3`` of 0 (the acceleration steps at each tick) stays 0."""
    jerk = planning.jerk_max_mps3
    if jerk > 0.0:
        jerk = min(float(jerk_mps3), jerk)
    return UavMotion("vehicle", min(float(speed_mps), planning.speed_max_mps),
                     min(float(accel_mps2), planning.accel_max_mps2), jerk)
