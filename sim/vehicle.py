"""Pure kinematic multicopter model for the mock autopilot.

Frame: local NED (x north, y east, z down), metres, seconds, radians; yaw is the
heading, 0 = north, positive clockwise (towards east). No sockets, threads or clocks:
`step` maps (state, setpoint, dt) to the next state; randomness only via the
`numpy.random.Generator` the caller passes.

The shaping follows ArduPilot's AC_PosControl (`shape_pos_vel_accel`): a square-root
controller turns the position error into a velocity demand that can still stop within
the acceleration limit, a second square-root controller turns the velocity error into
an acceleration demand, and that demand is reached under a jerk limit. With ArduCopter's
stock limits (WPNAV_SPEED 10 m/s, WPNAV_ACCEL 2.5 m/s^2, PSC_JERK_XY 5 m/s^3) this
reproduces what a stock ArduCopter SITL does in GUIDED with position targets
(see tests/test_vehicle.py for the three calibration figures).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

Vec3 = tuple[float, float, float]

GRAVITY = 9.80665  # m/s^2


@dataclass(frozen=True)
class VehicleLimits:
    """Kinematic limits; defaults are ArduCopter stock parameters converted to SI."""

    speed_xy: float = 10.0  # WPNAV_SPEED 1000 cm/s
    speed_up: float = 2.5  # WPNAV_SPEED_UP 250 cm/s
    speed_down: float = 1.5  # WPNAV_SPEED_DN 150 cm/s
    accel_xy: float = 2.5  # WPNAV_ACCEL 250 cm/s^2
    accel_z: float = 1.0  # WPNAV_ACCEL_Z 100 cm/s^2
    jerk_xy: float = 5.0  # PSC_JERK_XY 5 m/s^3
    jerk_z: float = 5.0  # PSC_JERK_Z 5 m/s^3
    yaw_rate: float = math.radians(90.0)  # rad/s, yaw slew used for heading targets
    pos_noise: float = 0.02  # m/sqrt(s): random-walk disturbance (wind, EKF noise)


@dataclass(frozen=True)
class VehicleState:
    """Kinematic state in local NED (m, m/s, m/s^2, rad)."""

    pos: Vec3 = (0.0, 0.0, 0.0)
    vel: Vec3 = (0.0, 0.0, 0.0)
    acc: Vec3 = (0.0, 0.0, 0.0)
    yaw: float = 0.0


@dataclass(frozen=True)
class Setpoint:
    """What the position controller is asked to do; None means "not commanded".

    - pos set: go to pos (vel/acc, if set, are feed-forward terms);
    - pos None, vel set: fly that velocity (acc is feed-forward);
    - only acc set: fly that acceleration;
    - nothing set: brake to a stop.
    yaw (rad, absolute) wins over yaw_rate (rad/s); neither set holds the heading.
    speed_xy/speed_up/speed_down override the limits (DO_CHANGE_SPEED).
    """

    pos: Optional[Vec3] = None
    vel: Optional[Vec3] = None
    acc: Optional[Vec3] = None
    yaw: Optional[float] = None
    yaw_rate: Optional[float] = None
    speed_xy: Optional[float] = None
    speed_up: Optional[float] = None
    speed_down: Optional[float] = None


def sqrt_controller(error: float, p: float, second_ord_lim: float, dt: float) -> float:
    """ArduPilot's sqrt_controller: linear (gain p) near zero, square root beyond.

    The square-root branch is the speed from which `second_ord_lim` stops exactly at the
    target, so the output never asks for more deceleration than allowed. The result is
    also limited so it cannot overshoot the error within one step of length dt.
    """
    if second_ord_lim <= 0.0:
        out = error * p
    elif p == 0.0:
        out = math.copysign(math.sqrt(2.0 * second_ord_lim * abs(error)), error)
    else:
        linear_dist = second_ord_lim / (p * p)
        if error > linear_dist:
            out = math.sqrt(2.0 * second_ord_lim * (error - linear_dist / 2.0))
        elif error < -linear_dist:
            out = -math.sqrt(2.0 * second_ord_lim * (-error - linear_dist / 2.0))
        else:
            out = error * p
    if dt > 0.0:
        bound = abs(error) / dt
        out = max(-bound, min(bound, out))
    return out


def _limit_norm(v: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if n > limit > 0.0:
        return v * (limit / n)
    if limit <= 0.0:
        return np.zeros_like(v)
    return v


def _shape_xy(
    pos_err: Optional[np.ndarray],
    vel_cmd: Optional[np.ndarray],
    acc_ff: np.ndarray,
    vel: np.ndarray,
    acc: np.ndarray,
    vmax: float,
    amax: float,
    jmax: float,
    dt: float,
) -> np.ndarray:
    """New horizontal acceleration (2-vector) after one jerk-limited step."""
    # Gains as AC_PosControl derives them from the jerk and acceleration limits; the
    # position loop keeps half the acceleration in reserve for velocity corrections.
    kp_vel = 0.5 * jmax / amax
    kp_acc = jmax / amax
    vel_target = np.zeros(2) if vel_cmd is None else vel_cmd.copy()
    if pos_err is not None:
        dist = float(np.linalg.norm(pos_err))
        if dist > 1e-9:
            speed = sqrt_controller(dist, kp_vel, 0.5 * amax, dt)
            vel_target = vel_target + pos_err / dist * min(speed, vmax)
    if pos_err is None and vel_cmd is None and np.any(acc_ff):
        acc_target = acc_ff  # acceleration-only command
    else:
        vel_target = _limit_norm(vel_target, vmax)
        verr = vel_target - vel
        n = float(np.linalg.norm(verr))
        acc_target = acc_ff.copy()
        if n > 1e-9:
            acc_target = acc_target + verr / n * sqrt_controller(n, kp_acc, jmax, dt)
    acc_target = _limit_norm(acc_target, amax)
    return acc + _limit_norm(acc_target - acc, jmax * dt)


def _shape_z(
    pos_err: Optional[float],
    vel_cmd: Optional[float],
    acc_ff: float,
    vel: float,
    acc: float,
    v_up: float,
    v_down: float,
    amax: float,
    jmax: float,
    dt: float,
) -> float:
    """New vertical (NED, +down) acceleration after one jerk-limited step."""
    kp_vel = 0.5 * jmax / amax
    kp_acc = jmax / amax
    vel_target = 0.0 if vel_cmd is None else vel_cmd
    if pos_err is not None:
        vel_target += sqrt_controller(pos_err, kp_vel, 0.5 * amax, dt)
    if pos_err is None and vel_cmd is None and acc_ff != 0.0:
        acc_target = acc_ff
    else:
        vel_target = max(-v_up, min(v_down, vel_target))
        acc_target = acc_ff + sqrt_controller(vel_target - vel, kp_acc, jmax, dt)
    acc_target = max(-amax, min(amax, acc_target))
    return acc + max(-jmax * dt, min(jmax * dt, acc_target - acc))


def wrap_pi(angle: float) -> float:
    """Wrap an angle to (-pi, pi]."""
    a = math.fmod(angle + math.pi, 2.0 * math.pi)
    if a <= 0.0:
        a += 2.0 * math.pi
    return a - math.pi


def step(
    state: VehicleState,
    setpoint: Setpoint,
    dt: float,
    limits: VehicleLimits = VehicleLimits(),
    rng: Optional[np.random.Generator] = None,
) -> VehicleState:
    """Advance the powered vehicle by dt seconds towards the setpoint (local NED).

    Speed limits are hard: the returned horizontal speed never exceeds
    setpoint.speed_xy or limits.speed_xy, the climb/descent rates never exceed
    speed_up/speed_down. With rng given, a small random-walk position disturbance of
    limits.pos_noise m/sqrt(s) is added (the controller then corrects it).
    """
    if dt <= 0.0:
        return state
    vmax = setpoint.speed_xy if setpoint.speed_xy else limits.speed_xy
    v_up = setpoint.speed_up if setpoint.speed_up else limits.speed_up
    v_down = setpoint.speed_down if setpoint.speed_down else limits.speed_down
    pos = np.asarray(state.pos, dtype=float)
    vel = np.asarray(state.vel, dtype=float)
    acc = np.asarray(state.acc, dtype=float)
    acc_ff = np.zeros(3) if setpoint.acc is None else np.asarray(setpoint.acc, dtype=float)
    vel_cmd = None if setpoint.vel is None else np.asarray(setpoint.vel, dtype=float)
    pos_err = None if setpoint.pos is None else np.asarray(setpoint.pos, dtype=float) - pos

    acc_xy = _shape_xy(
        None if pos_err is None else pos_err[:2],
        None if vel_cmd is None else vel_cmd[:2],
        acc_ff[:2],
        vel[:2],
        acc[:2],
        vmax,
        limits.accel_xy,
        limits.jerk_xy,
        dt,
    )
    acc_z = _shape_z(
        None if pos_err is None else float(pos_err[2]),
        None if vel_cmd is None else float(vel_cmd[2]),
        float(acc_ff[2]),
        float(vel[2]),
        float(acc[2]),
        v_up,
        v_down,
        limits.accel_z,
        limits.jerk_z,
        dt,
    )
    new_acc = np.array([acc_xy[0], acc_xy[1], acc_z])
    new_vel = vel + new_acc * dt
    # Hard limits: the airframe never flies faster than the configured speeds.
    new_vel[:2] = _limit_norm(new_vel[:2], vmax)
    new_vel[2] = max(-v_up, min(v_down, new_vel[2]))
    new_pos = pos + 0.5 * (vel + new_vel) * dt
    if rng is not None and limits.pos_noise > 0.0:
        new_pos = new_pos + rng.normal(0.0, limits.pos_noise * math.sqrt(dt), 3)

    yaw = state.yaw
    max_turn = limits.yaw_rate * dt
    if setpoint.yaw is not None:
        yaw += max(-max_turn, min(max_turn, wrap_pi(setpoint.yaw - yaw)))
    elif setpoint.yaw_rate is not None:
        yaw += max(-max_turn, min(max_turn, setpoint.yaw_rate * dt))
    return VehicleState(
        pos=_vec(new_pos), vel=_vec(new_vel), acc=_vec(new_acc), yaw=wrap_pi(yaw)
    )


def fall(state: VehicleState, dt: float, ground_z: float = 0.0) -> VehicleState:
    """Unpowered (disarmed) motion: ballistic fall with crude drag, stops on the ground."""
    pos = np.asarray(state.pos, dtype=float)
    vel = np.asarray(state.vel, dtype=float)
    acc = np.array([-0.5 * vel[0], -0.5 * vel[1], GRAVITY - 0.2 * vel[2]])
    vel = vel + acc * dt
    pos = pos + vel * dt
    if pos[2] >= ground_z:
        pos[2] = ground_z
        vel = np.zeros(3)
        acc = np.zeros(3)
    return replace(state, pos=_vec(pos), vel=_vec(vel), acc=_vec(acc))


def on_ground(state: VehicleState, ground_z: float = 0.0) -> VehicleState:
    """Clamp the state to the ground plane z = ground_z (NED, so below means z > ground_z)."""
    if state.pos[2] < ground_z:
        return state
    vz = min(state.vel[2], 0.0)
    az = min(state.acc[2], 0.0)
    return replace(
        state,
        pos=(state.pos[0], state.pos[1], ground_z),
        vel=(state.vel[0], state.vel[1], vz),
        acc=(state.acc[0], state.acc[1], az),
    )


def stopping_point(state: VehicleState, limits: VehicleLimits = VehicleLimits(),
                   dt: float = 0.02) -> Vec3:
    """Where the vehicle comes to rest if told to brake now (AC_PosControl's stopping point).

    Found by braking the model itself (no noise), so the current acceleration and the
    jerk limit are accounted for and a hold at this point does not overshoot.
    """
    s = replace(state, yaw=0.0)
    for _ in range(round(30.0 / dt)):
        if math.hypot(*s.vel) < 1e-3 and math.hypot(*s.acc) < 1e-2:
            break
        s = step(s, Setpoint(), dt, limits)
    return s.pos


def attitude(state: VehicleState) -> Vec3:
    """(roll, pitch, yaw) in rad that produce the state's horizontal acceleration."""
    an, ae = state.acc[0], state.acc[1]
    c, s = math.cos(state.yaw), math.sin(state.yaw)
    forward = an * c + ae * s
    right = -an * s + ae * c
    return (math.atan2(right, GRAVITY), -math.atan2(forward, GRAVITY), state.yaw)


def _vec(a: np.ndarray) -> Vec3:
    return (float(a[0]), float(a[1]), float(a[2]))
