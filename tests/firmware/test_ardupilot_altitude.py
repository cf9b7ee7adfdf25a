"""The mission altitude h on ArduPilot's own firmware (issue 29, item 6), with the real programs
as docs/SITL.md flies them (sim/stack/procedure.py; ArduCopter SITL, stock parameters and ADS-B avoidance on): the flight
policy's setpoints carry h, so ``pmon gcs params set PMON_ALT 60`` flies the copter to 60 m,
and after a pilot's takeover (LOITER: with no stick input ArduCopter sinks in it) and the
operator's resume the copter climbs back to h. Before, the setpoints carried the copter's own
altitude at each tick: it stayed at 40 m, and after a takeover it flew on at the height the
pilot left it at. The mock's version: tests/app/test_mission_altitude.py. The flight is the one
tests/firmware/test_ardupilot_hub.py reads (tests/support/stock_flight.py): the climb to 60 m
happens while the hub draws the targets, the takeover after it."""
from __future__ import annotations

import pytest

from onboard.app.mavlink2 import mavlink
from sim.firmware.ardupilot import skip_reason

from tests.support.stock_flight import AT_H_M, REACH_S

pytestmark = [pytest.mark.ardupilot, pytest.mark.sitl,
              pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")]


@pytest.fixture(scope="module")
def flight(stock_flight):
    """The flight tests/firmware/test_ardupilot_hub.py reads too (tests/support/stock_flight.py:
    ADS-B avoidance on, which nothing here triggers: that file checks it)."""
    return stock_flight


def test_a_new_h_flies_within_30_s(flight):
    assert flight["set"].rc == 0 and "PMON_ALT = 60" in flight["set"].stdout, flight["set"].stdout
    r = flight["to_60"]
    print(f"PMON_ALT 40 -> 60: within {AT_H_M} m of 60 m after {r}")
    assert r["s"] is not None and r["s"] <= REACH_S and r["held_within_m"] < AT_H_M, r
    # climbing to and flying at the new h, never inside an obstacle (the planner now takes those
    # below 60 m minus its margin as overflyable)
    c = flight["containment"]
    assert c["in_obstacle"] == 0 and c["outside_area"] == 0, c


def test_after_a_takeover_and_resume_the_copter_is_back_at_h_within_30_s(flight):
    assert flight["loiter"] is not None and flight["loiter"].result == mavlink.MAV_RESULT_ACCEPTED
    assert flight["resume"] is not None and flight["resume"].result == mavlink.MAV_RESULT_ACCEPTED
    r = flight["back"]
    print(f"LOITER 5 s: down to {flight['low_m']:.1f} m; back within {AT_H_M} m of 60 m after {r}")
    assert flight["low_m"] < 60.0 - 2 * AT_H_M, "the takeover left the copter off h (else this shows nothing)"
    assert r["s"] is not None and r["s"] <= REACH_S and r["held_within_m"] < AT_H_M, r
    assert flight["end_state"] == "monitoring"
    sent = [r for r in flight["m"].run_log() if r["sent"] and r["segment"] and r["t"] > flight["t_resumed"]]
    assert sent and all(r["segment"]["p0"][2] == pytest.approx(60.0) for r in sent)
