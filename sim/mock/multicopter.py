"""Pure multicopter model for the mock autopilot and the evaluation: ArduCopter's position
controller (or PX4's, ``VehicleLimits.shaping`` False) and the airframe it flies.

Frame: local NED (x north, y east, z down), metres, seconds, radians; yaw is the
heading, 0 = north, positive clockwise (towards east). No sockets, threads or clocks:
`step` maps (state, setpoint, dt) to the next state; randomness only via the
`numpy.random.Generator` the caller passes.

Horizontally the model is ArduCopter 4.4's AC_PosControl in two layers, as the firmware runs it:

1. the kinematic target (``input_pos_xyz``, ``input_pos_vel_accel_xy``, ``input_vel_accel_xy``):
   a jerk-limited path from the target's position, velocity and acceleration to the setpoint.
   ``shape_pos_vel_accel_xy`` turns the position error into a velocity (square-root controller
   that can stop within half the acceleration limit), adds the setpoint's velocity, and
   ``shape_vel_accel_xy`` reaches it with an acceleration that changes at most at the jerk limit.
   Position-only setpoints are approached with zero velocity at the point: the copter brakes
   to each one. Position + velocity setpoints are flown through at that velocity.
2. the vehicle following that target (``update_xy_controller``): position P (PSC_POSXY_P) and
   velocity PID (PSC_VELXY_P/I/D, 5 Hz filters) around the target's velocity and acceleration
   (feed-forward), the result limited by the lean angle (ANGLE_MAX), flown through the attitude
   loop (a first-order lag) by an airframe with drag.

The airframe terms (lean lag and drag) are fitted to ArduPilot's SITL '+' copter
(bench/sitl_response.py, tests/data/sitl_response.json.gz, tests/sim/test_vehicle.py): its drag at
ANGLE_MAX 30 deg caps level speed at 10.1 m/s whatever WPNAV_SPEED says. Vertically the vehicle
flies the shaped kinematic target itself (altitude changes are slow and not what is measured).

PX4 (v1.16 mc_pos_control's PositionControl, as OFFBOARD feeds it: ``limits_from_params`` with
PX4's MPC_* names): no kinematic shaping, the setpoint is the target; velocity = MPC_XY_P times
the position error plus the feed-forward, the feed-forward cut first to keep within
MPC_XY_VEL_MAX; acceleration = velocity PID (D on the vehicle's acceleration, tracking
anti-windup) plus the acceleration feed-forward, the tilt limited to MPC_TILTMAX_AIR. Its
airframe terms are fitted to PX4's SIH quad (bench/sitl_response.py --autopilot px4,
tests/data/sitl_response_px4.json.gz): SIH's drag is linear (SIH_KDV), hence ``drag_lin``.

The firmware's control maths both controllers are built of (the square-root controller, the
shaping, PX4's constrainXY) are in sim/mock/control_math.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from onboard.app.autopilot.profiles import arducopter_jerk_xy
from sim.mock.control_math import (_advance, _constrain_xy, _kinematic_limit, _len, _limit, _limit_accel_xy,
                              _shape_pos_vel_accel_xy, _shape_vel_accel_xy, _shape_z, _sqrt_2d,
                              Vec2, inv_sqrt_controller)

Vec3 = tuple[float, float, float]

# ArduCopter parameters a fast multicopter is set up with (20 m/s, 5 m/s^2, jerk 20 m/s^3, climb
# 5 m/s): the paper's steps of up to N_r * Delta_r = 20 m per tick need them (docs/SITL.md). The
# demo's vehicle (pmon demo, python -m sim.stack.sitl_stack, the SITL tests and benches); NAME@demo in pmon eval.
DEMO_VEHICLE_PARAMS = {"WPNAV_SPEED": 2000, "WPNAV_ACCEL": 500, "PSC_JERK_XY": 20,
                       "WPNAV_SPEED_UP": 500}

GRAVITY = 9.80665  # m/s^2


@dataclass(frozen=True)
class VehicleLimits:
    """Limits, controller gains and airframe; defaults are ArduCopter 4.4's stock parameters in
    SI and the terms fitted to ArduPilot's SITL copter (see the module's docstring)."""

    speed_xy: float = 10.0  # WPNAV_SPEED 1000 cm/s
    speed_up: float = 2.5  # WPNAV_SPEED_UP 250 cm/s
    speed_down: float = 1.5  # WPNAV_SPEED_DN 150 cm/s
    accel_xy: float = 2.5  # WPNAV_ACCEL 250 cm/s^2
    accel_z: float = 1.0  # WPNAV_ACCEL_Z 100 cm/s^2
    jerk_xy: float = 5.0  # PSC_JERK_XY 5 m/s^3
    jerk_z: float = 5.0  # PSC_JERK_Z 5 m/s^3
    yaw_rate: float = math.radians(90.0)  # rad/s, yaw slew used for heading targets
    pos_noise: float = 0.02  # m/sqrt(s): random-walk disturbance (wind, EKF noise)
    angle_max: float = math.radians(30.0)  # ANGLE_MAX 3000 cdeg: lean limit, g tan(angle) m/s^2
    lean_accel_max: float = math.radians(1100.0)  # ATC_ACCEL_R_MAX 110000 cdeg/s^2: caps the jerk
    pos_p: float = 1.0  # PSC_POSXY_P, 1/s
    vel_p: float = 2.0  # PSC_VELXY_P, 1/s
    vel_i: float = 1.0  # PSC_VELXY_I, 1/s^2
    vel_d: float = 0.5  # PSC_VELXY_D
    vel_imax: float = 10.0  # PSC_VELXY_IMAX 1000 cm/s^2
    vel_filt_hz: float = 5.0  # PSC_VELXY_FLTE and _FLTD
    lean_tc: float = 0.354  # s: the lean flown lags the lean asked for (attitude loop), fitted
    drag: float = 0.056  # 1/m: airframe drag, a = -drag |v| v, fitted
    drag_lin: float = 0.0  # 1/s: linear airframe drag, a = -drag_lin v (PX4's SIH: SIH_KDV / SIH_MASS)
    shaping: bool = True  # ArduCopter's jerk-limited target; False: PX4's (the setpoint is the target)

    def jerk_xy_max(self) -> float:
        """The horizontal jerk the shaper uses: PSC_JERK_XY, capped as set_max_speed_accel_xy
        does by the average jerk the attitude loop can give (the app's reading of the same
        parameters: onboard/app/autopilot/profiles.py ``arducopter_jerk_xy``)."""
        return arducopter_jerk_xy(self.jerk_xy, self.accel_xy, self.lean_accel_max)


# PX4 v1.16's stock values of the parameters read (its SITL read back: bench/sitl_response.py)
PX4_DEFAULTS = {"MPC_XY_VEL_MAX": 12.0, "MPC_ACC_HOR": 3.0, "MPC_Z_VEL_MAX_UP": 3.0, "MPC_Z_VEL_MAX_DN": 1.5,
                "MPC_ACC_UP_MAX": 4.0, "MPC_JERK_MAX": 8.0, "MPC_TILTMAX_AIR": 45.0, "MPC_XY_P": 0.95,
                "MPC_XY_VEL_P_ACC": 1.8, "MPC_XY_VEL_I_ACC": 0.4, "MPC_XY_VEL_D_ACC": 0.2}
# the airframe terms fitted to PX4's SIH quad (SIH_MASS 1 kg, SIH_KDV 1 N/(m/s): 1.0 /s of drag by its
# physics): python -m bench.sitl_response --fit tests/data/sitl_response_px4.json.gz
PX4_SIH_AIRFRAME = {"lean_tc": 0.131, "drag": 0.0, "drag_lin": 1.012}


def is_px4(params) -> bool:
    """The parameter set is PX4's (its multicopter position controller's MPC_* names)."""
    return any(name in params for name in PX4_DEFAULTS)


def limits_from_params(params, pos_noise: float = VehicleLimits.pos_noise) -> VehicleLimits:
    """VehicleLimits from ArduCopter parameters in its units (cm, cm/s, cdeg), or from PX4's
    (``is_px4``: m/s, m/s^2, deg; PX4's controller and its SIH airframe): any mapping that
    answers ``name in params`` and ``params[name]`` (the mock's Params, a dict of the values a
    vehicle reported); a parameter missing keeps the autopilot's default."""
    def get(name: str, default: float) -> float:
        return float(params[name]) if name in params else default

    if is_px4(params):
        px4 = {k: get(k, v) for k, v in PX4_DEFAULTS.items()}
        return VehicleLimits(
            speed_xy=max(px4["MPC_XY_VEL_MAX"], 0.1), speed_up=px4["MPC_Z_VEL_MAX_UP"],
            speed_down=px4["MPC_Z_VEL_MAX_DN"], accel_xy=px4["MPC_ACC_HOR"], accel_z=px4["MPC_ACC_UP_MAX"],
            jerk_z=px4["MPC_JERK_MAX"], angle_max=math.radians(px4["MPC_TILTMAX_AIR"]),
            pos_p=px4["MPC_XY_P"], vel_p=px4["MPC_XY_VEL_P_ACC"], vel_i=px4["MPC_XY_VEL_I_ACC"],
            vel_d=px4["MPC_XY_VEL_D_ACC"], pos_noise=pos_noise, shaping=False, **PX4_SIH_AIRFRAME)

    return VehicleLimits(
        speed_xy=max(get("WPNAV_SPEED", 1000.0), 20.0) / 100.0,  # AC_WPNav's minimum 20 cm/s
        speed_up=max(get("WPNAV_SPEED_UP", 250.0), 10.0) / 100.0,
        speed_down=max(abs(get("WPNAV_SPEED_DN", 150.0)), 10.0) / 100.0,
        accel_xy=max(get("WPNAV_ACCEL", 250.0), 50.0) / 100.0,
        accel_z=max(get("WPNAV_ACCEL_Z", 100.0), 50.0) / 100.0,
        jerk_xy=max(get("PSC_JERK_XY", 5.0), 0.5),
        jerk_z=max(get("PSC_JERK_Z", 5.0), 0.5),
        angle_max=math.radians(get("ANGLE_MAX", 3000.0) / 100.0),
        lean_accel_max=math.radians(min(get("ATC_ACCEL_R_MAX", 110000.0), get("ATC_ACCEL_P_MAX", 110000.0)) / 100.0),
        pos_p=get("PSC_POSXY_P", 1.0),
        vel_p=get("PSC_VELXY_P", 2.0),
        vel_i=get("PSC_VELXY_I", 1.0),
        vel_d=get("PSC_VELXY_D", 0.5),
        pos_noise=pos_noise,
    )


@dataclass(frozen=True)
class XyController:
    """AC_PosControl's horizontal state (local NED x, y): the kinematic target and the loops."""

    pos: Vec2  # target position, m
    vel: Vec2  # target (desired) velocity, m/s
    acc: Vec2  # target (desired) acceleration, m/s^2
    integrator: Vec2  # velocity PID's I term, m/s^2
    error: Vec2  # velocity error after the 5 Hz filter, m/s
    error_rate: Vec2  # its filtered derivative, m/s^2
    lean_acc: Vec2  # horizontal acceleration of the thrust the vehicle is leaning into, m/s^2
    limit: Vec2  # direction the acceleration was limited in last step (zero: not limited)


@dataclass(frozen=True)
class VehicleState:
    """Vehicle in local NED (m, m/s, m/s^2, rad) and its position controller.

    ``xy`` None: the controller starts from the vehicle at the next step (init_xy_controller);
    set it to None where ArduCopter re-initialises it (a new mode or GUIDED sub-mode).
    """

    pos: Vec3 = (0.0, 0.0, 0.0)
    vel: Vec3 = (0.0, 0.0, 0.0)
    acc: Vec3 = (0.0, 0.0, 0.0)
    yaw: float = 0.0
    xy: Optional[XyController] = None


@dataclass(frozen=True)
class Setpoint:
    """What the position controller is asked to do; None means "not commanded".

    - pos set, vel None: go to pos and stop there (input_pos_xyz);
    - pos and vel set: fly through pos at vel, acc (if set) as feed-forward
      (input_pos_vel_accel_xy; the caller moves pos and vel on with advance_input);
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


def advance_input(pos: Vec3, vel: Vec3, acc: Optional[Vec3], dt: float) -> tuple[Vec3, Vec3]:
    """A GUIDED position + velocity (+ acceleration) setpoint moved on by dt, as ArduCopter moves
    it between messages (input_pos_vel_accel_xy projects the input it is given)."""
    a = acc or (0.0, 0.0, 0.0)
    p = tuple(pos[i] + vel[i] * dt + 0.5 * a[i] * dt * dt for i in range(3))
    v = tuple(vel[i] + a[i] * dt for i in range(3))
    return p, v  # type: ignore[return-value]


def _init_xy(state: VehicleState) -> XyController:
    """init_xy_controller: the target at the vehicle, its velocity, no acceleration; the I term
    holds the lean the vehicle already has."""
    lean = state.xy.lean_acc if state.xy is not None else (state.acc[0], state.acc[1])
    return XyController(pos=(state.pos[0], state.pos[1]), vel=(state.vel[0], state.vel[1]),
                        acc=(0.0, 0.0), integrator=lean, error=(0.0, 0.0), error_rate=(0.0, 0.0),
                        lean_acc=lean, limit=(0.0, 0.0))


def _step_xy(state: VehicleState, sp: Setpoint, dt: float, lim: VehicleLimits,
             vmax: float, v_up: float, v_down: float) -> tuple[XyController, Vec2]:
    """One step of AC_PosControl's horizontal axis; returns the controller and the
    horizontal acceleration the airframe gets (lean minus drag)."""
    c = state.xy if state.xy is not None else _init_xy(state)
    amax, jmax = lim.accel_xy, lim.jerk_xy_max()
    pos, vel = (state.pos[0], state.pos[1]), (state.vel[0], state.vel[1])
    pos_err = (c.pos[0] - pos[0], c.pos[1] - pos[1])
    vel_err = c.error
    tpos, tvel = _advance(c.pos, c.vel, c.acc, dt, c.limit, pos_err, vel_err)
    acc_in = (0.0, 0.0) if sp.acc is None else (sp.acc[0], sp.acc[1])
    if sp.pos is not None and sp.vel is None:  # input_pos_xyz: to the point, zero velocity there
        d = (sp.pos[0] - tpos[0], sp.pos[1] - tpos[1], sp.pos[2] - state.pos[2])
        dn = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        v_xy = _kinematic_limit(d, vmax, v_up, v_down) * _len(d[0], d[1]) / dn if dn > 0.0 else 0.0
        tacc = _shape_pos_vel_accel_xy((sp.pos[0], sp.pos[1]), (0.0, 0.0), (0.0, 0.0), tpos, tvel,
                                       c.acc, v_xy, amax, jmax, dt)
    elif sp.pos is not None:  # input_pos_vel_accel_xy
        tacc = _shape_pos_vel_accel_xy((sp.pos[0], sp.pos[1]), (sp.vel[0], sp.vel[1]), acc_in, tpos,
                                       tvel, c.acc, vmax, amax, jmax, dt)
    elif sp.vel is not None:  # input_vel_accel_xy
        tacc = _shape_vel_accel_xy((sp.vel[0], sp.vel[1]), acc_in, tvel, c.acc, amax, jmax, dt)
    elif sp.acc is not None:  # input_accel_xy
        dx, dy = _limit(acc_in[0] - c.acc[0], acc_in[1] - c.acc[1], jmax * dt)
        tacc = (c.acc[0] + dx, c.acc[1] + dy)
    else:  # nothing commanded: brake
        tacc = _shape_vel_accel_xy((0.0, 0.0), (0.0, 0.0), tvel, c.acc, amax, jmax, dt)

    # update_xy_controller: position P (its error capped, dragging the target), velocity PID
    ex, ey = tpos[0] - pos[0], tpos[1] - pos[1]
    err_max = inv_sqrt_controller(vmax, lim.pos_p, amax) if lim.pos_p > 0.0 else 0.0
    if err_max > 0.0 and _len(ex, ey) > err_max:
        ex, ey = _limit(ex, ey, err_max)
        tpos = (pos[0] + ex, pos[1] + ey)
    cvx, cvy = _sqrt_2d(ex, ey, lim.pos_p, amax, 0.0)
    vtx, vty = cvx + tvel[0], cvy + tvel[1]
    alpha = dt / (dt + 1.0 / (2.0 * math.pi * lim.vel_filt_hz)) if lim.vel_filt_hz > 0.0 else 1.0
    raw = (vtx - vel[0], vty - vel[1])
    err = (c.error[0] + (raw[0] - c.error[0]) * alpha, c.error[1] + (raw[1] - c.error[1]) * alpha)
    der = ((err[0] - c.error[0]) / dt, (err[1] - c.error[1]) / dt)
    rate = (c.error_rate[0] + (der[0] - c.error_rate[0]) * alpha,
            c.error_rate[1] + (der[1] - c.error_rate[1]) * alpha)
    # AC_PID_2D::update_i: the I term does not grow towards a limited output
    dix, diy = err[0] * lim.vel_i * dt, err[1] * lim.vel_i * dt
    ix, iy = c.integrator[0] + dix, c.integrator[1] + diy
    if dix * c.limit[0] + diy * c.limit[1] > 0.0:
        ix, iy = _limit(ix, iy, _len(*c.integrator))
    ix, iy = _limit(ix, iy, lim.vel_imax)
    ax = lim.vel_p * err[0] + ix + lim.vel_d * rate[0] + tacc[0]
    ay = lim.vel_p * err[1] + iy + lim.vel_d * rate[1] + tacc[1]
    (ax, ay), limited = _limit_accel_xy(tvel, (ax, ay), GRAVITY * math.tan(lim.angle_max))
    limit = (ax, ay) if limited else (0.0, 0.0)

    # the airframe: the lean follows the demand with a lag; drag opposes the velocity
    k = dt / (lim.lean_tc + dt) if lim.lean_tc > 0.0 else 1.0
    lean = (c.lean_acc[0] + (ax - c.lean_acc[0]) * k, c.lean_acc[1] + (ay - c.lean_acc[1]) * k)
    drag = lim.drag * _len(*vel)
    acc = (lean[0] - drag * vel[0], lean[1] - drag * vel[1])
    return XyController(pos=tpos, vel=tvel, acc=tacc, integrator=(ix, iy), error=err, error_rate=rate,
                        lean_acc=lean, limit=limit), acc


def _step_xy_px4(state: VehicleState, sp: Setpoint, dt: float, lim: VehicleLimits,
                 vmax: float) -> tuple[XyController, Vec2]:
    """One step of PX4's PositionControl, horizontally (see the module), and its airframe."""
    c = state.xy if state.xy is not None else _init_xy(state)
    pos, vel = (state.pos[0], state.pos[1]), (state.vel[0], state.vel[1])
    ff = (0.0, 0.0) if sp.vel is None else (sp.vel[0], sp.vel[1])
    acc_ff = (0.0, 0.0) if sp.acc is None else (sp.acc[0], sp.acc[1])
    if sp.pos is None and sp.vel is None and sp.acc is None:  # nothing commanded: hold here
        sp = Setpoint(pos=(c.pos[0], c.pos[1], state.pos[2]))
    vp = (0.0, 0.0) if sp.pos is None else (lim.pos_p * (sp.pos[0] - pos[0]), lim.pos_p * (sp.pos[1] - pos[1]))
    vsp = _constrain_xy(vp, ff, vmax) if sp.pos is not None or sp.vel is not None else vel
    err = (vsp[0] - vel[0], vsp[1] - vel[1]) if sp.pos is not None or sp.vel is not None else (0.0, 0.0)
    a_meas = (state.acc[0], state.acc[1])
    ax = lim.vel_p * err[0] + c.integrator[0] - lim.vel_d * a_meas[0] + acc_ff[0]
    ay = lim.vel_p * err[1] + c.integrator[1] - lim.vel_d * a_meas[1] + acc_ff[1]
    lx, ly = _limit(ax, ay, GRAVITY * math.tan(lim.angle_max))
    # tracking anti-windup (Rundqwist): the saturated part is taken off the error integrated
    arw = 2.0 / lim.vel_p if lim.vel_p > 0.0 else 0.0
    ix = c.integrator[0] + (err[0] - arw * (ax - lx)) * lim.vel_i * dt
    iy = c.integrator[1] + (err[1] - arw * (ay - ly)) * lim.vel_i * dt
    ix, iy = _limit(ix, iy, lim.vel_imax)
    k = dt / (lim.lean_tc + dt) if lim.lean_tc > 0.0 else 1.0
    lean = (c.lean_acc[0] + (lx - c.lean_acc[0]) * k, c.lean_acc[1] + (ly - c.lean_acc[1]) * k)
    drag = lim.drag * _len(*vel) + lim.drag_lin
    acc = (lean[0] - drag * vel[0], lean[1] - drag * vel[1])
    target = (sp.pos[0], sp.pos[1]) if sp.pos is not None else pos
    return XyController(pos=target, vel=vsp, acc=acc_ff, integrator=(ix, iy), error=err, error_rate=(0.0, 0.0),
                        lean_acc=lean, limit=(0.0, 0.0)), acc


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

    Horizontally the shaped target never asks for more than setpoint.speed_xy or
    limits.speed_xy towards a position-only setpoint (a position + velocity or velocity setpoint
    adds its own velocity, which ArduCopter does not cap), and the airframe's drag at the lean
    limit caps the speed flown. Vertically the climb/descent rates never exceed
    speed_up/speed_down. With rng given, a small random-walk position disturbance of
    limits.pos_noise m/sqrt(s) is added (the controller then corrects it).
    """
    if dt <= 0.0:
        return state
    vmax = setpoint.speed_xy if setpoint.speed_xy else limits.speed_xy
    v_up = setpoint.speed_up if setpoint.speed_up else limits.speed_up
    v_down = setpoint.speed_down if setpoint.speed_down else limits.speed_down
    if limits.shaping:
        xy, (ax, ay) = _step_xy(state, setpoint, dt, limits, vmax, v_up, v_down)
    else:
        xy, (ax, ay) = _step_xy_px4(state, setpoint, dt, limits, vmax)
    az = _shape_z(
        None if setpoint.pos is None else setpoint.pos[2] - state.pos[2],
        None if setpoint.vel is None else setpoint.vel[2],
        0.0 if setpoint.acc is None else setpoint.acc[2],
        state.vel[2], state.acc[2], v_up, v_down, limits.accel_z, limits.jerk_z, dt)
    vx, vy = state.vel[0] + ax * dt, state.vel[1] + ay * dt
    vz = max(-v_up, min(v_down, state.vel[2] + az * dt))
    px = state.pos[0] + 0.5 * (state.vel[0] + vx) * dt
    py = state.pos[1] + 0.5 * (state.vel[1] + vy) * dt
    pz = state.pos[2] + 0.5 * (state.vel[2] + vz) * dt
    if rng is not None and limits.pos_noise > 0.0:
        nx, ny, nz = rng.normal(0.0, limits.pos_noise * math.sqrt(dt), 3)
        px, py, pz = px + float(nx), py + float(ny), pz + float(nz)

    yaw = state.yaw
    max_turn = limits.yaw_rate * dt
    if setpoint.yaw is not None:
        yaw += max(-max_turn, min(max_turn, wrap_pi(setpoint.yaw - yaw)))
    elif setpoint.yaw_rate is not None:
        yaw += max(-max_turn, min(max_turn, setpoint.yaw_rate * dt))
    return VehicleState(pos=(px, py, pz), vel=(vx, vy, vz), acc=(ax, ay, az), yaw=wrap_pi(yaw), xy=xy)


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
    return replace(state, pos=_vec(pos), vel=_vec(vel), acc=_vec(acc), xy=None)


def on_ground(state: VehicleState, ground_z: float = 0.0) -> VehicleState:
    """Clamp the state to the ground plane z = ground_z (NED, so below means z > ground_z).
    On the ground the horizontal controller is relaxed: it starts again from the vehicle."""
    if state.pos[2] < ground_z:
        return state
    vz = min(state.vel[2], 0.0)
    az = min(state.acc[2], 0.0)
    return replace(
        state,
        pos=(state.pos[0], state.pos[1], ground_z),
        vel=(state.vel[0], state.vel[1], vz),
        acc=(state.acc[0], state.acc[1], az),
        xy=None,
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
    """(roll, pitch, yaw) in rad: the lean into the thrust's horizontal acceleration."""
    an, ae = state.xy.lean_acc if state.xy is not None else state.acc[:2]
    c, s = math.cos(state.yaw), math.sin(state.yaw)
    forward = an * c + ae * s
    right = -an * s + ae * c
    return (math.atan2(right, GRAVITY), -math.atan2(forward, GRAVITY), state.yaw)


def _vec(a: np.ndarray) -> Vec3:
    return (float(a[0]), float(a[1]), float(a[2]))
