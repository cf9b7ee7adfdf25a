"""When the ground station cannot have its link, the error names what holds it: another local
process connected to a one-client TCP port (ArduPilot's serial-over-TCP ports, SITL's SERIAL2), or
bound to the UDP port it wants. Before, both said "no vehicle heard ... (no MAVLink at all)"."""
from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time

import pytest

from sim.stack.gcs_fake_vehicle import free_udp_port
from groundstation.errors import GcsError
from groundstation.gcs_link import GcsLink
from onboard.app.mavlink_connection import mavlink

HOLDER = """import socket, sys, time
s = socket.socket(socket.AF_INET, socket.SOCK_{kind})
{how}
print("holding", flush=True)
time.sleep(30)
"""


def holder(kind: str, how: str) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", HOLDER.format(kind=kind, how=how)], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline().strip() == "holding"
    return p


class OneClientServer:
    """A TCP MAVLink port as ArduPilot serves one: the first client gets heartbeats, later
    connections wait in the listen backlog and get nothing."""

    def __init__(self):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(4)
        self.port = self.sock.getsockname()[1]
        self.stop = threading.Event()
        self.t = threading.Thread(target=self._run, daemon=True)
        self.t.start()

    def _run(self):
        conn, _ = self.sock.accept()
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        while not self.stop.is_set():
            try:
                conn.sendall(mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav))
            except OSError:
                break
            time.sleep(0.2)
        conn.close()

    def close(self):
        self.stop.set()
        self.t.join(timeout=2)
        self.sock.close()


@pytest.mark.timeout(30)
def test_a_one_client_tcp_port_held_by_another_process_is_named():
    srv = OneClientServer()
    other = holder("STREAM", f"s.connect(('127.0.0.1', {srv.port}))")
    try:
        with pytest.raises(GcsError) as err:
            with GcsLink(f"tcp:127.0.0.1:{srv.port}", timeout=1.5) as gl:
                gl.connect()
        msg = str(err.value)
        assert "no MAVLink at all" in msg and f"pid {other.pid} (" in msg and f"connected to port {srv.port}" in msg
        assert "pmon gcs hub" in msg
    finally:
        other.kill()
        srv.close()


@pytest.mark.timeout(30)
def test_a_udp_port_bound_by_another_process_is_named():
    port = free_udp_port()
    other = holder("DGRAM", f"s.bind(('127.0.0.1', {port}))")
    try:
        with pytest.raises(GcsError) as err:
            GcsLink(f"udpin:127.0.0.1:{port}", timeout=1.0)
        assert "Address already in use" in str(err.value) and f"held by pid {other.pid} (" in str(err.value)
    finally:
        other.kill()


@pytest.mark.timeout(30)
def test_the_views_port_held_by_another_process_is_named():
    from groundstation.view import serve
    from onboard.config import load_scenario

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    other = holder("STREAM", f"s.bind(('127.0.0.1', {port})); s.listen(1)")
    try:
        with pytest.raises(GcsError) as err:
            serve(None, load_scenario("paper"), port, 1.0, False, None)
        assert "Address already in use" in str(err.value) and f"held by pid {other.pid} (" in str(err.value)
    finally:
        other.kill()
