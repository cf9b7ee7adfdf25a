"""The ground-station outputs on ArduPilot's own firmware (ArduCopter SITL, ../shared/ardupilot
or $PMON_ARDUPILOT_SITL): STATUSTEXT chunks pass ArduPilot's routing whole, and ``pmon gcs hub``
puts the targets on a ground station's map during a monitoring flight with the autopilot's
ADS-B avoidance enabled (ADSB_TYPE 1, AVD_ENABLE 1, 1 km distances): 0 avoidance reports, 0
mode changes (bench/adsb_route.py measures the other route, which triggers it)."""
from __future__ import annotations

import time

import pytest

from sim.firmware.ardupilot import ArduPilotSitl, find_binary, skip_reason

pytestmark = [pytest.mark.ardupilot, pytest.mark.sitl,
              pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")]

LONG = "PMON: arming refused: PreArm: Need Position Estimate (EKF not ready, GPS 0 sats)"


@pytest.mark.timeout(120)
def test_statustext_chunks_pass_arducopters_routing_whole():
    from groundstation.gcs_link import GcsLink
    from onboard.app.mavlink_connection import Link
    from onboard.app.gcs.statustext import send_statustext

    with ArduPilotSitl(find_binary(), (35.145, 33.411, 160.0), speedup=1.0) as sitl:
        app = Link(sitl.url(0), source_system=1, source_component=191)
        try:
            with GcsLink(sitl.url(2), timeout=30) as gl:
                gl.connect()
                t0 = time.monotonic()
                for _ in range(3):  # ArduPilot learns the app's route from its heartbeat
                    app.send(app.mav.heartbeat_encode(18, 8, 0, 0, 3))
                    time.sleep(0.3)
                send_statustext(app, 4, LONG)
                assert gl.wait_for(lambda: LONG in gl.texts_since(t0, 191), 5), gl.texts_since(t0, 191)
        finally:
            app.close()


@pytest.mark.timeout(600)
def test_hub_draws_every_target_every_tick_without_triggering_avoidance(stock_flight):
    """40 autopilot s of the hub route (bench/adsb_route.py's) in the flight
    tests/firmware/test_ardupilot_altitude.py reads too (tests/support/stock_flight.py), with
    the autopilot's ADS-B avoidance on."""
    res = stock_flight
    hub = res["hub"]
    print(hub)
    assert hub["mode_changes"] == [] and hub["collision_msgs"] == 0 and hub["avoidance_texts"] == []
    assert hub["adsb_vehicle_on_observer"] == 0
    for name, row in hub["per_target"].items():
        assert row["ticks"] >= 10 and row["adsb"] == row["ticks"], (name, row)  # one per target per tick
    assert hub["max_error_m"] is not None and hub["max_error_m"] <= 1.0
    assert hub["hub_summary"]["estimates_refused"] == {}


@pytest.mark.timeout(900)
def test_the_flight_replays_to_the_same_decisions_bit_for_bit(stock_flight):
    """``pmon replay`` of the flight's run log (docs/MAVLINK.md "Replay"): every estimate and setpoint
    again, with the guidance's clock stops replayed as counts and PMON_ALT's set in flight."""
    from tests.support.replay_check import assert_replays_bit_for_bit
    ticks = assert_replays_bit_for_bit(stock_flight["m"].out / "run.jsonl", 40)
    assert sum("setup" in t["replay"] for t in ticks) >= 2  # the set parameter was replayed too
