"""A UDP relay standing in for a telemetry link between the companion and the autopilot on a UDP
link (PX4's offboard link), that a test can cut: sim/stack/rig.py puts it on the app's link when
asked (``RigConfig.link_proxy``), as sim/stack/tcp_proxy.py does on ArduPilot's TCP ports.

The autopilot's side pushes its datagrams to ``listen_port`` (where the companion would listen:
a ``udpin`` port); the relay sends them on to the companion's ``udpin`` port ``app_port`` and
the companion's answers back to whoever pushed last. ``cut(s)`` drops every datagram both ways
for s wall seconds (a radio outage); nothing queues meanwhile.
"""
from __future__ import annotations

import contextlib
import select
import socket
import threading
import time


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 free now (for a program that binds it soon after)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class UdpProxy:
    def __init__(self, listen_port: int):
        self._outer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the autopilot's side
        self._outer.bind(("127.0.0.1", listen_port))
        self._inner = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the companion's side
        self._inner.bind(("127.0.0.1", 0))
        self.app_port = free_udp_port()
        self._autopilot: tuple[str, int] | None = None
        self._down_until = 0.0
        self.dropped = 0
        self.relayed = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="udp-proxy", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        """The companion's MAVLink URL."""
        return f"udpin:127.0.0.1:{self.app_port}"

    def cut(self, seconds: float) -> None:
        self._down_until = time.monotonic() + seconds

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._outer.close()
        self._inner.close()

    def _run(self) -> None:
        socks = [self._outer, self._inner]
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select(socks, [], [], 0.05)
            except (OSError, ValueError):
                return
            for s in ready:
                with contextlib.suppress(OSError):
                    data, addr = s.recvfrom(65535)
                    if time.monotonic() < self._down_until:
                        self.dropped += 1
                        continue
                    if s is self._outer:
                        self._autopilot = addr
                        self._inner.sendto(data, ("127.0.0.1", self.app_port))
                    elif self._autopilot is not None:
                        self._outer.sendto(data, self._autopilot)
                    self.relayed += 1
