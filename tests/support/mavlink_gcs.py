"""A raw pymavlink ground station for the SITL tests, and the quick boot they use."""
from __future__ import annotations

import threading
import time

from onboard.app.mavlink2 import mavlink, mavutil

# autopilot s until a mock SITL stack can arm, in tests not about the boot (ArduCopter's ~43 s
# is flown in tests/sim/test_autopilot.py, test_conformance.py and against the firmware itself)
QUICK_BOOT_S = 4.0


class Gcs:
    """A raw pymavlink ground station (sysid 255 by default, component 190) on its own TCP link
    to the mock autopilot (127.0.0.1:port); the onboard app is reached by the autopilot's
    routing. A thread keeps every message received (``msgs``) and sends a GCS heartbeat every
    0.5 s. Used by tests/app/test_app_sitl.py, tests/app/test_failsafes.py and tests/gcs/test_gcs_terminal.py
    (``from tests.support.mavlink_gcs import Gcs``); ``close()`` joins the thread and frees the port."""

    def __init__(self, port: int, sysid: int = 255):
        self.conn = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=sysid,
                                               source_component=190, dialect="ardupilotmega")
        self.msgs: list = []
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self):
        last_hb = 0.0
        while not self._stop.is_set():
            m = self.conn.recv_match(blocking=True, timeout=0.05)
            if m is not None and m.get_type() != "BAD_DATA":
                self.msgs.append(m)
            if time.monotonic() - last_hb > 0.5:
                last_hb = time.monotonic()
                self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def wait(self, pred, timeout: float, since: int = 0):
        """The first message from index ``since`` on that satisfies ``pred`` (None after timeout)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for m in self.msgs[since:]:
                if pred(m):
                    return m
            time.sleep(0.01)
        return None

    def command(self, comp: int, cmd: int, *params, timeout: float = 5.0):
        """COMMAND_LONG to (1, comp); its COMMAND_ACK or None."""
        since = len(self.msgs)
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(1, comp, cmd, 0, *p)
        return self.wait(lambda m: m.get_type() == "COMMAND_ACK" and m.command == cmd
                         and m.get_srcComponent() == comp, timeout, since)

    def param_set(self, name: str, value: float, timeout: float = 5.0, comp: int = 191,
                  ptype: int = mavlink.MAV_PARAM_TYPE_REAL32):
        """PARAM_SET of a parameter of (1, comp), by default the app's; its PARAM_VALUE or None."""
        since = len(self.msgs)
        self.conn.mav.param_set_send(1, comp, name.encode(), value, ptype)
        return self.wait(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == name
                         and m.get_srcComponent() == comp, timeout, since)

    def texts(self) -> list[str]:
        return [m.text for m in self.msgs if m.get_type() == "STATUSTEXT"]

    def close(self):
        self._stop.set()
        self._t.join(timeout=2)
        self.conn.close()
