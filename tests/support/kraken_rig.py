"""The KrakenSDR input's tests share: an app reading a URL (no autopilot: the test gives it the
autopilot's UTC and poses), frames as the simulated KrakenSDR writes them, and a hostile HTTP
server on 127.0.0.1 that answers each request with whatever bytes its script says."""
from __future__ import annotations

import math
import socket
import threading
import time
from typing import Callable

import numpy as np

from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.autopilot.clock import ManualClock
from onboard.app.autopilot.pose import PoseSample
from onboard.config import load_scenario, override
from onboard.policy import with_policy
from sim.stack.kraken import KrakenModel, frame_lines

UNIX0 = 1_700_000_000.0
M = 4
SC = with_policy(load_scenario("paper", {"kraken.poll_s": 0.005}), "paper")  # the app on the paper's method
FREQS = {j: v.freq_hz for j, v in enumerate(SC.kraken.vfos)}
MODEL = KrakenModel(multipath=False)
UAV = np.array([150.0, 200.0, 40.0])
YAW = math.radians(30.0)


def epoch(t: float, latency_ms: int = MODEL.latency_ms) -> int:
    """The stamp KrakenSDR writes for a frame measured at autopilot ``t`` (UNIX0 = autopilot 0)."""
    return int(round((UNIX0 + t) * 1000 + latency_ms / 2))


def frame(t: float, bearings, seed: int) -> str:
    """The lines of one frame measured at ``t``: target j's bearings ``bearings[j]`` (rad)."""
    scans = [(np.asarray(b, float), np.arange(len(b)) == 0) for b in bearings]
    return frame_lines(epoch(t), scans, FREQS, YAW, MODEL, np.random.default_rng(seed))


def kraken_app(url: str, clock: ManualClock, sc=SC) -> OnboardApp:
    """An app reading ``url``, started, hovering at ``UAV`` heading ``YAW`` for 600 s."""
    app = OnboardApp(AppConfig("udpin:127.0.0.1:0", sensor_port=0, kraken=True),
                     override(sc, {"kraken.url": url}), clock=clock)
    for k in range(9):
        app.autopilot.utc.observe(int((UNIX0 + 1.0 + k) * 1e6), int((1.0 + k) * 1e3))
    app.poses.keep_s = 1e6
    for k in range(0, 6000):  # 10 Hz for 600 s
        app.poses.add(PoseSample(k / 10.0, UAV.copy(), np.zeros(3), YAW))
    return app.start()


def http_answer(body: bytes, *, length: bytes | None = None, keep_alive: bool = True) -> bytes:
    """A 200 answer to a GET: its Content-Length ``length`` (default: the body's)."""
    head = [b"HTTP/1.1 200 OK", b"Content-Type: text/html",
            b"Content-Length: " + (str(len(body)).encode() if length is None else length)]
    if not keep_alive:
        head.append(b"Connection: close")
    return b"\r\n".join(head) + b"\r\n\r\n" + body


class HostileServer:
    """A TCP server on 127.0.0.1 speaking just enough HTTP to be read: for the n-th request
    (0-based, over all connections) it calls ``script(n, conn)``, which writes what it likes to
    ``conn`` and returns True to keep the connection for the next request. Counts ``requests``
    and ``connections``; stops by itself after ``life_s`` (every socket closed); a context manager."""

    def __init__(self, script: Callable[[int, socket.socket], bool], life_s: float = 30.0):
        self.script = script
        self.requests = self.connections = 0
        self.paths: list[str] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._conns: list[socket.socket] = []
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}/DOA_value.html"
        self._end = time.monotonic() + life_s
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def __enter__(self) -> "HostileServer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)

    def stopping(self) -> bool:
        return self._stop.is_set() or time.monotonic() > self._end

    def _serve(self) -> None:
        try:
            while not self.stopping():
                try:
                    conn, _ = self.sock.accept()
                except TimeoutError:
                    continue
                with self._lock:
                    self.connections += 1
                    self._conns.append(conn)
                threading.Thread(target=self._handle, args=(conn,), daemon=True).start()
        finally:
            self.sock.close()
            with self._lock:
                for c in self._conns:
                    c.close()

    def _handle(self, conn: socket.socket) -> None:
        conn.settimeout(0.2)
        buf = b""
        try:
            while not self.stopping():
                try:
                    got = conn.recv(4096)
                except TimeoutError:
                    continue
                if not got:
                    return
                buf += got
                while b"\r\n\r\n" in buf:
                    head, buf = buf.split(b"\r\n\r\n", 1)
                    with self._lock:
                        n = self.requests
                        self.requests += 1
                        self.paths.append(head.split(b" ", 2)[1].decode("latin-1"))
                    if not self.script(n, conn):
                        return
        except OSError:  # the client went away
            pass
        finally:
            conn.close()
