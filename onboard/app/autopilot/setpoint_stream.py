"""What the app sends the autopilot to fly the plan, as SET_POSITION_TARGET_LOCAL_NED.

- The vehicle motion (the flight policy): the plan's state at the moment of sending, position +
  velocity + acceleration (type_mask 3072), from the segment the tick planned
  (``onboard.core.setpoint.plan_setpoint``): it starts at the scan the tick answers, where the
  vehicle was then, and its acceleration at the last segment's end (continuous, ramping over the
  tick). ArduCopter's GUIDED carries such a target on by itself between messages and flies
  through the planned point at speed, where the position alone makes it brake to each point
  (how close it follows: bench/ardupilot.py, bench/sitl_response.py, docs/SITL.md).
  PX4's OFFBOARD takes the same fields as feed-forward.
- The jump model (the paper's policy): the planned point alone (type_mask 3576), as before.

Frames: the plan is in the mission's ENU frame; the message in LOCAL_NED at the autopilot's
origin (``Frame.ned_from_enu`` for positions; a vector's ENU -> NED is (n, e, -u)).

``SetpointStream`` holds the setpoint the last tick adopted and sends it: at once when adopted,
then re-sent at PMON_SP_HZ of autopilot time while the app commands. Every message is checked
against the fence as it goes out (fence.outgoing_violation); one that fails is not sent, and
the setpoint is dropped (the vehicle holds the last good one). io thread and worker, under the
app lock.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from onboard.app.autopilot.fence import Fence, outgoing_violation, violation
from onboard.app.context import AppContext
from onboard.app.mavlink_connection import mavlink
from onboard.app.part import Job, Part
from onboard.core.setpoint import plan_setpoint

POSITION_ONLY = 3576  # type_mask: velocity, acceleration, yaw, yaw rate ignored
POS_VEL_ACCEL = 3072  # type_mask: yaw and yaw rate ignored (ArduCopter's PosVelAccel sub-mode)


@dataclass(frozen=True, eq=False)
class PlannedSegment:
    """The plan between two ticks: from ``p0`` (ENU m) with velocity ``v0`` at autopilot time
    ``t0`` to the next planned point with ``v1`` (planar ENU m/s) one tick (``tick_s``) later;
    ``a0`` (planar ENU m/s^2): its acceleration at ``t0``, continuous with the last segment's
    (onboard/core/setpoint.py), None: constant over the tick. The plan is planar: its altitude
    is ``p0[2]``, the planned point's (h), held throughout."""

    t0: float
    p0: np.ndarray  # (3,)
    v0: np.ndarray  # (2,)
    v1: np.ndarray  # (2,)
    tick_s: float
    a0: np.ndarray | None = None  # (2,)

    def at(self, now: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position, velocity, acceleration), ENU, of the plan at autopilot time ``now``
        (held at the segment's ends outside it: a late tick leaves the target on the planned
        point with its velocity, which the autopilot carries on)."""
        d = min(max(now - self.t0, 0.0), self.tick_s)
        pos, vel, acc = plan_setpoint(self.p0[:2], self.v0, self.v1, self.tick_s, d, self.a0)
        return (np.array([pos[0], pos[1], self.p0[2]]), np.array([vel[0], vel[1], 0.0]),
                np.array([acc[0], acc[1], 0.0]))

    def end_acceleration(self) -> np.ndarray:
        """(2,) ENU m/s^2: the plan's acceleration at its end, where the next segment's starts."""
        return self.at(self.t0 + self.tick_s)[2][:2]


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


class SetpointStream(Part):
    """``autopilot``: the autopilot side (its vehicle, frame and fixed origin); ``setup()``: the
    core setup now (its area and obstacles make the fence); ``may_stream()``: whether the
    setpoint may be re-sent now (the state machine's); ``ctx``: the app's link, parameters,
    counters, voice and local clock."""

    def __init__(self, ctx: AppContext, autopilot, setup: Callable[[], object], may_stream: Callable[[], bool]):
        self.link = ctx.link
        self.autopilot = autopilot
        self.params = ctx.params
        self.setup = setup
        self.may_stream = may_stream
        self.counters = ctx.counters
        self.say = ctx.say
        self.mono = ctx.mono
        self.setpoint: np.ndarray | None = None  # ENU, m, checked safe: the planned next point
        self.segment: PlannedSegment | None = None  # vehicle motion: the plan to it
        self.next_t = -np.inf  # autopilot s of the next re-send
        self.sent: deque[tuple[float, float, np.ndarray]] = deque(maxlen=600)  # (ap t, local t, enu)

    def clear(self) -> None:
        """Stop: no setpoint until a tick adopts one."""
        self.setpoint = self.segment = None

    def restart(self) -> None:
        """The next setpoint goes out as soon as there is one."""
        self.next_t = -np.inf

    def adopt(self, point, segment: PlannedSegment | None, now: float, centre, setup) -> tuple[bool, str | None]:
        """A tick's next point (ENU) and the plan to it: checked against the fence of the tick's
        ``setup`` (``centre``: where the vehicle is, for the path rule), then sent at once.
        Returns (sent, why refused); a refused point leaves the previous setpoint in place."""
        refused = violation(Fence.of(setup, self.params), point, centre)
        if refused is not None:
            self.counters.add("setpoints_refused")
            self.say(f"setpoint refused: {refused}", mavlink.MAV_SEVERITY_ERROR)
            return False, refused
        previous = self.setpoint, self.segment
        self.setpoint, self.segment = np.array(point, float), segment
        sent = self.send(now, centre)
        if self.setpoint is None:  # refused as sent: the previous one stays
            self.setpoint, self.segment = previous
            return sent, "refused as sent"
        return sent, None

    def jobs(self) -> tuple[Job, ...]:
        return (Job("setpoint stream", self.periodic, clocked=True),)

    def periodic(self, local: float, now: float) -> None:
        if self.may_stream():
            self.stream(now)

    def stream(self, now: float) -> None:
        """The periodic re-send (the caller decides whether the app commands now)."""
        if self.setpoint is not None and now >= self.next_t:
            self.send(now)

    def send(self, now: float, centre=None) -> bool:
        """Send the setpoint in LOCAL_NED at the fixed origin: with a planned segment (vehicle
        motion) the plan's position, velocity and acceleration at ``now``, else the point alone;
        the message checked against the fence before it goes (its position read back to ENU).
        A message that fails is not sent: counted, said, and the setpoint dropped. ``centre``:
        where the vehicle was when the tick planned it (path rule, first send only)."""
        ap = self.autopilot
        v = ap.vehicle
        if v.ned_origin is None:
            return False
        if self.segment is not None:
            pos, vel, acc = self.segment.at(now)
            msg = message(self.link.mav, now, v.sysid, v.compid, ap.frame.ned_from_enu(pos, v.ned_origin),
                          enu_to_ned_vector(vel), enu_to_ned_vector(acc))
        else:
            pos = np.asarray(self.setpoint, float)
            msg = message(self.link.mav, now, v.sysid, v.compid, ap.frame.ned_from_enu(pos, v.ned_origin))
        self.next_t = now + 1.0 / self.params.settings.app.setpoint_hz
        refused = outgoing_violation(msg, ap.frame, ap.origin.value,
                                     Fence.of(self.setup(), self.params, at_altitude=False), centre)
        if refused is not None:
            self.counters.add("setpoints_refused")
            self.counters.add("setpoints_refused_at_send")
            self.clear()
            self.say(f"setpoint refused as sent: {refused}", mavlink.MAV_SEVERITY_ERROR)
            return False
        ok = self.link.send(msg)
        if ok:
            self.sent.append((now, self.mono(), np.array(pos, float)))
        return ok
