"""The setpoint that makes a multicopter fly the plan: position + velocity + acceleration.

The planner gives the UAV's state at the tick it plans from, (p_k, v_k), and one tick later,
v_(k+1), with the position between them integrated trapezoidally (p_(k+1) = p_k + (v_k + v_(k+1))
T / 2: a constant acceleration a = (v_(k+1) - v_k) / T over the tick). Sent d seconds after the
tick as a position, velocity and acceleration target, the plan's state at k + d is

    pos = p_k + v_k d + a d^2 / 2,   vel = v_k + a d,   acc = a,

and ArduCopter's GUIDED (``set_destination_posvelaccel``; PX4's OFFBOARD likewise) moves that
target on by itself between messages (pos += vel dt + acc dt^2 / 2, vel += acc dt), so the
target is at p_(k+1) with v_(k+1) when the next tick's setpoint is due: the copter flies through
the planned points at speed instead of braking to each one (a position-only setpoint). Measured
on ArduCopter SITL: 0.5-0.7 m from the planned point at the next tick, against 16-27 m with the
position only (bench/sitl_response.py, sim/mock/guided.py).

With a continuous acceleration (the vehicle motion's ``jerk_max_mps3`` > 0,
onboard/core/planning/next_position.py) the plan's acceleration is ``a_k`` at the tick, where the previous
tick's plan left it, and changes linearly to a_(k+1) = 2 (v_(k+1) - v_k) / T - a_k over the tick
(the same v_(k+1)), so that

    pos = p_k + v_k d + a_k d^2 / 2 + j d^3 / 6,   vel = v_k + a_k d + j d^2 / 2,   acc = a_k + j d,

with j = (a_(k+1) - a_k) / T. ArduCopter's GUIDED shapes its target's acceleration at most at
PSC_JERK_XY (5 m/s^3 stock; AC_PosControl::input_pos_vel_accel_xy): a step of the acceleration
at a tick (up to 2 a_max = 5 m/s^2 when a turn reverses) takes it up to a second to follow, and
the copter ends the tick up to ~1.7 m off the planned point (the p95 of bench/ardupilot.py
before the ramps); a ramp within the jerk limit it follows.

Frame-free (any frame in which the plan is given, the mission's ENU in the app and the
evaluation); metres, seconds. Pure: no MAVLink here (the type_mask is the link's business).
"""
from __future__ import annotations

import numpy as np


def plan_setpoint(p_k, v_k, v_next, tick_s: float, offset_s: float = 0.0, a_k=None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pos, vel, acc) of the plan at ``offset_s`` after the tick it starts from (see the module).

    p_k, v_k: the plan's position and velocity at that tick; v_next: its velocity one tick
    (``tick_s``) later; a_k: its acceleration at the tick (continuous acceleration), None: the
    acceleration is constant over the tick; arrays of one shape (planar or 3-D). offset_s in
    [0, tick_s] is the time the setpoint is sent after the tick (the tick's own latency): the
    target then starts where the plan is at that moment. ValueError on a non-finite input,
    tick_s <= 0 or an offset outside [0, tick_s].
    """
    p, v, vn = (np.asarray(x, dtype=float) for x in (p_k, v_k, v_next))
    a0 = None if a_k is None else np.asarray(a_k, dtype=float)
    if not (p.shape == v.shape == vn.shape) or (a0 is not None and a0.shape != p.shape):
        raise ValueError(f"plan_setpoint: shapes differ: {p.shape}, {v.shape}, {vn.shape}"
                         + ("" if a0 is None else f", {a0.shape}"))
    if not (np.isfinite(p).all() and np.isfinite(v).all() and np.isfinite(vn).all()
            and (a0 is None or np.isfinite(a0).all())):
        raise ValueError("plan_setpoint: a plan state is not finite")
    if not (np.isfinite(tick_s) and tick_s > 0.0):
        raise ValueError(f"plan_setpoint: tick_s must be > 0, got {tick_s}")
    if not (0.0 <= offset_s <= tick_s):
        raise ValueError(f"plan_setpoint: offset_s must be in [0, {tick_s:g}], got {offset_s}")
    d = float(offset_s)
    if a0 is None:
        a = (vn - v) / tick_s
        return p + v * d + 0.5 * a * d * d, v + a * d, a
    j = (2.0 * (vn - v) / tick_s - 2.0 * a0) / tick_s  # (a_(k+1) - a_k) / T
    return p + v * d + 0.5 * a0 * d * d + j * d ** 3 / 6.0, v + a0 * d + 0.5 * j * d * d, a0 + j * d


def ramp_displacement(v_k, a_k, a_next, tick_s: float) -> np.ndarray:
    """Displacement one tick on, the acceleration changing linearly from ``a_k`` to ``a_next``
    over it (the module's continuous acceleration); arrays of any broadcastable shapes."""
    T = float(tick_s)
    return v_k * T + T * T * (a_k / 3.0 + a_next / 6.0)


def ramp_velocity(v_k, a_k, a_next, tick_s: float) -> np.ndarray:
    """Velocity one tick on, as ``ramp_displacement``."""
    return v_k + 0.5 * (a_k + a_next) * float(tick_s)
