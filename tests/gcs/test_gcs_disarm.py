"""A take-off refused because the autopilot disarmed itself after ``arm`` (ArduCopter's
DISARM_DELAY) says so, and when, not "no reason given": the mock ArduCopter at 10x (its 10 s
auto-disarm is 1 s of wall time), the ground station's commands in-process."""
from __future__ import annotations

import re

import pytest

from sim.mock.autopilot import BootTimeline, MockAutopilot

from groundstation import gcs_commands as C
from groundstation.cli import main
from groundstation.errors import GcsError
from groundstation.gcs_link import GcsLink

pytestmark = pytest.mark.sitl


@pytest.fixture
def ap():
    ap = MockAutopilot(home=(35.145, 33.411, 160.0), speedup=10.0, endpoints=["tcpin:127.0.0.1:0"],
                       boot=BootTimeline.scaled(2.0)).start()
    try:
        yield ap
    finally:
        ap.stop()


def _url(ap) -> str:
    return f"tcp:127.0.0.1:{ap.port('tcpin', 0)}"


@pytest.mark.timeout(90)
def test_a_takeoff_after_the_autopilot_disarmed_itself_says_so_and_when(ap):
    with GcsLink(_url(ap), timeout=10) as gl:
        gl.connect()
        C.arm(gl, wait=True)
        assert gl.v.armed
        assert gl.wait_for(lambda: gl.v.armed is False, 10)  # DISARM_DELAY: 10 s of autopilot time
        with pytest.raises(GcsError) as err:
            C.takeoff(gl, 40.0, wait=False)
    text = str(err.value)
    assert "no reason given" not in text
    m = re.search(r"refused by the autopilot \(FAILED\): the autopilot disarmed itself ([\d.]+) s ago "
                  r"\('Disarming motors[^']*'\), ([\d.]+) s after it armed: ArduPilot disarms a vehicle armed "
                  r"on the ground that has not taken off after DISARM_DELAY = 10 s; arm again and take off "
                  r"within 10 s \[vehicle: GUIDED, disarmed", text)
    assert m, text
    assert float(m.group(1)) < 5 and abs(float(m.group(2)) - 10.0) <= 1.5, text


@pytest.mark.timeout(90)
def test_a_takeoff_command_started_after_the_disarm_says_the_vehicle_was_disarmed_at_connect(ap, capsys):
    """The issue's case: ``arm --wait``, then ``takeoff`` as a separate command after the auto-disarm."""
    assert main(["--connect", _url(ap), "--timeout", "10", "arm", "--wait"]) == 0
    assert ap.wait_until(lambda s: not s.armed, 10)
    capsys.readouterr()
    assert main(["--connect", _url(ap), "--timeout", "5", "takeoff", "40"]) == 1
    err = capsys.readouterr().err.strip()
    assert re.fullmatch(r"pmon gcs: takeoff to 40 m refused by the autopilot \(FAILED\): the vehicle was "
                        r"disarmed already when this command connected [\d.]+ s ago \(ArduPilot disarms a "
                        r"vehicle armed on the ground that has not taken off after DISARM_DELAY = 10 s\): arm "
                        r"again and take off within 10 s \[vehicle: GUIDED, disarmed, [-\d.]+ m above home\]",
                        err), err
