"""The app speaks MAVLink 2 on the wire, whichever module a process imports first: pymavlink
picks the protocol from ``MAVLINK20`` when mavutil loads a dialect, and onboard/app/mavlink2.py
sets it (tests/test_layout.py checks that every module takes mavutil from there)."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SEND = """
import sys
{first}
from onboard.app.mavlink_connection import Link
link = Link("udpout:127.0.0.1:" + sys.argv[1])
assert link.send(link.mav.heartbeat_encode(6, 8, 0, 0, 4))
link.close()
"""


@pytest.mark.parametrize("first", ["", "from pymavlink import mavutil", "import onboard.app.app"])
def test_the_apps_link_sends_mavlink2_frames_in_a_fresh_process(first):
    """A fresh interpreter without MAVLINK20 in its environment (pymavlink's default is MAVLink 1),
    importing pymavlink itself, or the whole app, before the link: the heartbeat it sends starts
    with MAVLink 2's magic 0xFD (MAVLink 1's is 0xFE)."""
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(20.0)
    env = {k: v for k, v in os.environ.items() if k != "MAVLINK20"}
    env["PYTHONPATH"] = str(ROOT)
    try:
        run = subprocess.run([sys.executable, "-c", SEND.format(first=first), str(rx.getsockname()[1])],
                             env=env, cwd=ROOT, capture_output=True, text=True, timeout=60)
        assert run.returncode == 0, run.stderr
        data, _ = rx.recvfrom(512)
    finally:
        rx.close()
    assert data[0] == 0xFD, f"first byte {data[0]:#x}: not a MAVLink 2 frame"
    assert data[7:10] == b"\x00\x00\x00"  # HEARTBEAT, message id 0 in the 3 bytes MAVLink 2 gives it
