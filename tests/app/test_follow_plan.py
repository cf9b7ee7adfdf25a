"""The flight policy's setpoints fly the plan, over loopback with the mock autopilot (stock
ArduCopter limits, its model of the jerk-limited GUIDED shaper): each tick's plan starts at the
scan it answers, where the vehicle was then, with the acceleration the last plan ended with, and
the vehicle is at the planned point when the next scan comes. Before, the plan started at the
tick's snapshot (a telemetry sample later, the app's latency) and its acceleration stepped at
every tick: on ArduCopter SITL 0.4-0.7 m median and 1.5-2.0 m p95 from the planned point
(docs/SITL.md), on the mock 0.46 / 1.57 m. The same on the firmware: tests/firmware/test_ardupilot.py (flight A),
which stands in for both tests here where it runs in the same session (``mock_of``, tests/README.md)."""
from __future__ import annotations

import numpy as np
import pytest

from sim.mock.autopilot import BootTimeline, MockAutopilot
from sim.firmware.priority import app_config_priority, vehicle_threads

from tests.support.app_helpers import ScriptedDf, wait_for
from tests.support.plan_checks import assert_plans_start_at_their_scans_and_join

from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.contract import State
from onboard.config import load_scenario
from onboard.policy import POLICIES
from sim.stack.procedure import follow_errors_m

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(240)]
SPEEDUP = 2.0
MONITORING_TICKS = 50


@pytest.fixture(scope="module")
def ticks():
    sc = load_scenario("paper", POLICIES["flight"])
    o = sc.origin
    ap = MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=SPEEDUP, seed=3,
                       endpoints=["tcpin:127.0.0.1:0"], max_lag_s=0.1, boot=BootTimeline.scaled(3.0))
    ap.start()
    vehicle_threads(ap._thread)  # scheduled as a flight is (sim/firmware/priority.py)
    app = df = None
    try:
        app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{ap.port('tcpin', 0)}", sensor_port=0,
                                   auto_launch=True, seed=1, **app_config_priority()), sc).start()
        df = ScriptedDf(ap, app.sensor_port, np.array([t.mean for t in sc.targets])).start()
        vehicle_threads(df._t)
        assert wait_for(lambda: app.state == State.MONITORING
                        and sum(1 for t in app.ticks if t["planned"]) >= MONITORING_TICKS, 200), list(app.events)
        yield [t for t in app.ticks]
    finally:
        if df is not None:
            df.stop()
        if app is not None:
            app.stop()
        ap.stop()


@pytest.mark.mock_of("tests/firmware/test_ardupilot.py::test_each_plan_starts_at_its_scan_with_the_last_plans_acceleration")
def test_each_plan_starts_at_its_scan_with_the_last_plans_acceleration(ticks):
    assert_plans_start_at_their_scans_and_join(ticks, MONITORING_TICKS - 5, MONITORING_TICKS - 10)


@pytest.mark.mock_of("tests/firmware/test_ardupilot.py::test_the_copter_flies_the_plan_instead_of_braking_to_each_point")
def test_the_vehicle_is_at_the_planned_point_at_the_next_scan(ticks):
    d = np.array(follow_errors_m(ticks))
    assert len(d) >= MONITORING_TICKS - 10
    print(f"from the planned point at the next scan: median {np.median(d):.3f} m, p95 {np.percentile(d, 95):.3f} m")
    # p95 is what tells the old behaviour (0.46 / 1.57 m) from this one; this one's spread between
    # runs on one idle machine reaches the old median and about 1 m of p95 (docs/LOG.md 2026-12-03,
    # "the follow test's spread"), so the median is held only against a gross regression, and p95
    # between this one's worst and the old one's
    assert np.median(d) <= 0.9 and np.percentile(d, 95) <= 1.3, (np.median(d), np.percentile(d, 95))
