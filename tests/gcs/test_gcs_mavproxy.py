"""MAVProxy (a real ground station, as a process) on ``pmon gcs hub``'s port sees the vehicle
through the hub and each target as ADS-B traffic (its adsb module), and drops them when they
are lost. MAVProxy 1.8.74's ``adsb status`` prints the count, then fails on each entry's
distance (the module never computes it), so a four-line MAVProxy module of the test's,
``pmonlist``, prints what MAVProxy's own adsb module holds: address, callsign, position."""
from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import time

import numpy as np
import pytest

from tests.support.processes import LineReader, stop_process
from sim.stack.hub_rig import FRAME, TARGETS, Rig

pytestmark = pytest.mark.sitl


LISTER = """from MAVProxy.modules.lib import mp_module


class Lister(mp_module.MPModule):
    def __init__(self, mpstate):
        super().__init__(mpstate, "pmonlist", "print MAVProxy's ADS-B traffic")
        self.add_command("pmonlist", self.cmd, "list traffic")

    def cmd(self, args):
        for key, v in sorted(self.module("adsb").threat_vehicles.items()):
            s = v.state
            print("traffic %s %s %.7f %.7f" % (key, s["callsign"].strip(), s["lat"] * 1e-7, s["lon"] * 1e-7))


def init(mpstate):
    return Lister(mpstate)
"""


def pump(out: LineReader, seconds: float) -> None:
    """Collect MAVProxy's lines for ``seconds`` (LineReader reads while it waits)."""
    try:
        out.wait_for(r"^\b\B$", seconds)  # matches nothing
    except AssertionError:
        pass


@pytest.mark.timeout(90)
@pytest.mark.parametrize("circles", [True, False], ids=["with-circles", "markers-only"])
def test_mavproxy_lists_each_target_as_traffic_and_drops_lost_ones(tmp_path, circles):
    pytest.importorskip("MAVProxy", reason="MAVProxy is a test-only dependency")
    (tmp_path / "pmonlist.py").write_text(LISTER)
    rig = Rig(circles=circles, lost_after_s=3.0)
    mp = subprocess.Popen(
        [sys.executable, "-m", "MAVProxy.mavproxy", f"--master=udpout:127.0.0.1:{rig.sport}", "--non-interactive",
         "--no-state", "--cmd=module load pmonlist; repeat add 1 adsb status; repeat add 1 pmonlist"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"),
        cwd=tmp_path)
    out = LineReader(mp)
    try:
        want = 8 if circles else 4
        mark = len(out.lines)
        callsigns = set()
        t = 200.0
        deadline = time.monotonic() + 25
        while time.monotonic() < deadline and len(callsigns) < 4:
            rig.veh.heartbeat()
            rig.tick(t)
            t += 1.0
            pump(out, 0.4)
            callsigns |= {m.group(1) for line in out.lines[mark:] if (m := re.search(r"^traffic \S+ (PMON-T\d) ", line))}
        assert any("Detected vehicle 1:1" in line for line in out.lines)  # the vehicle, through the hub
        assert callsigns == {"PMON-T1", "PMON-T2", "PMON-T3", "PMON-T4"}
        for line in out.lines[mark:]:  # where MAVProxy has each: one of the app's estimates, within 1 m
            if (m := re.search(r"^traffic \S+ PMON-T(\d) (\S+) (\S+)", line)):
                x, y = TARGETS[int(m.group(1)) - 1]
                e, n, _ = FRAME.enu_from_geodetic(float(m.group(2)), float(m.group(3)), FRAME.origin[2])
                assert min(math.hypot(e - (x + k), n - (y - k)) for k in np.arange(200.0, t)) <= 1.0, line
        out.wait_for(rf"total threat count: {want}\b", 10, since=mark)
        # the app falls silent: the hub stops the traffic, MAVProxy drops it (its 5 s timeout)
        lost = len(out.lines)
        out.wait_for(r"total threat count: 0\b", 3.0 + 5.0 + 6.0, since=lost)
    finally:
        stop_process(mp)
        rig.close()
