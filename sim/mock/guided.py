"""What an ArduCopter flies in GUIDED from the setpoints it is sent (pure; local NED, SI units).

ArduCopter 4.4 (ModeGuided, GCS_MAVLink's SET_POSITION_TARGET_LOCAL_NED handler) picks the
GUIDED sub-mode from which fields the type_mask keeps:

- position only: ``Pos`` (``set_destination``): AC_PosControl's input_pos_xyz shapes a path that
  stops at the point (it brakes to every setpoint);
- position + velocity (+ acceleration): ``PosVelAccel`` (``set_destination_posvelaccel``):
  input_pos_vel_accel_xy shapes a path onto a target that the firmware itself moves on between
  messages (position += velocity dt + acceleration dt^2 / 2, velocity += acceleration dt) and
  flies through at that velocity; after GUID_TIMEOUT (3 s) without a message the velocity and
  acceleration are zeroed and the copter stops at the target;
- velocity (+ acceleration): ``VelAccel``; acceleration only: ``Accel``.
Entering a sub-mode re-initialises the position controller at the vehicle (pva_control_start);
a message of the same sub-mode only replaces the target.

``fly`` is one tick of that; ``fly_plan`` is one tick of the evaluation's vehicle following
its plan with the app's setpoint (onboard.core.setpoint); ``fly_timeline`` replays a timed
sequence of setpoints (tests/sim/test_vehicle.py replays the real SITL's with it). With
``offboard=True`` it replays them as PX4's OFFBOARD takes them: each held as sent until the next
(no sub-modes, no GUID_TIMEOUT; the stream's own loss timeout is not modelled). ``fly_plan`` with
PX4's limits (``limits.shaping`` False) keeps ArduCopter's moving target: the app sends PX4 the
plan's state again at 10 Hz, which that target follows between ticks. Frames: local
NED, as sent; the mission frame's ENU point (x east, y north, z up) is NED (y, x, -z) (``ned``,
``enu``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Iterable, Optional, Sequence

import numpy as np

from onboard.core.setpoint import plan_setpoint
from sim.mock.multicopter import Setpoint, Vec3, VehicleLimits, VehicleState, advance_input, step

FIRMWARE_HZ = 400.0  # ArduCopter's main loop (SCHED_LOOP_RATE) runs the position controller
GUID_TIMEOUT_S = 3.0  # GUID_TIMEOUT's default
RESEND_HZ = 10.0  # the app's setpoint re-send rate (PMON_SP_HZ's default)


@dataclass(frozen=True)
class GuidedSetpoint:
    """One SET_POSITION_TARGET_LOCAL_NED as ArduCopter reads it (local NED; None: ignored by the
    type_mask). pos with vel: fly through pos at vel (acc, if set, as feed-forward)."""

    pos: Optional[Vec3] = None
    vel: Optional[Vec3] = None
    acc: Optional[Vec3] = None

    def __post_init__(self):
        if self.pos is None and self.vel is None and self.acc is None:
            raise ValueError("GuidedSetpoint: no position, velocity or acceleration")
        if self.pos is not None and self.vel is None and self.acc is not None:
            raise ValueError("GuidedSetpoint: position + acceleration without velocity "
                             "(ArduCopter rejects it and holds)")

    @property
    def submode(self) -> str:
        if self.pos is not None:
            return "pos" if self.vel is None and self.acc is None else "posvelaccel"
        return "velaccel" if self.vel is not None else "accel"


def fly(state: VehicleState, setpoint: GuidedSetpoint, duration_s: float,
        limits: VehicleLimits = VehicleLimits(), rate_hz: float = FIRMWARE_HZ,
        new_submode: bool = False, timeout_s: float = GUID_TIMEOUT_S) -> VehicleState:
    """The vehicle ``duration_s`` after ``setpoint`` arrives, with no other message meanwhile,
    stepped at ``rate_hz`` (the firmware's 400 Hz by default, about 6 ms of CPU per simulated second;
    the mock's 50 Hz moves the flown position by under 0.15 m over a recorded route,
    tests/sim/test_vehicle.py).

    ``new_submode``: the previous message was of another GUIDED sub-mode (or none was sent in
    GUIDED yet): the controller restarts at the vehicle, as ArduCopter does. Sending position +
    velocity every tick keeps one sub-mode: pass False after the first.
    """
    if new_submode:
        state = replace(state, xy=None)
    return fly_timeline(state, [(0.0, setpoint)], [duration_s], limits, rate_hz, timeout_s,
                        submode=setpoint.submode)[-1]


def fly_timeline(state: VehicleState, sends: Sequence[tuple[float, GuidedSetpoint]],
                 sample_times: Iterable[float], limits: VehicleLimits = VehicleLimits(),
                 rate_hz: float = FIRMWARE_HZ, timeout_s: float = GUID_TIMEOUT_S,
                 submode: Optional[str] = None, hold: Optional[Vec3] = None,
                 offboard: bool = False) -> list[VehicleState]:
    """Replay setpoints received at times ``sends[i][0]`` (s, ascending, on the clock the state
    is at t = 0) and return the vehicle at each of ``sample_times`` (ascending, >= 0).

    Before the first send the copter holds ``hold`` (position only; None: where it is);
    ``submode`` is the GUIDED sub-mode it was in (None: a new one, the controller restarts).
    ``offboard``: PX4's OFFBOARD (see the module)."""
    dt = 1.0 / rate_hz
    times = list(sample_times)
    out: list[VehicleState] = []
    cur = GuidedSetpoint(pos=hold if hold is not None else state.pos)
    cur_t = 0.0
    cur_mode = submode
    i, t, n = 0, 0.0, 0
    pos, vel, acc = cur.pos, cur.vel, cur.acc
    for ts in times:
        while True:
            while i < len(sends) and sends[i][0] <= t + 1e-9:
                cur_t, cur = sends[i]
                i += 1
                if cur.submode != cur_mode and not offboard:
                    state = replace(state, xy=None)  # pva_control_start: init_xy_controller
                    cur_mode = cur.submode
                pos, vel, acc = cur.pos, cur.vel, cur.acc
            if t >= ts - 1e-9:
                break
            timed_out = t - cur_t > timeout_s
            if offboard:
                state = step(state, Setpoint(pos=pos, vel=vel, acc=acc), dt, limits)
            elif cur.submode == "posvelaccel":
                v = (0.0, 0.0, 0.0) if timed_out or vel is None else vel
                a = None if timed_out else acc
                state = step(state, Setpoint(pos=pos, vel=v, acc=a), dt, limits)
                pos, vel_next = advance_input(pos, v, a, dt)
                if not timed_out:
                    vel = vel_next
            elif cur.submode == "pos":
                state = step(state, Setpoint(pos=pos), dt, limits)
            elif cur.submode == "velaccel":
                state = step(state, Setpoint(vel=(0.0, 0.0, 0.0) if timed_out else vel,
                                             acc=None if timed_out else acc), dt, limits)
            else:  # accel; timed out: brake (input_vel_accel to zero)
                state = step(state, Setpoint() if timed_out else Setpoint(acc=acc), dt, limits)
            n += 1
            t = n * dt
        out.append(state)
    return out


def ned(p_enu) -> Vec3:
    """A mission-frame ENU vector (x east, y north, z up) in local NED."""
    return (float(p_enu[1]), float(p_enu[0]), -float(p_enu[2]))


def enu(p_ned) -> np.ndarray:
    """A local NED vector in the mission frame's ENU."""
    return np.array([p_ned[1], p_ned[0], -p_ned[2]], dtype=float)


def fly_plan(state: VehicleState, v_next: Optional[Sequence[float]], altitude_m: float, tick_s: float,
             limits: VehicleLimits = VehicleLimits(), first: bool = False,
             rate_hz: float = FIRMWARE_HZ, a_k: Optional[Sequence[float]] = None) -> VehicleState:
    """The vehicle one tick after the app sends the plan's setpoint at the tick (no latency).

    The plan starts where the vehicle is, at its velocity (what the app's telemetry says), and
    asks for the planar velocity ``v_next`` (ENU, m/s) one tick later: the setpoint is the
    plan's position + velocity + acceleration (onboard.core.setpoint.plan_setpoint) at
    ``altitude_m``. ``v_next`` None (no admissible move): the same kind of setpoint at rest
    where the vehicle is, which it brakes back to. ``first``: the first setpoint in GUIDED (the
    controller starts at the vehicle); every later one is of the same sub-mode. ``a_k`` (ENU,
    m/s^2): the plan's acceleration at the tick, for a continuous one (None: constant over the
    tick): its state is sent again every 1 / RESEND_HZ s as the app does (the autopilot carries
    each message's acceleration on as constant; a constant one needs no re-send here)."""
    here = enu(state.pos)
    if v_next is None:
        pos, vel, acc = here[:2], np.zeros(2), np.zeros(2)
    elif a_k is not None:
        v0, v1, a0 = enu(state.vel)[:2], np.asarray(v_next, float)[:2], np.asarray(a_k, float)[:2]
        sends = []
        for d in np.arange(0.0, tick_s - 1e-9, 1.0 / RESEND_HZ):
            pos, vel, acc = plan_setpoint(here[:2], v0, v1, tick_s, float(d), a0)
            sends.append((float(d), GuidedSetpoint(pos=ned((pos[0], pos[1], altitude_m)), vel=ned((vel[0], vel[1], 0.0)),
                                                   acc=ned((acc[0], acc[1], 0.0)))))
        return fly_timeline(state, sends, [tick_s], limits, rate_hz,
                            submode=None if first else "posvelaccel")[-1]
    else:
        pos, vel, acc = plan_setpoint(here[:2], enu(state.vel)[:2], np.asarray(v_next, float)[:2], tick_s)
    sp = GuidedSetpoint(pos=ned((pos[0], pos[1], altitude_m)), vel=ned((vel[0], vel[1], 0.0)),
                        acc=ned((acc[0], acc[1], 0.0)))
    return fly(state, sp, tick_s, limits, rate_hz, new_submode=first)
