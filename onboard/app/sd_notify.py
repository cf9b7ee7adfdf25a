"""systemd's notify protocol, without a dependency: one AF_UNIX datagram per message to
``$NOTIFY_SOCKET`` (a path, or ``@name`` for the abstract namespace), as sd_notify(3) sends it.

Under a unit with ``Type=notify`` and ``WatchdogSec=`` (config/systemd/pmon.service) the app
sends ``READY=1`` once its loop runs, ``WATCHDOG=1`` every half ``$WATCHDOG_USEC`` while its tick
worker and io loop are alive (onboard/app/app.py), and ``STOPPING=1`` on stop; systemd restarts
a process whose pings stop. Outside systemd (no ``$NOTIFY_SOCKET``) nothing is sent. A send
that fails is dropped: the service manager's absence must never stop the app.
"""
from __future__ import annotations

import os
import socket


class Notifier:
    """``address``: the socket's path ('\\0name' for an abstract one); ``watchdog_s``: the
    service's watchdog period (None: no watchdog)."""

    def __init__(self, address: str, watchdog_s: float | None):
        self.address = address
        self.watchdog_s = watchdog_s
        self.sent = 0
        self.failed = 0
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._sock.set_inheritable(False)

    @classmethod
    def from_env(cls, env=os.environ) -> "Notifier | None":
        """From systemd's variables; None outside a notify service. ``$WATCHDOG_PID``, when set,
        names the process the watchdog is for (not this one: no pings)."""
        address = env.get("NOTIFY_SOCKET")
        if not address or address[0] not in "/@":
            return None
        if address[0] == "@":
            address = "\0" + address[1:]
        watchdog_s = None
        usec, pid = env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            watchdog_s = int(usec) / 1e6
        return cls(address, watchdog_s)

    @property
    def ping_every_s(self) -> float | None:
        """Local s between WATCHDOG=1 pings: half the period, as sd_watchdog_enabled(3) advises."""
        return None if self.watchdog_s is None else self.watchdog_s / 2

    def send(self, text: str) -> bool:
        try:
            self._sock.sendto(text.encode(), self.address)
        except OSError:
            self.failed += 1
            return False
        self.sent += 1
        return True

    def close(self) -> None:
        self._sock.close()
