"""How the real ArduCopter SITL follows GUIDED setpoints (PX4's SITL, OFFBOARD ones), and how
sim/multicopter.py does on the same ones.

    python bench/sitl_response.py [--limits stock,demo] [--cases top,step20,step100,ramp,route90,route70]
                                  [--speedup 4] [--param NAME=VALUE ...] [--save FILE.json.gz]
    python bench/sitl_response.py --autopilot px4 [--speedup 2] [--save FILE.json.gz]
    python bench/sitl_response.py --replay tests/data/sitl_response.json.gz   # the model, no SITL
    python bench/sitl_response.py --fit tests/data/sitl_response.json.gz      # its airframe terms

Boots ArduPilot's own SITL firmware (sim/ardupilot.py; set PMON_ARDUPILOT_SITL) once per set of
limits, takes off in GUIDED to 20 m and flies each case from a settled hover where the last one
ended (its coordinates are relative to that point, local NED, metres):

- ``top``: a velocity-only command at 3x WPNAV_SPEED for 15 s: the airframe's top speed (the
  drag at ANGLE_MAX; ArduCopter does not cap a velocity command at WPNAV_SPEED);
- ``step20``, ``step100``: one position-only SET_POSITION_TARGET_LOCAL_NED 20 m / 100 m away;
- ``ramp``: a target moving in a straight line at half the lower of WPNAV_SPEED and the top
  speed, sent at 10 Hz as position + velocity (its position at the send time, its velocity);
- ``routeNN``: a planner-like route, one setpoint per second: from hover, accelerate at half
  WPNAV_ACCEL to NN % of the lower of WPNAV_SPEED and the top speed, then six legs with turns
  of 90, -120, 60, -150, 45 deg at 0.6x WPNAV_ACCEL. It is flown four times, each sending, at
  tick k (the plan's time k s, when the setpoint is sent d s after it), for p[k], v[k]: the
  plan's position and velocity at k, T = 1 s:
  ``pos``: p[k+1], position only (what the app sends today: the copter brakes to each point);
  ``posvel_next``: p[k+1] with v[k+1] (the point and the velocity to fly through it);
  ``ramp``: p[k] + d c with c = (p[k+1] - p[k]) / T (a target that reaches p[k+1] when the
  next setpoint is due);
  ``pva``: the plan's state at k + d: p[k] + d v[k] + d^2 a / 2, v[k] + d a, and a =
  (v[k+1] - v[k]) / T as acceleration (the firmware integrates it to p[k+1], v[k+1]); what the
  app sends, computed by the same function (onboard.core.setpoint.plan_setpoint).

PX4 (``--autopilot px4``: PX4 v1.16 SITL, SIH quad, sim/px4.py; set PMON_PX4_SITL): armed in
Hold, NAV_TAKEOFF to 20 m (AMSL), then OFFBOARD entered the way PX4 requires (setpoints first).
PX4 holds a setpoint as sent and leaves OFFBOARD 1 s after the last, so every setpoint is sent
again at 10 Hz of PX4's clock as the app does (PMON_SP_HZ): a fixed one as it was, a route's as
the plan's state at that moment. Limits: its stock parameters (``stock``); WPNAV_SPEED /
WPNAV_ACCEL read as MPC_XY_VEL_MAX / MPC_ACC_HOR. The routes are flown three ways: ``pos`` (the
next point, resent), ``posvel`` (the plan's position and velocity at the moment of sending) and
``pva`` (and its acceleration: what the app sends). ``--replay`` of a PX4 flight holds each
setpoint until the next, as PX4 does (sim.guided.fly_timeline(offboard=True)).

Limits: ``stock`` is what the binary boots with (copter.parm over the firmware's defaults: read
back and printed), ``demo`` is sim/multicopter.py's DEMO_VEHICLE_PARAMS. The copter's
LOCAL_POSITION_NED is recorded at ~40 Hz (50 Hz asked) on the firmware's clock (time_boot_ms);
a setpoint's time is the firmware time of the last message received when it was sent.

Printed per case: for routes and the ramp, the horizontal distance from the vehicle to the point
the plan puts it at, when the next 1-s setpoint is due (median, p95, max over the ticks); for
steps, the time to come within 1 m, the overshoot and the peak speed. Last line: JSON of these.
``--save`` writes the traces (10 Hz, horizontal) and every setpoint sent: the reference data of
tests/sim/test_vehicle.py. ``--replay`` gives a saved flight's setpoints to the model
(sim.guided.fly_timeline at the firmware's 400 Hz) and prints its RMS position error on each
trace and its distance at the next tick beside the SITL's.
"""
from __future__ import annotations

import os

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink is imported

import argparse  # noqa: E402
import gzip  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import struct  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field, replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from onboard.core.setpoint import plan_setpoint  # noqa: E402
from sim.multicopter import DEMO_VEHICLE_PARAMS  # noqa: E402
from sim import px4 as px4_sitl  # noqa: E402
from sim.ardupilot import ArduPilotSitl, SitlError, find_binary, param_item, skip_reason  # noqa: E402

HOME = (35.145, 33.411, 160.0)
ALT_M = 20.0
STREAM_HZ = 50.0
TICK_S = 1.0
# type_mask (POSITION_TARGET_TYPEMASK): what is ignored; yaw and yaw rate always ignored
MASK_POS = 0b110111111000
MASK_POSVEL = 0b110111000000
MASK_PVA = 0b110000000000
MASK_VEL = 0b110111000111
READ_PARAMS = ("WPNAV_SPEED", "WPNAV_ACCEL", "WPNAV_SPEED_UP", "WPNAV_SPEED_DN", "PSC_JERK_XY",
               "PSC_POSXY_P", "PSC_VELXY_P", "PSC_VELXY_I", "PSC_VELXY_D", "ATC_ACCEL_R_MAX",
               "ATC_ACCEL_P_MAX", "ATC_RATE_FF_ENAB", "ATC_RATE_R_MAX", "ANGLE_MAX", "GUID_TIMEOUT",
               "GUID_OPTIONS", "FENCE_ENABLE", "SCHED_LOOP_RATE", "WP_YAW_BEHAVIOR")
PX4_READ_PARAMS = ("MPC_XY_VEL_MAX", "MPC_ACC_HOR", "MPC_ACC_HOR_MAX", "MPC_JERK_MAX", "MPC_JERK_AUTO",
                   "MPC_XY_CRUISE", "MPC_XY_P", "MPC_XY_VEL_P_ACC", "MPC_XY_VEL_I_ACC", "MPC_XY_VEL_D_ACC",
                   "MPC_TILTMAX_AIR", "MPC_Z_VEL_MAX_UP", "MPC_Z_VEL_MAX_DN", "MPC_ACC_UP_MAX", "MPC_ACC_DOWN_MAX",
                   "MPC_Z_P", "MPC_THR_HOVER", "SIH_MASS", "SIH_KDV", "SIH_L_ROLL", "COM_OF_LOSS_T")
LIMITS = {"stock": {}, "demo": dict(DEMO_VEHICLE_PARAMS)}
ROUTE_KINDS = ("pos", "posvel_next", "ramp", "pva")
PX4_ROUTE_KINDS = ("pos", "posvel", "pva")
RESEND_S = 0.1  # PX4: every setpoint again at 10 Hz of its clock (the app's PMON_SP_HZ)
PX4_OFFBOARD = 6 << 16


class FlightError(RuntimeError):
    """The SITL did not do what a step of the flight needs; the message says which."""


@dataclass
class Trace:
    """One case as flown: samples on the firmware clock (s), local NED relative to the case's start."""

    name: str
    t: list = field(default_factory=list)
    pos: list = field(default_factory=list)  # (x, y, z) m
    vel: list = field(default_factory=list)  # (vx, vy, vz) m/s
    sends: list = field(default_factory=list)  # (t, mask, pos, vel, acc) as sent, relative
    # (a setpoint's vel / acc is None where the type_mask ignores it)
    plan: list = field(default_factory=list)  # (t, x, y): where the plan puts the vehicle at t

    def as_dict(self, every: int = 5) -> dict:
        """Compact: horizontal samples decimated to STREAM_HZ / every, cm and cm/s resolution."""
        t0 = self.t[0]
        keep = slice(None, None, every)
        return {
            "name": self.name,
            "t": [round(x - t0, 3) for x in self.t[keep]],
            "pos": [[round(p[0], 2), round(p[1], 2)] for p in self.pos[keep]],
            "vel": [[round(v[0], 2), round(v[1], 2)] for v in self.vel[keep]],
            "sends": [[round(s[0] - t0, 3), s[1], [round(c, 3) for c in s[2]],
                       None if s[3] is None else [round(c, 3) for c in s[3]],
                       None if s[4] is None else [round(c, 3) for c in s[4]]] for s in self.sends],
            "plan": [[round(p[0] - t0, 3), round(p[1], 3), round(p[2], 3)] for p in self.plan],
        }


class SitlFlight:
    """A pymavlink client flying the SITL in GUIDED, every message timed on the firmware clock."""

    def __init__(self, url: str, speedup: float, autopilot: str = "ardupilot"):
        self.conn = mavutil.mavlink_connection(url, source_system=245, source_component=191,
                                               dialect="ardupilotmega", autoreconnect=False)
        self.speedup = speedup
        self.px4 = autopilot == "px4"
        # PX4: what to send at time t (s, its clock) until the next setpoint, every RESEND_S
        self.resend = None
        self._resend_ms = 0.0
        self._hb_wall = -math.inf
        self.home_amsl = None
        self.t_ms = 0  # firmware time of the last timed message
        self.pos = (0.0, 0.0, 0.0)
        self.vel = (0.0, 0.0, 0.0)
        self.have_pos = False
        self.recording: Trace | None = None
        self.origin = (0.0, 0.0, 0.0)  # NED of the case's start
        self.texts: list[str] = []
        self.heartbeat = None

    # ----- receiving
    def pump(self, wall_timeout: float = 0.2, until_ms: float | None = None) -> None:
        """Handle the messages received within wall_timeout (at least one read); with until_ms,
        return as soon as the firmware clock reaches it."""
        deadline = time.monotonic() + wall_timeout
        while True:
            self._keep_alive()
            m = self.conn.recv_match(blocking=True, timeout=max(0.0, deadline - time.monotonic()))
            if m is None:
                return
            self._handle(m)
            if time.monotonic() >= deadline or (until_ms is not None and self.t_ms >= until_ms):
                return

    def _keep_alive(self) -> None:
        """PX4: a heartbeat a second (the relay and PX4's links know us by it) and the current
        setpoint again every RESEND_S of PX4's clock."""
        if not self.px4:
            return
        if time.monotonic() - self._hb_wall >= 1.0:
            self._hb_wall = time.monotonic()
            self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 4)
        if self.resend is not None and self.t_ms >= self._resend_ms:
            self._send(*self.resend(self.t_ms / 1000.0))

    def _handle(self, m) -> None:
        kind = m.get_type()
        if kind == "LOCAL_POSITION_NED":
            self.t_ms = max(self.t_ms, m.time_boot_ms)
            self.pos, self.vel = (m.x, m.y, m.z), (m.vx, m.vy, m.vz)
            self.have_pos = True
            r = self.recording
            if r is not None:
                o = self.origin
                r.t.append(m.time_boot_ms / 1000.0)
                r.pos.append((m.x - o[0], m.y - o[1], m.z - o[2]))
                r.vel.append(self.vel)
        elif kind == "GLOBAL_POSITION_INT" and self.home_amsl is None and m.lat != 0:
            self.home_amsl = (m.alt - m.relative_alt) / 1000.0
        elif kind == "STATUSTEXT":
            self.texts.append(m.text)
        elif kind == "HEARTBEAT" and m.get_srcComponent() == 1:
            self.heartbeat = m

    def wait_fw(self, t_s: float, wall_limit: float = 60.0) -> None:
        """Read messages until the firmware clock reaches t_s."""
        deadline = time.monotonic() + wall_limit
        while self.t_ms < t_s * 1000.0:
            if time.monotonic() > deadline:
                raise FlightError(f"firmware clock stuck at {self.t_ms} ms (waiting for {t_s:.2f} s)")
            self.pump(0.05, until_ms=t_s * 1000.0)

    def wait_for(self, pred, what: str, sim_s: float) -> None:
        deadline = time.monotonic() + sim_s / self.speedup + 20.0
        while not pred():
            if time.monotonic() > deadline:
                raise FlightError(f"{what}: not within {sim_s:g} s of simulated time "
                                  f"(last texts: {self.texts[-3:]})")
            self.pump(0.05)

    # ----- sending
    def command(self, cmd: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(1, 1, cmd, 0, *p)

    def set_interval(self, msg_id: int, hz: float) -> None:
        self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)

    def send(self, mask: int, pos, vel=None, acc=None) -> None:
        """A SET_POSITION_TARGET_LOCAL_NED relative to the case's start (local NED); on PX4 it
        is sent again every RESEND_S until the next (``resend`` may be set after, to a plan)."""
        if self.px4:
            self.resend = self.resending(lambda _t: (mask, pos, vel, acc))
        self._send(mask, pos, vel, acc)

    def resending(self, fn):
        """A resend for PX4 from ``fn(t) -> (mask, pos, vel, acc)`` relative to the current
        case's start: it keeps that start when the next case moves the origin."""
        o = self.origin
        return lambda t: (lambda m, p, v, a: (m, tuple(p[i] + o[i] - self.origin[i] for i in range(3)), v, a))(*fn(t))

    def _send(self, mask: int, pos, vel=None, acc=None) -> None:
        self._resend_ms = self.t_ms + RESEND_S * 1000.0
        o = self.origin
        p = (pos[0] + o[0], pos[1] + o[1], pos[2] + o[2])
        v = vel or (0.0, 0.0, 0.0)
        a = acc or (0.0, 0.0, 0.0)
        self.conn.mav.set_position_target_local_ned_send(
            0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, mask, *p, *v, *a, 0.0, 0.0)
        if self.recording is not None:
            self.recording.sends.append((self.t_ms / 1000.0, mask, tuple(pos),
                                         None if mask & 0b111000 else tuple(v),
                                         None if mask & 0b111000000 else tuple(a)))

    def read_params(self, names) -> dict:
        out = {}
        for n in names:
            self.conn.mav.param_request_read_send(1, 1, n.encode(), -1)
        deadline = time.monotonic() + 10.0
        while len(out) < len(names) and time.monotonic() < deadline:
            m = self.conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=0.5)
            if m is not None and m.param_id in names:
                value = float(m.param_value)
                if m.param_type not in (mavlink.MAV_PARAM_TYPE_REAL32, mavlink.MAV_PARAM_TYPE_REAL64):
                    value = float(struct.unpack("<i", struct.pack("<f", m.param_value))[0])  # PX4: bytewise
                out[m.param_id] = round(value, 4)
        return out

    # ----- flight
    def take_off(self) -> None:
        """GUIDED, armed (retried while the pre-arm checks refuse: ~40 s of simulated time after
        boot), NAV_TAKEOFF to ALT_M once LOCAL_POSITION_NED flows (the EKF uses GPS: a take-off
        before that is refused and the copter disarms)."""
        deadline = time.monotonic() + 150.0 / self.speedup + 30.0
        while not self.have_pos:
            if time.monotonic() > deadline:
                raise FlightError(f"no LOCAL_POSITION_NED (EKF origin): {self.texts[-3:]}")
            self.set_interval(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, STREAM_HZ)
            t_end = time.monotonic() + 2.0 / self.speedup + 0.2
            while time.monotonic() < t_end:
                self.pump(0.05)
        self.wait_for(lambda: self.heartbeat is not None, "heartbeat", 10)
        while -self.pos[2] < 1.0:
            if time.monotonic() > deadline:
                raise FlightError(f"no take-off (last texts: {self.texts[-3:]})")
            if self.heartbeat.custom_mode != 4:
                self.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)
            elif not self.heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED:
                self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            else:
                self.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, ALT_M)  # lat/lon 0, never NaN
            t_end = time.monotonic() + 2.0 / self.speedup + 0.2
            while time.monotonic() < t_end:
                self.pump(0.05)
        self.wait_for(lambda: -self.pos[2] > ALT_M - 0.5, "take-off to 20 m", 60)

    def take_off_px4(self) -> None:
        """Armed in Hold (retried while refused: ~5 s after boot), NAV_TAKEOFF to ALT_M above
        home (param7 AMSL), then OFFBOARD: a hold setpoint streamed 1 s before the switch."""
        deadline = time.monotonic() + 60.0 / self.speedup + 30.0
        self.set_interval(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, STREAM_HZ)
        self.wait_for(lambda: self.have_pos and self.heartbeat is not None and self.home_amsl is not None,
                      "position", 30)
        while -self.pos[2] < 1.0:  # retried: an arming refused at boot, a take-off not taken
            if time.monotonic() > deadline:
                raise FlightError(f"PX4 did not take off (mode {self.heartbeat.custom_mode:#x})")
            if not self.heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED:
                self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            else:
                self.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, float("nan"), float("nan"), float("nan"),
                             self.home_amsl + ALT_M)
            self.wait_fw(self.t_ms / 1000.0 + 2.0)
        self.wait_for(lambda: -self.pos[2] > ALT_M - 0.5, "take-off to 20 m", 60)
        self.wait_fw(self.t_ms / 1000.0 + 3.0)  # PX4 switches to Hold at the end of its take-off
        self.send(MASK_POS, (self.pos[0], self.pos[1], -ALT_M))
        self.wait_fw(self.t_ms / 1000.0 + 1.0)
        while (self.heartbeat.custom_mode >> 16) & 0xFF != 6:
            if time.monotonic() > deadline:
                raise FlightError(f"PX4 did not take OFFBOARD (mode {self.heartbeat.custom_mode:#x})")
            self.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6, 0)
            self.wait_fw(self.t_ms / 1000.0 + 1.5)

    def in_offboard(self) -> bool:
        return self.heartbeat is not None and self.heartbeat.custom_mode & 0xFF0000 == PX4_OFFBOARD

    def settle(self, max_s: float = 40.0) -> None:
        """Hold the current position (position-only target) until the copter is still."""
        self.recording = None
        self.origin = (0.0, 0.0, 0.0)
        hold = (self.pos[0], self.pos[1], -ALT_M)
        t0 = self.t_ms / 1000.0
        still_since, resend = None, t0
        while self.t_ms / 1000.0 - t0 < max_s:
            if self.t_ms / 1000.0 >= resend:
                self.send(MASK_POS, hold)
                resend += 2.0
            self.pump(0.05)
            if math.hypot(*self.vel[:2]) < 0.1 and abs(self.vel[2]) < 0.1:
                still_since = still_since or self.t_ms
                if self.t_ms - still_since > 2000:
                    break
            else:
                still_since = None
        self.send(MASK_POS, (self.pos[0], self.pos[1], -ALT_M))
        self.wait_fw(self.t_ms / 1000.0 + 1.0)

    def start_case(self, name: str) -> Trace:
        self.settle()
        self.origin = (self.pos[0], self.pos[1], -ALT_M)
        self.recording = Trace(name)
        # 0.5 s of hover recorded before the case
        self.wait_fw(self.t_ms / 1000.0 + 0.5)
        return self.recording


# --------------------------------------------------------------------------- cases

def fly_step(f: SitlFlight, distance: float, heading_deg: float, duration: float) -> Trace:
    tr = f.start_case(f"step{distance:g}")
    h = math.radians(heading_deg)
    f.send(MASK_POS, (distance * math.cos(h), distance * math.sin(h), 0.0))
    t0 = f.t_ms / 1000.0
    f.wait_fw(t0 + duration)
    f.recording = None
    return tr


def fly_top(f: SitlFlight, speed: float, heading_deg: float, duration: float) -> Trace:
    """A velocity-only command far above what the airframe flies: its top speed at ANGLE_MAX."""
    tr = f.start_case("top")
    h = math.radians(heading_deg)
    v = (speed * math.cos(h), speed * math.sin(h), 0.0)
    t0 = f.t_ms / 1000.0
    k = 0
    while k * 0.5 <= duration:  # within GUID_TIMEOUT
        f.wait_fw(t0 + k * 0.5)
        f.send(MASK_VEL, (0.0, 0.0, 0.0), v)
        k += 1
    f.send(MASK_VEL, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    f.wait_fw(t0 + duration + 6.0)
    f.recording = None
    return tr


def top_speed(tr: Trace) -> float:
    """The top speed held: the median speed over the last 3 s of the command."""
    d = tr.as_dict(every=1)
    t, v = np.asarray(d["t"]), np.linalg.norm(np.asarray(d["vel"]), axis=1)
    # the last send of the fast command (on PX4 the stop after it is resent to the trace's end)
    t_stop = max(x[0] for x in d["sends"] if x[3] is not None and math.hypot(*x[3][:2]) > 1.0)
    return float(np.median(v[(t > t_stop - 3.0) & (t <= t_stop)]))


def fly_ramp(f: SitlFlight, speed: float, heading_deg: float, duration: float) -> Trace:
    tr = f.start_case(f"ramp{speed:.0f}")
    h = math.radians(heading_deg)
    v = (speed * math.cos(h), speed * math.sin(h), 0.0)
    t0 = f.t_ms / 1000.0
    k = 0
    while k * 0.1 <= duration:
        f.wait_fw(t0 + k * 0.1)
        dt = f.t_ms / 1000.0 - t0
        f.send(MASK_POSVEL, (v[0] * dt, v[1] * dt, 0.0), v)
        if k % 10 == 0:
            tr.plan.append((f.t_ms / 1000.0, v[0] * dt, v[1] * dt))
        k += 1
    f.wait_fw(t0 + duration + 3.0)
    f.recording = None
    return tr


def planner_route(speed: float, accel: float, heading_deg: float = 0.0,
                  turns=((6, 90), (5, -120), (4, 60), (6, -150), (4, 45), (5, 0))) -> tuple[np.ndarray, np.ndarray]:
    """A route a vehicle with these limits can fly, sampled every TICK_S: from hover, accelerate at
    half the acceleration limit to ``speed``, then legs (seconds straight) each followed by a turn
    (degrees, + = clockwise) at 0.6x the acceleration limit. Returns p (K, 2) and v (K, 2)."""
    dt = 0.01
    a_t, a_n = 0.5 * accel, 0.6 * accel
    psi = math.radians(heading_deg)
    p, s = np.zeros(2), 0.0
    plan = [(p.copy(), np.zeros(2))]
    events, t = [], 0.0
    for leg_s, turn_deg in turns:
        events.append(("straight", leg_s))
        if turn_deg:
            events.append(("turn", math.radians(turn_deg)))
    t_next = TICK_S
    queue = list(events)
    mode, left = "accel", None
    while True:
        if mode == "accel":
            s = min(speed, s + a_t * dt)
            if s >= speed:
                if not queue:
                    break
                mode, left = queue.pop(0)
        elif mode == "straight":
            left -= dt
            if left <= 0:
                if not queue:
                    break
                mode, left = queue.pop(0)
        else:
            rate = a_n / max(s, 1e-6)
            step = math.copysign(min(rate * dt, abs(left)), left)
            psi += step
            left -= step
            if abs(left) < 1e-9:
                if not queue:
                    break
                mode, left = queue.pop(0)
        p = p + s * dt * np.array([math.cos(psi), math.sin(psi)])
        t += dt
        if t >= t_next - 1e-9:
            plan.append((p.copy(), s * np.array([math.cos(psi), math.sin(psi)])))
            t_next += TICK_S
    P = np.array([x[0] for x in plan])
    V = np.array([x[1] for x in plan])
    return P, V


def route_setpoint(kind: str, P: np.ndarray, V: np.ndarray, k: int, latency: float = 0.0):
    """What to send at tick k (the plan's time k TICK_S) for the route: (mask, pos, vel, acc), NED."""
    nxt = min(k + 1, len(P) - 1)
    if kind == "pos":
        return MASK_POS, (*P[nxt], 0.0), None, None
    if kind == "posvel":  # the plan's position and velocity ``latency`` s after tick k
        p, v, _ = plan_setpoint(P[k], V[k], V[nxt], TICK_S, min(latency, TICK_S))
        return MASK_POSVEL, (*p, 0.0), (*v, 0.0), None
    if kind == "posvel_next":
        return MASK_POSVEL, (*P[nxt], 0.0), (*V[nxt], 0.0), None
    if kind == "ramp":
        v = (P[nxt] - P[k]) / TICK_S
        p = P[k] + v * latency
        return MASK_POSVEL, (*p, 0.0), (*v, 0.0), None
    if kind == "pva":  # the app's setpoint (onboard.core.setpoint); the last tick: no acceleration
        p, v, a = plan_setpoint(P[k], V[k], V[nxt], TICK_S, min(latency, TICK_S))
        return MASK_PVA, (*p, 0.0), (*v, 0.0), (*a, 0.0)
    raise ValueError(kind)


def fly_route(f: SitlFlight, kind: str, P: np.ndarray, V: np.ndarray, latency: float = 0.0,
              name: str | None = None) -> Trace:
    tr = f.start_case(name or f"route_{kind}")
    t0 = f.t_ms / 1000.0
    for k in range(len(P)):
        f.wait_fw(t0 + k * TICK_S + latency)
        tr.plan.append((t0 + k * TICK_S, *P[k]))
        late = f.t_ms / 1000.0 - (t0 + k * TICK_S)  # the plan's state when it is sent
        mask, p, v, a = route_setpoint(kind, P, V, k, late)
        f.send(mask, p, v, a)
        if f.px4:  # resent as the app does: the plan's state at each send (the point, for pos)
            f.resend = f.resending((lambda k: lambda t: route_setpoint(kind, P, V, k, t - (t0 + k * TICK_S)))(k))
    f.wait_fw(t0 + len(P) * TICK_S + 2.0)
    f.recording = None
    return tr


# --------------------------------------------------------------------------- figures

def distance_at_ticks(tr: Trace | dict) -> np.ndarray:
    """Horizontal distance from the vehicle to the plan's point at each planned time after the first
    (the time the next 1-s setpoint is due), the vehicle's position interpolated on the firmware clock."""
    d = tr if isinstance(tr, dict) else tr.as_dict(every=1)
    t = np.asarray(d["t"])
    pos = np.asarray(d["pos"])
    out = []
    for tp, x, y in d["plan"][1:]:
        if tp > t[-1]:
            break
        px, py = np.interp(tp, t, pos[:, 0]), np.interp(tp, t, pos[:, 1])
        out.append(math.hypot(px - x, py - y))
    return np.asarray(out)


def step_figures(tr: Trace, distance: float) -> dict:
    d = tr.as_dict(every=1)
    t, pos = np.asarray(d["t"]), np.asarray(d["pos"])
    # the step itself (on PX4 the hold before it is resent into the trace's first half second)
    first = next(x for x in d["sends"] if math.hypot(*x[2][:2]) > 0.5 * distance)
    t_send = first[0]
    goal = np.asarray(first[2][:2])
    err = np.linalg.norm(pos[:, :2] - goal, axis=1)
    inside = np.nonzero((err < 1.0) & (t >= t_send))[0]
    along = pos[:, :2] @ (goal / np.linalg.norm(goal))
    return {"t_within_1m_s": None if not len(inside) else round(float(t[inside[0]] - t_send), 2),
            "overshoot_m": round(float(max(0.0, along.max() - distance)), 2),
            "peak_speed_mps": round(float(np.max(np.linalg.norm(np.asarray(d["vel"])[:, :2], axis=1))), 2)}


def stats(x: np.ndarray) -> dict:
    return {"median_m": round(float(np.median(x)), 2), "p95_m": round(float(np.percentile(x, 95)), 2),
            "max_m": round(float(np.max(x)), 2), "n": int(len(x))}


# --------------------------------------------------------------------------- the model on the same setpoints

def guided_setpoint(mask: int, pos, vel, acc):
    """A recorded SET_POSITION_TARGET_LOCAL_NED as sim.guided reads it (the type_mask's fields)."""
    from sim.guided import GuidedSetpoint

    return GuidedSetpoint(pos=None if mask & 0b111 else tuple(pos),
                          vel=None if mask & 0b111000 or vel is None else tuple(vel),
                          acc=None if mask & 0b111000000 or acc is None else tuple(acc))


def replay(trace: dict, limits=None, rate_hz: float = 400.0) -> np.ndarray:
    """The model (sim.multicopter, sim.guided) given the trace's setpoints at their firmware times,
    from the trace's first sample (hovering at its start, GUIDED position-only): its horizontal
    positions at the trace's sample times, (N, 2)."""
    from sim.guided import fly_timeline
    from sim.multicopter import VehicleLimits, VehicleState

    limits = limits or VehicleLimits()
    t = np.asarray(trace["t"], float)
    p0, v0 = trace["pos"][0], trace["vel"][0]
    state = VehicleState(pos=(p0[0], p0[1], 0.0), vel=(v0[0], v0[1], 0.0))
    sends = [(s[0] - t[0], guided_setpoint(s[1], s[2], s[3], s[4])) for s in trace["sends"]]
    states = fly_timeline(state, sends, t - t[0], limits, rate_hz, submode="pos", hold=(0.0, 0.0, 0.0),
                          offboard=not limits.shaping)
    return np.array([s.pos[:2] for s in states])


def rms_error(trace: dict, limits=None, rate_hz: float = 400.0) -> float:
    """RMS horizontal distance (m) between the model's positions and the SITL's over the trace."""
    model = replay(trace, limits, rate_hz)
    return float(np.sqrt(np.mean(np.sum((model - np.asarray(trace["pos"])) ** 2, axis=1))))


IN_ENVELOPE = ("not the demo's route90: its plan asks more than the airframe's lean gives at 9 m/s; "
               "not PX4's top: 15 s at the tilt limit, which two SITL runs flew 11 m apart")


def in_envelope(label: str, name: str) -> bool:
    """The traces the model is fitted and held to (the rest: see IN_ENVELOPE)."""
    return not ((label == "demo" and name.startswith("route90")) or (label == "px4" and name == "top"))


def model_errors(data: dict, rate_hz: float = 400.0, **airframe) -> dict:
    """{(limits label, trace name): RMS error of the model, m} over a saved flight."""
    return {(lab, tr["name"]): rms_error(tr, limits_for(data[lab]["params"], **airframe), rate_hz)
            for lab in data for tr in data[lab]["traces"]}


def fit_airframe(data: dict, rate_hz: float = 400.0, evaluations: int = 60) -> dict:
    """The airframe terms minimising the RMS over the in-envelope traces of their RMS errors
    (Nelder-Mead from the model's current values): lean_tc and drag (quadratic) for ArduCopter's
    SITL, lean_tc and drag_lin (linear, as SIH's) for PX4's."""
    from scipy.optimize import minimize

    from sim.multicopter import is_px4

    px4 = any(is_px4(data[lab]["params"]) for lab in data)
    names = ("lean_tc", "drag_lin") if px4 else ("lean_tc", "drag")
    start = limits_for(next(iter(data.values()))["params"])

    def cost(x):
        if x[0] < 0.0 or x[1] <= 0.0:
            return 1e9
        e = model_errors(data, rate_hz, **dict(zip(names, x)))
        return float(np.sqrt(np.mean([v * v for k, v in e.items() if in_envelope(*k)])))

    r = minimize(cost, [getattr(start, n) for n in names], method="Nelder-Mead",
                 options=dict(maxfev=evaluations, xatol=1e-3, fatol=1e-4))
    return {names[0]: round(float(r.x[0]), 3), names[1]: round(float(r.x[1]), 4), "rms_m": round(r.fun, 3)}


def load(path: str) -> dict:
    with gzip.open(path, "rt") as fh:
        return json.load(fh)


def limits_for(params: dict, **airframe):
    """sim.multicopter's limits for the parameters a flight read back (and airframe terms, if given)."""
    from sim.multicopter import limits_from_params

    return replace(limits_from_params(params), **airframe)


# --------------------------------------------------------------------------- main

def _number(text: str) -> bool:
    try:
        return float(text) > 0
    except ValueError:
        return False


def fly_limits(label: str, binary: Path, speedup: float, cases: list[str], latency: float,
               route_speed: float | None = None, extra: dict | None = None,
               log=print, autopilot: str = "ardupilot") -> tuple[dict, dict, list[Trace]]:
    px4 = autopilot == "px4"
    params_in = {**LIMITS[label], **(extra or {})}
    # PX4's ULog of a full run is ~200 MB: its working directory goes with the bench
    workdir = tempfile.TemporaryDirectory(prefix="pmon-px4-bench-") if px4 else None
    sitl = px4_sitl.Px4Sitl(binary, HOME, speed=speedup, params=params_in, workdir=Path(workdir.name)) if px4 else \
        ArduPilotSitl(binary, HOME, speedup=speedup, params=params_in)
    sitl.start()
    try:
        f = SitlFlight(sitl.talk_url("api") if px4 else sitl.url(0), speedup, autopilot)
        try:
            f.take_off_px4() if px4 else f.take_off()
            params = f.read_params(PX4_READ_PARAMS if px4 else READ_PARAMS)
            log(f"[{label}] parameters read back: {params}")
            if px4:
                vmax, amax = params["MPC_XY_VEL_MAX"], params["MPC_ACC_HOR"]
            else:
                vmax, amax = params["WPNAV_SPEED"] / 100.0, params["WPNAV_ACCEL"] / 100.0
            figures, traces = {}, []
            top = None
            for case in cases:
                if case == "top":
                    tr = fly_top(f, 3.0 * vmax, 45.0, 15.0)
                    top = top_speed(tr)
                    figures[tr.name] = {"top_speed_mps": round(top, 2)}
                    traces.append(tr)
                elif case.startswith("step"):
                    dist = float(case[4:])
                    tr = fly_step(f, dist, 0.0 if dist < 50 else 180.0, 8.0 + dist / vmax * 1.3)
                    figures[tr.name] = step_figures(tr, dist)
                    traces.append(tr)
                elif case == "ramp":
                    tr = fly_ramp(f, 0.5 * min(vmax, top or vmax), 90.0, 20.0)
                    figures[tr.name] = stats(distance_at_ticks(tr))
                    traces.append(tr)
                elif case.startswith("route"):
                    share = float(case[5:] or 90) / 100.0
                    cruise = route_speed or share * min(vmax, top or vmax)
                    figures[f"{case}_speed_mps"] = round(cruise, 2)
                    P, V = planner_route(cruise, amax)
                    for kind in PX4_ROUTE_KINDS if px4 else ROUTE_KINDS:
                        tr = fly_route(f, kind, P, V, latency, name=f"{case}_{kind}")
                        figures[tr.name] = stats(distance_at_ticks(tr))
                        traces.append(tr)
                log(f"[{label}] {case}: " + json.dumps({k: v for k, v in figures.items()
                                                          if k.startswith(case)}))
                if px4 and not f.in_offboard():
                    raise FlightError(f"PX4 left OFFBOARD during {case} (mode {f.heartbeat.custom_mode:#x})")
        finally:
            f.conn.close()
    finally:
        sitl.stop()
        if workdir is not None:
            workdir.cleanup()
    return params, figures, traces


def offline(path: str, fit: bool) -> int:
    try:
        data = load(path)
    except (OSError, ValueError) as exc:
        print(f"python bench/sitl_response.py: {path}: {exc}", file=sys.stderr)
        return 2
    if fit:
        print(json.dumps(fit_airframe(data)))
        return 0
    out = {}
    for lab in data:
        limits = limits_for(data[lab]["params"])
        for tr in data[lab]["traces"]:
            model = replay(tr, limits)
            rms = float(np.sqrt(np.mean(np.sum((model - np.asarray(tr["pos"])) ** 2, axis=1))))
            fig = {"rms_m": round(rms, 2), "in_envelope": in_envelope(lab, tr["name"])}
            if tr["plan"]:
                fig["sitl"] = stats(distance_at_ticks(tr))
                fig["model"] = stats(distance_at_ticks({**tr, "pos": model.tolist()}))
            out[f"{lab}:{tr['name']}"] = fig
            line = f"{lab:6s} {tr['name']:20s} rms={fig['rms_m']:5.2f} m"
            if "sitl" in fig:
                line += (f"  next tick: SITL median {fig['sitl']['median_m']:5.2f} p95 {fig['sitl']['p95_m']:5.2f}"
                         f"  model median {fig['model']['median_m']:5.2f} p95 {fig['model']['p95_m']:5.2f}")
            print(line + ("" if fig["in_envelope"] else "  (beyond the airframe's envelope)"))
    print(json.dumps(out))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python bench/sitl_response.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("--autopilot", choices=("ardupilot", "px4"), default="ardupilot",
                    help="ArduCopter SITL (default) or PX4 SITL (SIH quad, OFFBOARD)")
    ap.add_argument("--limits", default=None, help="comma-separated: stock, demo (default stock,demo; PX4: stock)")
    ap.add_argument("--cases", default="top,step20,step100,ramp,route90,route70",
                    help="comma-separated cases (default top,step20,step100,ramp,route90,route70)")
    ap.add_argument("--route-speed", type=float, default=None,
                    help="the routes' cruise speed, m/s (default: routeNN flies at NN %% of the lower of "
                    "WPNAV_SPEED and the top speed measured by the case 'top')")
    ap.add_argument("--speedup", type=float, default=4.0, help="SITL speedup (default 4)")
    ap.add_argument("--latency-s", type=float, default=0.0,
                    help="route setpoints sent this long after their tick (default 0)")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", type=param_item,
                    help="a parameter over each set of limits at boot; repeatable (e.g. WPNAV_SPEED=400)")
    ap.add_argument("--save", help="write the traces here (gzipped JSON)")
    ap.add_argument("--replay", metavar="FILE", help="fly nothing: the model's RMS error (m) on each "
                    "trace of a saved flight, and its distance at the next tick beside the SITL's")
    ap.add_argument("--fit", metavar="FILE", help="fly nothing: fit sim.multicopter's lean_tc and drag to "
                    "a saved flight's in-envelope traces (a few minutes)")
    args = ap.parse_args(argv)
    if args.replay or args.fit:
        return offline(args.replay or args.fit, fit=bool(args.fit))
    px4 = args.autopilot == "px4"
    labels = [x.strip() for x in (args.limits or ("stock" if px4 else "stock,demo")).split(",") if x.strip()]
    for lab in labels:
        if lab not in LIMITS:
            ap.error(f"--limits: unknown set {lab!r} (stock, demo)")
    cases = [x.strip() for x in args.cases.split(",") if x.strip()]
    extra = dict(args.param)
    for case in cases:
        if not (case in ("top", "ramp") or (case.startswith("step") and _number(case[4:]))
                or (case.startswith("route") and (case == "route" or _number(case[5:])))):
            ap.error(f"--cases: unknown case {case!r} (top, stepD, ramp, routeNN)")
    binary = px4_sitl.find_sitl() if px4 else find_binary()
    why = px4_sitl.skip_reason() if px4 else skip_reason()
    if why is not None:
        print(f"python bench/sitl_response.py: {why}", file=sys.stderr)
        return 2
    out, saved = {}, {}
    for lab in labels:
        try:
            params, figures, traces = fly_limits(lab, binary, args.speedup, cases, args.latency_s,
                                                 args.route_speed, extra, autopilot=args.autopilot)
        except (SitlError, px4_sitl.SitlError, FlightError) as exc:
            print(f"python bench/sitl_response.py: {lab}: {exc}", file=sys.stderr)
            return 1
        key = "px4" if px4 else lab  # PX4's stock parameters: their own label
        out[key] = {"params": params, "cases": figures}
        saved[key] = {"params": params, "traces": [t.as_dict() for t in traces]}
        for name, fig in figures.items():
            if isinstance(fig, dict):
                print(f"{key:6s} {name:18s} " + "  ".join(f"{k}={v}" for k, v in fig.items()))
    if args.save:
        with gzip.GzipFile(args.save, "wb", mtime=0) as fh:  # mtime 0: the same flight, the same bytes
            fh.write(json.dumps(saved, separators=(",", ":")).encode())
        print(f"traces saved to {args.save} ({Path(args.save).stat().st_size // 1024} kB)")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
