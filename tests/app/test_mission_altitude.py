"""The flight policy holds the mission altitude h (PMON_ALT), over loopback with the mock
autopilot (issue 29, item 6): the setpoints carry h (they used to carry the vehicle's own
altitude at the tick, so a new h never flew and a vehicle a pilot had flown lower stayed low);
a change of h flies; after a takeover and resume the vehicle goes back to h.
The same on ArduCopter's own firmware: tests/firmware/test_ardupilot_altitude.py, which stands in for
this module where it runs in the same session (``mock_of``, tests/README.md)."""
from __future__ import annotations

import numpy as np
import pytest

from onboard.app.mavlink2 import mavlink
from sim.mock.autopilot import BootTimeline, MockAutopilot, Mode
from sim.firmware.priority import app_config_priority, vehicle_threads

from tests.support.app_helpers import ScriptedDf, wait_for
from tests.support.mavlink_gcs import Gcs

from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.contract import State
from onboard.config import load_scenario
from sim.mock.multicopter import DEMO_VEHICLE_PARAMS
from onboard.policy import POLICIES

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(240)]
SPEEDUP = 2.0
REACH_S = 30.0  # autopilot s to be within AT_H_M of a new h
AT_H_M = 1.0


def _time_to_h(ap: MockAutopilot, h: float, timeout_s: float = 60.0) -> float | None:
    """Autopilot s from now until the vehicle is within AT_H_M of ``h`` (None: not in time)."""
    t0 = ap.sim_time
    ok = ap.wait_until(lambda s: abs(s.pos_enu[2] - h) < AT_H_M, timeout_s / SPEEDUP * 2)
    return ap.sim_time - t0 if ok else None


@pytest.fixture(scope="module")
def flight():
    sc = load_scenario("paper", POLICIES["flight"])  # the vehicle motion: a planned segment per tick
    o = sc.origin
    out: dict = {"rx": []}
    ap = MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=SPEEDUP, seed=5,
                       endpoints=["tcpin:127.0.0.1:0"] * 2, params=DEMO_VEHICLE_PARAMS, max_lag_s=0.1,
                       boot=BootTimeline.scaled(3.0))
    # home = the mission origin: NED z = -up
    ap.watch("SET_POSITION_TARGET_LOCAL_NED", lambda msg: out["rx"].append((ap.copter.t, -msg.z)))
    ap.start()
    vehicle_threads(ap._thread)  # scheduled as a flight is (sim/firmware/priority.py)
    app = df = gcs = None
    try:
        app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{ap.port('tcpin', 0)}", sensor_port=0,
                                   auto_launch=True, seed=1, **app_config_priority()), sc).start()
        df = ScriptedDf(ap, app.sensor_port, np.array([t.mean for t in sc.targets])).start()
        vehicle_threads(df._t)
        gcs = Gcs(ap.port("tcpin", 1))
        assert wait_for(lambda: app.state == State.MONITORING
                        and sum(1 for t in app.ticks if t["planned"]) >= 3, 120), list(app.events)
        out["h0"] = ap.state().pos_enu[2]
        # 1. the operator raises h in flight
        out["set_60"] = gcs.param_set("PMON_ALT", 60.0)
        out["t_60"] = ap.sim_time
        out["to_60_s"] = _time_to_h(ap, 60.0)
        # 2. a pilot takes over (LOITER); h is lowered meanwhile; the operator resumes
        ack = gcs.command(1, mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, Mode.LOITER)
        assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED
        assert wait_for(lambda: app.state == State.PILOT_OVERRIDE, 10)
        out["set_45"] = gcs.param_set("PMON_ALT", 45.0)
        out["resume"] = gcs.command(191, mavlink.MAV_CMD_USER_1, 3)
        out["t_resume"] = ap.sim_time
        out["to_45_s"] = _time_to_h(ap, 45.0)
        out["ticks"] = list(app.ticks)
        out["counters"] = dict(app.counters)
        yield out
    finally:
        if df is not None:
            df.stop()
        if gcs is not None:
            gcs.close()
        if app is not None:
            app.stop()
        ap.stop()


@pytest.mark.mock_of("tests/firmware/test_ardupilot_altitude.py::test_a_new_h_flies_within_30_s")
def test_a_new_h_flies(flight):
    assert abs(flight["h0"] - 40.0) < AT_H_M
    assert flight["set_60"] is not None and flight["set_60"].param_value == 60.0
    print(f"within {AT_H_M} m of h = 60 m {flight['to_60_s']} autopilot s after the set")
    assert flight["to_60_s"] is not None and flight["to_60_s"] <= REACH_S
    # every setpoint of a tick planned after the set carries the new h
    first = min(t["t"] for t in flight["ticks"] if t["planned"] and t["next"] and t["t"] > flight["t_60"] + 1.0)
    alts = np.array([u for t, u in flight["rx"] if first + 0.5 < t < flight["t_resume"]])
    assert len(alts) > 10 and np.abs(alts - 60.0).max() < 0.01, np.unique(alts.round(2))


@pytest.mark.mock_of("tests/firmware/test_ardupilot_altitude.py::"
                     "test_after_a_takeover_and_resume_the_copter_is_back_at_h_within_30_s")
def test_after_a_takeover_and_resume_the_vehicle_returns_to_h(flight):
    assert flight["resume"] is not None and flight["resume"].result == mavlink.MAV_RESULT_ACCEPTED
    print(f"within {AT_H_M} m of h = 45 m {flight['to_45_s']} autopilot s after the resume")
    assert flight["to_45_s"] is not None and flight["to_45_s"] <= REACH_S
    assert flight["counters"].get("tick_errors", 0) == 0 and flight["counters"].get("io_errors", 0) == 0
