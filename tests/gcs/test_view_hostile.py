"""Hostile clients of the live view's HTTP server (issue 45, item 5), on loopback, no vehicle:
clients that hang up mid-answer, hold connections open without a request, trickle half a
request or open the event stream and never read. The server stays quiet (hang-ups counted, no
traceback), holds a bounded number of connections and threads, drops idle ones, and answers a
genuine GET promptly all the while."""
from __future__ import annotations

import http.client
import socket
import struct
import threading
import time

import pytest

from groundstation import view
from onboard.config import load_scenario

pytestmark = pytest.mark.timeout(60)
HOSTILE = 300  # connections held at once
BOUND = 64  # threads the server may spend on them, at most


def rst_close(s: socket.socket) -> None:
    """Close with a reset, as a client killed mid-answer does."""
    s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    s.close()


def genuine_get(port: int, path: str = "/state.json") -> tuple[int, float]:
    t0 = time.monotonic()
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    try:
        c.request("GET", path, headers={"Host": f"127.0.0.1:{port}"})
        r = c.getresponse()
        r.read()
        return r.status, time.monotonic() - t0
    finally:
        c.close()


@pytest.fixture
def server(monkeypatch):
    monkeypatch.setattr(view, "IDLE_S", 1.0, raising=False)  # an idle connection is closed after this
    srv = view.ViewServer(load_scenario("paper"), 0).start()
    yield srv
    srv.close()


def test_hangups_are_quiet_and_counted_and_held_connections_cost_bounded_threads(server, capfd):
    port = server.port
    threads0 = threading.active_count()
    held: list[socket.socket] = []
    try:
        for i in range(HOSTILE):
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
            if i % 3 == 1:
                s.sendall(b"GET /view.js HT")  # half a request line, never finished
            elif i % 3 == 2:
                s.sendall(f"GET /events HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())  # never read
            held.append(s)
        for _ in range(50):  # a request, then a reset before the answer is read
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
            s.sendall(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
            rst_close(s)
        time.sleep(0.3)
        server.bus.publish({"seq": 1})  # the streams get an event to write
        times = [genuine_get(port)[1] for _ in range(5)]
        assert all(t < 1.0 for t in times), times
        status, _ = genuine_get(port, "/")
        assert status == 200
        extra = threading.active_count() - threads0
        assert extra <= BOUND, f"{extra} threads for {HOSTILE} held connections"
    finally:
        for s in held:
            rst_close(s)
    deadline = time.monotonic() + 5
    while server.hangups < 50 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Exception occurred" not in err, err[-2000:]
    assert server.hangups >= 50, (server.hangups, server.evicted)
    assert view.MAX_CLIENTS <= BOUND and server.evicted >= HOSTILE - view.MAX_CLIENTS


def test_an_idle_connection_is_closed_after_the_idle_timeout(server):
    port = server.port
    s = socket.create_connection(("127.0.0.1", port), timeout=5)
    t = socket.create_connection(("127.0.0.1", port), timeout=5)
    try:
        t.sendall(b"GET / HTTP/1.1\r\nHo")  # a request trickled, then nothing
        t0 = time.monotonic()
        assert s.recv(1) == b"" and t.recv(1) == b""  # the server closed them (else: socket timeout, 5 s)
        assert time.monotonic() - t0 < 3 * view.IDLE_S
        assert genuine_get(port)[0] == 200
    finally:
        s.close()
        t.close()
