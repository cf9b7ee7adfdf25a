"""What the planners are given, shared by the planners (onboard/core/planning/next_position.py) and the
lookahead's route geometry (onboard/core/planning/routes.py): the candidate grid S_(t+1) (eq. (3) of the
paper), where the UAV plans from (``UavState``), how it moves between ticks (``UavMotion``; the
paper's ``JUMP``) and the route planner's knobs (``LookaheadParams``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from onboard.core.setpoint import ramp_displacement, ramp_velocity


def planar_norms(xy: np.ndarray) -> np.ndarray:
    """|xy| of planar vectors (C, 2) as (C, 1): np.linalg.norm's values (sqrt(x x + y y)) without
    its generic path, which costs more than the arithmetic in the route planner's loops."""
    return np.sqrt(xy[:, 0] * xy[:, 0] + xy[:, 1] * xy[:, 1])[:, None]


@dataclass(frozen=True)
class CandidateGrid:
    step_m: float  # Delta_r
    n_radial: int  # N_r
    n_heading: int  # N_theta
    altitude_m: float  # h, the mission altitude: m above the mission origin, ENU up

    @classmethod
    def from_config(cls, u) -> "CandidateGrid":
        return cls(u.step_m, u.n_radial, u.n_heading, u.altitude_m)


@dataclass(frozen=True, eq=False)
class UavState:
    """Where the UAV plans from: its position (ENU m; the planners read x and y), its planar
    velocity there (ENU m/s; None: at rest) and the plan's planar acceleration there (ENU m/s^2,
    a continuous acceleration's; None: 0)."""

    position: np.ndarray
    velocity: np.ndarray | None = None
    acceleration: np.ndarray | None = None


@dataclass(frozen=True)
class UavMotion:
    """How the UAV moves between ticks.

    ``jump``: the paper's model, any point of the polar grid S_(t+1) is reached in one tick.
    ``vehicle``: a multicopter with a speed and an acceleration limit (double integrator;
    ArduCopter's WPNAV_SPEED and WPNAV_ACCEL defaults, the scenario's, reproduce the measured 5.6 s
    for a 20 m step from hover); the next positions are those reached in one tick under a
    constant acceleration of N_r magnitudes (a_max k / N_r) in N_theta directions, or none.
    ``jerk_max_mps3`` > 0: the acceleration is continuous instead, changing linearly over each
    tick from where the last tick left it to the one asked for, by at most jerk_max_mps3 times
    the tick (onboard/core/setpoint.py: what ArduCopter's jerk-limited GUIDED follows).
    """

    kind: str  # jump | vehicle
    speed_max_mps: float  # vehicle only
    accel_max_mps2: float  # vehicle only
    jerk_max_mps3: float  # vehicle only; 0: the acceleration steps at each tick

    @classmethod
    def from_config(cls, planning) -> "UavMotion":
        """From the scenario's ``planning`` (onboard/settings/sections.py declares the defaults)."""
        return cls(planning.motion, planning.speed_max_mps, planning.accel_max_mps2, planning.jerk_max_mps3)

    def step(self, p: np.ndarray, v: np.ndarray, a: np.ndarray, a_new: np.ndarray, dt: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Continuous acceleration (``jerk_max_mps3`` > 0): one tick from position, velocity and
        acceleration ``a`` (C, 2) asking for the acceleration ``a_new`` (|a_new| <= a_max): it
        ramps to it over the tick, the change capped at jerk_max_mps3 dt, the end speed at
        speed_max_mps (the end acceleration then what gives that speed). Returns (p, v, a) at
        the tick's end."""
        dj = a_new - a
        n = planar_norms(dj)
        a_end = a + dj * np.minimum(1.0, self.jerk_max_mps3 * dt / np.maximum(n, 1e-12))
        v_new = ramp_velocity(v, a, a_end, dt)
        sp = planar_norms(v_new)
        v_new = v_new * np.minimum(1.0, self.speed_max_mps / np.maximum(sp, 1e-12))
        a_end = 2.0 * (v_new - v) / dt - a
        disp = ramp_displacement(v, a, a_end, dt)
        return p + disp, v_new, a_end


JUMP = UavMotion("jump", math.inf, math.inf, 0.0)  # the paper's motion: no speed or acceleration limit applies


@dataclass(frozen=True)
class LookaheadParams:
    """The route planner's knobs (docs/PLANNING.md argues each value).

    ranges_m x n_headings: waypoints on a polar grid around the UAV; the targets' predicted
    positions (and their centroid) half-way and at the end of the horizon are waypoints too.
    Each route flies the shortest obstacle-free polyline to its waypoint at the motion's speed
    limit, then circles (left or right) through it with radius loiter_radius_m: a route always
    keeps moving, so the line of sight keeps turning. A route's score is the sum over the
    horizon and the targets of tr P_pos, position only and undiscounted (docs/PLANNING.md says
    why).
    """

    ranges_m: tuple[float, ...]  # m
    n_headings: int
    loiter_radius_m: float
    corner_clearance_m: float
    spacing_m: float  # arc-length resolution of the sampled routes, m

    @classmethod
    def from_config(cls, c) -> "LookaheadParams":
        """From the scenario's ``planning.lookahead`` (onboard/settings/sections.py ``Lookahead`` declares
        the defaults, units and ranges)."""
        return cls(tuple(c.ranges_m), c.n_headings, c.loiter_radius_m, c.corner_clearance_m, c.spacing_m)
