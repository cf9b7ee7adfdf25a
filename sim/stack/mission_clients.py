"""The mission's own MAVLink clients of the autopilot (sim.stack.procedure.Mission), each on a port of
its own beside the operator's: the ``Observer``, which records what the autopilot and the app say,
and a pilot's ``Sticks``."""
from __future__ import annotations

import contextlib
import math
import select
import threading
import time
from collections import deque

import numpy as np

from onboard.app.mavlink_connection import Link, mavlink
from onboard.app.gcs.statustext import Reassembler

OBSERVER_SYSID = 250  # neither the operator's GCS (255) nor the feed (245)
PILOT_SYSID = 252  # a pilot's ground station with sticks (Mission.take_sticks)
JOYSTICK_HZ = 20.0  # wall Hz of its MANUAL_CONTROL


class Observer:
    """A MAVLink client of the autopilot on its own port, recording (autopilot s since boot,
    or the last one heard for messages without a time) what the autopilot and the app say."""

    def __init__(self, url: str):
        self.link = Link(url, source_system=OBSERVER_SYSID, source_component=mavlink.MAV_COMP_ID_MISSIONPLANNER,
                         wait_for_peer=True)
        self.lock = threading.Lock()
        self.t: float | None = None  # the autopilot's clock, s
        self.boots = 0  # autopilot (re)boots seen: its clock went back
        self.origin: tuple[float, float, float] | None = None  # EKF origin (deg, deg, m)
        self.positions: list[tuple] = []  # (t, lat, lon, alt_amsl, rel_alt) deg, m
        self.targets: list[tuple] = []  # (t, x, y, z) POSITION_TARGET_LOCAL_NED, m (EKF origin)
        self.modes: list[tuple] = []  # (t, custom_mode, armed) on every change
        self.beats: deque[float] = deque(maxlen=50)  # t of its latest heartbeats
        self.texts: list[tuple] = []  # (t, compid, text)
        self.estimates: list[tuple] = []  # (t, index, x, y, sigma_x, sigma_y) PMON_TGT
        self.app_state: str | None = None
        self._stop = threading.Event()
        self._chunks = Reassembler()
        self._asked = -math.inf
        self._last_pos_local = -math.inf
        self._thread = threading.Thread(target=self._run, name="observer", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.link.close()

    def _ask(self) -> None:
        self._asked = time.monotonic()
        send = self.link.send
        for mid, hz in ((mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 10.0),
                        (mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED, 10.0),
                        (mavlink.MAVLINK_MSG_ID_SYSTEM_TIME, 2.0),
                        (mavlink.MAVLINK_MSG_ID_HEARTBEAT, 4.0)):
            send(self.link.mav.command_long_encode(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                   mid, 1e6 / hz, 0, 0, 0, 0, 0))
        if self.origin is None:
            send(self.link.mav.command_long_encode(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                                   mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 0, 0, 0, 0, 0, 0))

    def _run(self) -> None:
        hb = -math.inf
        while not self._stop.is_set():
            fd = self.link.fileno()
            if fd is not None:
                with contextlib.suppress(OSError, ValueError):
                    select.select([fd], [], [], 0.01)
            else:
                time.sleep(0.01)
            for _ in range(500):
                msg = self.link.recv()
                if msg is None:
                    break
                self._on(msg)
            now = time.monotonic()
            if now - hb > 1.0:
                hb = now
                self.link.send(self.link.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                              0, 0, mavlink.MAV_STATE_ACTIVE))
            if now - self._last_pos_local > 2.0 and now - self._asked > 2.0:
                self._ask()

    def _on(self, msg) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA" or msg.get_srcSystem() != 1:
            return
        comp = msg.get_srcComponent()
        with self.lock:
            tb = getattr(msg, "time_boot_ms", None)
            if comp == 1 and tb is not None:
                t = tb / 1000.0
                if self.t is not None and t < self.t - 5.0:
                    self.boots += 1
                self.t = t
            t = self.t
            if comp == 1:
                if mtype == "GLOBAL_POSITION_INT" and not (msg.lat == 0 and msg.lon == 0):
                    self._last_pos_local = time.monotonic()
                    self.positions.append((t, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3,
                                           msg.relative_alt * 1e-3))
                elif mtype == "POSITION_TARGET_LOCAL_NED":
                    self.targets.append((t, msg.x, msg.y, msg.z))
                elif mtype == "HEARTBEAT":
                    if t is not None:
                        self.beats.append(t)
                    armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                    if not self.modes or self.modes[-1][1:] != (msg.custom_mode, armed):
                        self.modes.append((t, msg.custom_mode, armed))
                elif mtype == "GPS_GLOBAL_ORIGIN":
                    self.origin = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            if mtype == "STATUSTEXT":  # whole, as a ground station shows it (chunks joined)
                self.texts.extend((t, comp, text) for text in self._chunks.feed(msg))
            elif comp == mavlink.MAV_COMP_ID_ONBOARD_COMPUTER:
                if mtype == "DEBUG_FLOAT_ARRAY" and msg.name == "PMON_TGT":
                    d = msg.data
                    self.estimates.append((d[13], msg.array_id, d[0], d[1], d[6], d[7]))
                elif mtype == "HEARTBEAT":
                    from groundstation.protocol import app_state_name
                    self.app_state = app_state_name(msg.custom_mode)

    def heartbeat_period_s(self) -> float:
        """The autopilot's HEARTBEAT period as heard, autopilot s (median; 1 s until known)."""
        with self.lock:
            beats = list(self.beats)
        gaps = [b - a for a, b in zip(beats, beats[1:]) if 0 < b - a < 5.0]
        return float(np.median(gaps)) if gaps else 1.0

    def app_texts(self, since_t: float = -math.inf) -> list[str]:
        with self.lock:
            return [x for (t, c, x) in self.texts if c == mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
                    and (t is None or t >= since_t)]


class Sticks:
    """A pilot's sticks, centred, on a ground station of their own (sysid PILOT_SYSID):
    MANUAL_CONTROL at JOYSTICK_HZ from a thread that does nothing else (PX4 takes POSCTL only
    with manual control, and fails safe when it stops for COM_RC_LOSS_T)."""

    def __init__(self, url: str):
        self.link = Link(url, source_system=PILOT_SYSID, source_component=mavlink.MAV_COMP_ID_MISSIONPLANNER,
                         wait_for_peer=True)
        self.gap_s = 0.0  # the longest wall s between two
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sticks", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        last = hb = None
        while not self._stop.wait(1.0 / JOYSTICK_HZ):
            now = time.monotonic()
            if hb is None or now - hb >= 1.0:
                hb = now
                self.link.send(self.link.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                              0, 0, mavlink.MAV_STATE_ACTIVE))
            self.link.send(self.link.mav.manual_control_encode(1, 0, 0, 500, 0, 0))
            self.gap_s = max(self.gap_s, now - last) if last is not None else 0.0
            last = now
            # what the autopilot sends back is not read, only drained, for half a period at most:
            # while another thread of this process computes, each recv waits for the GIL, and an
            # unbounded drain of PX4's 50 Hz streams can hold the next MANUAL_CONTROL past
            # COM_RC_LOSS_T (PX4's manual control loss failsafe: Hold, then RTL). What is left
            # stays in the UDP socket's buffer, which drops the rest when full.
            end = now + 0.5 / JOYSTICK_HZ
            while time.monotonic() < end and self.link.recv() is not None:
                pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.link.close()
