"""The MAVLink client of bench/sitl_response.py: a pymavlink connection flying ArduCopter's SITL in
GUIDED (PX4's in OFFBOARD), every message timed on the firmware clock, and the trace of a case as
flown. The cases and their figures are in sim/firmware/response_cases.py.
"""
from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass, field

from onboard.app.mavlink2 import mavlink, mavutil

HOME = (35.145, 33.411, 160.0)
ALT_M = 20.0
STREAM_HZ = 50.0
# type_mask (POSITION_TARGET_TYPEMASK): what is ignored; yaw and yaw rate always ignored
MASK_POS = 0b110111111000
MASK_POSVEL = 0b110111000000
MASK_PVA = 0b110000000000
MASK_VEL = 0b110111000111
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

