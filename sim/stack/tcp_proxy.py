"""A TCP relay standing in for a telemetry link between the companion and the autopilot, that a
test can cut (sim/stack/rig.py puts it on the app's link when asked: ``RigConfig.link_proxy``)."""
from __future__ import annotations

import contextlib
import select
import socket
import threading
import time
from typing import Callable


class TcpProxy:
    """A TCP relay standing in for a telemetry link between the companion and the autopilot:
    ``cut(s)`` drops the connection and refuses new ones for s wall seconds (a radio or cable
    outage), then relays again with a new upstream connection."""

    def __init__(self, upstream: tuple[str, int], tap: Callable[[bytes], None] | None = None):
        self.upstream = upstream
        self.tap = tap  # called with every chunk relayed towards the upstream (sim/stack/link_count.py)
        self._lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._lsock.bind(("127.0.0.1", 0))
        self._lsock.listen(1)
        self.port = self._lsock.getsockname()[1]
        self._down_until = 0.0
        self._stop = threading.Event()
        self._pair: list[socket.socket] = []
        self._lock = threading.Lock()
        self.connections = 0
        self._thread = threading.Thread(target=self._run, name="tcp-proxy", daemon=True)
        self._thread.start()

    def cut(self, seconds: float) -> None:
        with self._lock:
            self._down_until = time.monotonic() + seconds
            self._drop()

    def _drop(self) -> None:
        for s in self._pair:
            with contextlib.suppress(OSError):
                s.close()
        self._pair = []

    def close(self) -> None:
        self._stop.set()
        self.cut(0)
        self._thread.join(timeout=5)
        self._lsock.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                pair = list(self._pair)
            if not pair:
                r, _, _ = select.select([self._lsock], [], [], 0.05)
                if not r:
                    continue
                client, _ = self._lsock.accept()
                if time.monotonic() < self._down_until:
                    client.close()  # the link is down: the companion's reconnect fails
                    continue
                try:
                    up = socket.create_connection(self.upstream, timeout=2)
                except OSError:
                    client.close()
                    continue
                with self._lock:
                    self._pair = [client, up]
                    self.connections += 1
                continue
            try:
                r, _, _ = select.select(pair, [], [], 0.05)
                for s in r:
                    data = s.recv(65536)
                    if not data:
                        raise OSError("closed")
                    if s is pair[0] and self.tap is not None:
                        self.tap(data)
                    (pair[1] if s is pair[0] else pair[0]).sendall(data)
            except (OSError, ValueError):  # either side closed (or cut() closed both)
                with self._lock:
                    if self._pair == pair:
                        self._drop()
