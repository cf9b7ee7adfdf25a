"""Replay feed: a recording is sent as valid datagrams, on time; bad files are named."""
import json
import socket

import pytest

from onboard.app.df import datagram as dg
from sim.stack.feed import read_recording, replay


@pytest.mark.timeout(30)
def test_replay_sends_every_recorded_scan_as_valid_datagrams(tmp_path):
    rec = tmp_path / "truth.jsonl"
    lines = [{"header": {"scenario": "paper"}}] + [
        {"t": 5.0 + k, "k": k, "bearings": [[0.1 * k], [], [0.2, -0.3], [3.0]]} for k in range(3)]
    rec.write_text("\n".join(json.dumps(x) for x in lines) + "\n")
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(2.0)
    try:
        n = replay(rec, rx.getsockname(), speedup=20.0, log=lambda s: None)
        got = [dg.parse(rx.recvfrom(4096)[0], 4) for _ in range(n)]
    finally:
        rx.close()
    assert n == 12
    assert [(d.t, d.ch) for d in got] == [(5.0 + k, ch) for k in range(3) for ch in range(4)]
    assert got[2].bearings.tolist() == [0.2, -0.3]


def test_a_bad_recording_is_named(tmp_path):
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"t": 1}\n')
    with pytest.raises(ValueError, match="bad.jsonl:1"):
        list(read_recording(bad))


def test_the_live_feeds_start_waits_for_the_arming_or_the_mission_altitude():
    """--start altitude (pmon demo's): the first scan only once the vehicle is armed within 1 m
    of h (the app's own 'at altitude'), so the world's t = 0 has the UAV at h as the paper's
    mission; --start armed scans from the ground; now as soon as a position is known."""
    import numpy as np

    from onboard.app.autopilot.pose import PoseSample
    from sim.stack.live_feed import LiveFeedConfig, ready_to_scan

    def at(up):
        return PoseSample(10.0, np.array([150.0, 200.0, up]), np.zeros(3), None)
    altitude_m = 40.0
    assert not ready_to_scan("altitude", True, at(0.0), altitude_m)
    assert ready_to_scan("armed", True, at(0.0), altitude_m)
    assert not ready_to_scan("altitude", True, at(38.9), altitude_m)
    assert ready_to_scan("altitude", True, at(39.1), altitude_m) and ready_to_scan("altitude", True, at(55.0), altitude_m)
    assert not ready_to_scan("altitude", False, at(40.0), altitude_m)
    assert not ready_to_scan("armed", False, at(40.0), altitude_m)
    assert ready_to_scan("now", False, at(0.0), altitude_m)
    assert not any(ready_to_scan(s, True, None, altitude_m) for s in ("armed", "altitude", "now"))  # no position yet
    with pytest.raises(ValueError, match="feed start must be one of armed, altitude, now"):
        LiveFeedConfig("tcp:127.0.0.1:1", start="airborne")
