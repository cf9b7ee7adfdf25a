"""The control maths the position controllers of sim/mock/multicopter.py are built of, as the
firmware writes them: ArduPilot's square-root controller and jerk-limited shaping
(AC_PosControl's shape_*, limit_accel_xy, update_pos_vel_accel_xy, kinematic_limit) and PX4's
ControlMath::constrainXY. Pure functions of floats: the model steps at 50-400 Hz."""
from __future__ import annotations

import math
from typing import Optional

Vec2 = tuple[float, float]


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


def inv_sqrt_controller(output: float, p: float, d_max: float) -> float:
    """The error for which sqrt_controller gives ``output`` (ArduPilot's inv_sqrt_controller)."""
    if d_max > 0.0 and p == 0.0:
        return output * output / (2.0 * d_max)
    if d_max <= 0.0:
        return output / p if p != 0.0 else 0.0
    if abs(output) < d_max / p:
        return output / p
    dist = d_max / (p * p) * 0.5 + output * output / (2.0 * d_max)
    return math.copysign(dist, output)


# ----- 2-vectors as (x, y) tuples: the model steps at 50-400 Hz, plain floats keep it cheap

def _len(x: float, y: float) -> float:
    return math.sqrt(x * x + y * y)


def _limit(x: float, y: float, lim: float) -> Vec2:
    n = math.sqrt(x * x + y * y)
    if n > lim and n > 0.0:
        k = lim / n
        return x * k, y * k
    return x, y


def _sqrt_2d(ex: float, ey: float, p: float, lim: float, dt: float) -> Vec2:
    n = math.sqrt(ex * ex + ey * ey)
    if n <= 0.0:
        return 0.0, 0.0
    k = sqrt_controller(n, p, lim, dt) / n
    return ex * k, ey * k


def _shape_vel_accel_xy(vin: Vec2, ain: Vec2, vel: Vec2, acc: Vec2, amax: float, jmax: float,
                        dt: float) -> Vec2:
    """shape_vel_accel_xy (limit_total false): the target's next acceleration."""
    ax, ay = _sqrt_2d(vin[0] - vel[0], vin[1] - vel[1], jmax / amax, jmax, dt)
    vn = _len(*vin)
    if vn <= 0.0:
        ax, ay = _limit(ax, ay, amax)
    else:
        # keep 1/sqrt(2) of the limit for the component across the input velocity (corners)
        ux, uy = vin[0] / vn, vin[1] / vn
        along = ux * ax + uy * ay
        cx, cy = ax - ux * along, ay - uy * along
        if along * along <= cx * cx + cy * cy:
            ax, ay = _limit(ax, ay, amax)
        else:
            cx, cy = _limit(cx, cy, amax / math.sqrt(2.0))
            amax_along = math.sqrt(max(0.0, amax * amax - cx * cx - cy * cy))
            along = max(-amax_along, min(amax_along, along))
            ax, ay = cx + ux * along, cy + uy * along
    ax, ay = ax + ain[0], ay + ain[1]
    dx, dy = _limit(ax - acc[0], ay - acc[1], jmax * dt)  # shape_accel_xy: the jerk limit
    return acc[0] + dx, acc[1] + dy


def _shape_pos_vel_accel_xy(pin: Vec2, vin: Vec2, ain: Vec2, pos: Vec2, vel: Vec2, acc: Vec2,
                            vmax: float, amax: float, jmax: float, dt: float) -> Vec2:
    """shape_pos_vel_accel_xy (limit_total false): the target's next acceleration."""
    cx, cy = _sqrt_2d(pin[0] - pos[0], pin[1] - pos[1], 0.5 * jmax / amax, 0.5 * amax, dt)
    if vmax > 0.0:
        cx, cy = _limit(cx, cy, vmax)
    return _shape_vel_accel_xy((cx + vin[0], cy + vin[1]), ain, vel, acc, amax, jmax, dt)


def _limit_accel_xy(vel: Vec2, acc: Vec2, amax: float) -> tuple[Vec2, bool]:
    """limit_accel_xy: cap |acc| at amax, keeping the part across vel first."""
    if acc[0] * acc[0] + acc[1] * acc[1] <= amax * amax:
        return acc, False
    vn = _len(*vel)
    if vn <= 0.0:
        return _limit(acc[0], acc[1], amax), True
    ux, uy = vel[0] / vn, vel[1] / vn
    along = ux * acc[0] + uy * acc[1]
    cx, cy = acc[0] - ux * along, acc[1] - uy * along
    if cx * cx + cy * cy >= amax * amax:
        cx, cy = _limit(cx, cy, amax)
        along = 0.0
    else:
        m = math.sqrt(amax * amax - cx * cx - cy * cy)
        along = max(-m, min(m, along))
    return (cx + ux * along, cy + uy * along), True


def _advance(pos: Vec2, vel: Vec2, acc: Vec2, dt: float, limit: Vec2, pos_err: Vec2,
             vel_err: Vec2) -> tuple[Vec2, Vec2]:
    """update_pos_vel_accel_xy: move the target on by dt, not further into a limit."""
    dpx = vel[0] * dt + 0.5 * acc[0] * dt * dt
    dpy = vel[1] * dt + 0.5 * acc[1] * dt * dt
    dvx, dvy = acc[0] * dt, acc[1] * dt
    if limit[0] or limit[1]:
        if dpx * limit[0] + dpy * limit[1] > 0.0 and pos_err[0] * limit[0] + pos_err[1] * limit[1] > 0.0:
            dpx = dpy = 0.0
        if (dvx * limit[0] + dvy * limit[1] > 0.0 and vel_err[0] * limit[0] + vel_err[1] * limit[1] > 0.0
                and vel[0] * limit[0] + vel[1] * limit[1] >= 0.0):
            dvx = dvy = 0.0
    return (pos[0] + dpx, pos[1] + dpy), (vel[0] + dvx, vel[1] + dvy)


def _kinematic_limit(d: tuple[float, float, float], max_xy: float, max_up: float, max_down: float) -> float:
    """kinematic_limit: the speed allowed along direction d (NED, z down)."""
    n = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    if n <= 0.0 or max_xy <= 0.0 or max_up <= 0.0 or max_down <= 0.0:
        return 0.0
    x, y, z = d[0] / n, d[1] / n, -d[2] / n  # z up
    xy = math.sqrt(x * x + y * y)
    if xy <= 0.0:
        return max_up if z > 0.0 else max_down
    if z == 0.0:
        return max_xy
    slope = z / xy
    lim_z = max_up if slope > 0.0 else max_down
    if abs(slope) < lim_z / max_xy:
        return max_xy / xy
    return abs(lim_z / z)


def _constrain_xy(v0: Vec2, v1: Vec2, vmax: float) -> Vec2:
    """PX4's ControlMath::constrainXY: v0 + v1 within vmax, v0 kept first (v1 cut, then v0)."""
    n0 = _len(*v0)
    if n0 >= vmax:
        return _limit(v0[0], v0[1], vmax)
    s = (v0[0] + v1[0], v0[1] + v1[1])
    if _len(*s) <= vmax:
        return s
    # the largest k in [0, 1] with |v0 + k v1| = vmax
    a = v1[0] * v1[0] + v1[1] * v1[1]
    b = 2.0 * (v0[0] * v1[0] + v0[1] * v1[1])
    c = n0 * n0 - vmax * vmax
    k = (-b + math.sqrt(max(b * b - 4.0 * a * c, 0.0))) / (2.0 * a)
    return v0[0] + k * v1[0], v0[1] + k * v1[1]


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
