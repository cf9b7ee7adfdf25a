"""A vehicle on loopback for the hub's tests and benches: an autopilot heartbeat and position, and the
onboard app's PMON_TGT / PMON_STAT, sent with pymavlink as the real ones send them (system 1;
autopilot component 1, app component 191), plus a hostile peer's variants. Every packet the
hub writes towards the vehicle is kept (``received``)."""
from __future__ import annotations

import math
import socket
import threading
import time

from onboard.app.mavlink2 import mavutil
from onboard.app.mavlink_connection import mavlink


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def target_values(x, y, vx=3.0, vy=-4.0, sx=40.0, sy=25.0, cxy=300.0, since=0.4, t=10.0, degenerate=0.0):
    """PMON_TGT's 14 fields (docs/MAVLINK.md)."""
    return [x, y, 0.0, vx, vy, 0.0, sx, sy, since, cxy, 1.0, 1.0, degenerate, t]


class FakeVehicle:
    def __init__(self, hub_port: int, sysid: int = 1):
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{hub_port}", source_system=sysid,
                                               source_component=1, dialect="ardupilotmega")
        self.sysid = sysid
        self.received: list = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._rx, daemon=True)
        self._t.start()
        self.boot = time.monotonic()

    def _rx(self):
        while not self._stop.is_set():
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.1)
            except OSError:
                continue
            if m is not None and m.get_type() != "BAD_DATA":
                with self._lock:
                    self.received.append(m)

    def as_(self, comp: int, sysid: int | None = None):
        self.conn.mav.srcComponent = comp
        self.conn.mav.srcSystem = self.sysid if sysid is None else sysid
        return self.conn.mav

    def heartbeat(self):
        self.as_(1).heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                   mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, mavlink.MAV_STATE_ACTIVE)
        self.as_(191).heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                     mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 1, mavlink.MAV_STATE_ACTIVE)

    def position(self, lat, lon, alt_m):
        ms = int((time.monotonic() - self.boot) * 1000)
        self.as_(1).global_position_int_send(ms, int(lat * 1e7), int(lon * 1e7), int(alt_m * 1000), 40000,
                                             500, -300, 0, 9000)

    def target(self, index: int, values, comp: int = 191, sysid: int | None = None, t_usec: int = 0):
        data = [float(v) for v in values][:58]
        data += [0.0] * (58 - len(data))
        self.as_(comp, sysid).debug_float_array_send(t_usec, b"PMON_TGT", index, data)

    def stat(self, t: float):
        data = [1.0, 1.0, t] + [math.nan] * 3 + [0.0] * 52
        self.as_(191).debug_float_array_send(int(t * 1e6), b"PMON_STAT", 0, data)

    def raw(self, buf: bytes):
        self.conn.write(buf)

    def got(self, mtype: str) -> list:
        with self._lock:
            return [m for m in self.received if m.get_type() == mtype]

    def close(self):
        self._stop.set()
        self._t.join(timeout=2)
        self.conn.close()


class Client:
    """A MAVLink ground station on the hub's port (pymavlink, as MAVProxy and QGC parse)."""

    def __init__(self, hub_serve_port: int, sysid: int = 254, comp: int = 190):
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{hub_serve_port}", source_system=sysid,
                                               source_component=comp, dialect="ardupilotmega")
        self.msgs: list = []
        self.stamps: list = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._rx, daemon=True)
        self._t.start()
        self.hello()

    def hello(self):
        self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def _rx(self):
        while not self._stop.is_set():
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.1)
            except OSError:
                continue
            if m is not None and m.get_type() != "BAD_DATA":
                with self._lock:
                    self.msgs.append(m)
                    self.stamps.append(time.monotonic())

    def got(self, mtype: str) -> list:
        with self._lock:
            return [m for m in self.msgs if m.get_type() == mtype]

    def wait(self, pred, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pred():
                return True
            time.sleep(0.02)
        return pred()

    def close(self):
        self._stop.set()
        self._t.join(timeout=2)
        self.conn.close()
