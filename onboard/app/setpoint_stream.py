"""What the app sends the autopilot to fly the plan, as SET_POSITION_TARGET_LOCAL_NED.

- The vehicle motion (the flight policy): the plan's state at the moment of sending, position +
  velocity + acceleration (type_mask 3072), from the segment the tick planned
  (``onboard.core.setpoint.plan_setpoint``). ArduCopter's GUIDED carries such a target on by
  itself between messages and flies through the planned point at speed; measured on its SITL
  0.5-0.7 m from the planned point at the next tick, against 16-27 m with the position alone,
  which it brakes to (bench/sitl_response.py, docs/PLANNING.md). PX4's OFFBOARD takes the same
  fields as feed-forward.
- The jump model (the paper's policy): the planned point alone (type_mask 3576), as before.

Frames: the plan is in the mission's ENU frame; the message in LOCAL_NED at the autopilot's
origin (``Frame.ned_from_enu`` for positions; a vector's ENU -> NED is (n, e, -u)).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.core.setpoint import plan_setpoint

POSITION_ONLY = 3576  # type_mask: velocity, acceleration, yaw, yaw rate ignored
POS_VEL_ACCEL = 3072  # type_mask: yaw and yaw rate ignored (ArduCopter's PosVelAccel sub-mode)


@dataclass(frozen=True, eq=False)
class PlannedSegment:
    """The plan between two ticks: from ``p0`` (ENU m) with velocity ``v0`` at autopilot time
    ``t0`` to the next planned point with ``v1`` (planar ENU m/s) one tick (``tick_s``) later."""

    t0: float
    p0: np.ndarray  # (3,)
    v0: np.ndarray  # (2,)
    v1: np.ndarray  # (2,)
    tick_s: float

    def at(self, now: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position, velocity, acceleration), ENU, of the plan at autopilot time ``now``
        (held at the segment's ends outside it: a late tick leaves the target on the planned
        point with its velocity, which the autopilot carries on)."""
        d = min(max(now - self.t0, 0.0), self.tick_s)
        pos, vel, acc = plan_setpoint(self.p0[:2], self.v0, self.v1, self.tick_s, d)
        return (np.array([pos[0], pos[1], self.p0[2]]), np.array([vel[0], vel[1], 0.0]),
                np.array([acc[0], acc[1], 0.0]))


def enu_to_ned_vector(v) -> np.ndarray:
    return np.array([v[1], v[0], -v[2]], dtype=float)


def message(mav, now: float, sysid: int, compid: int, ned_pos, ned_vel=None, ned_acc=None):
    """The SET_POSITION_TARGET_LOCAL_NED for a position (and, if given, velocity and
    acceleration feed-forward), all NED at the autopilot's origin; ``now``: autopilot s."""
    z3 = (0.0, 0.0, 0.0)
    mask = POSITION_ONLY if ned_vel is None else POS_VEL_ACCEL
    vel = z3 if ned_vel is None else ned_vel
    acc = z3 if ned_acc is None else ned_acc
    return mav.set_position_target_local_ned_encode(
        int(now * 1000) & 0xFFFFFFFF, sysid, compid, 1,  # MAV_FRAME_LOCAL_NED
        mask, *(float(x) for x in ned_pos), *(float(x) for x in vel), *(float(x) for x in acc), 0.0, 0.0)
