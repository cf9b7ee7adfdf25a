"""Frame changes are not taken from the air (issue 23, part 3), in flight, over real sockets.

The app's autopilot link is unsigned UDP (``udpin``; the mock autopilot sends to it), so anyone
who can reach the port can pose as the autopilot: a raw pymavlink peer with the autopilot's
system and component ids sends

  1. a GPS_GLOBAL_ORIGIN 2.6 km away (the old app took it: 91 setpoints went out 2 km outside
     the area): refused, the app stops commanding and says so; after the operator's resume it
     flies on the fixed origin;
  2. SYSTEM_TIMEs an hour ahead (the old clock jumped: a burst of coast ticks, false watchdog
     alarms): ignored, counted; no coast tick, no alarm, every scan of the DF ticked.
  3. (defence in depth) a code path that converts with another origin than the fixed one,
     injected: the setpoints are refused as sent (the fence is checked on the message).

Throughout, every setpoint the autopilot receives is checked against the fence where it lands
(the mock's local NED at the mission origin): 0 outside.
"""
from __future__ import annotations

import time

import numpy as np
import pytest

from onboard.app.mavlink2 import mavlink, mavutil
from sim.mock.autopilot import BootTimeline, MockAutopilot

from tests.support.app_helpers import ScriptedDf, wait_autopilot_s, wait_for

from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.contract import State
from onboard.app.autopilot.pose import Frame
from onboard.config import load_scenario
from onboard.policy import with_policy
from onboard.core.obstacles import Obstacles
from sim.mock.multicopter import DEMO_VEHICLE_PARAMS

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]


@pytest.fixture(scope="module")
def flight():
    sc = with_policy(load_scenario("paper"), "paper")
    o = sc.origin
    lo, hi = np.array(sc.area.min_m), np.array(sc.area.max_m)
    inflated = Obstacles.from_boxes(sc.obstacles).inflate(sc.uav.obstacle_margin_m)
    out: dict = {"rx": [], "outside": []}
    app = OnboardApp(AppConfig("udpin:127.0.0.1:0", sensor_port=0, auto_launch=True, seed=1), sc).start()
    port = app.link.conn.port.getsockname()[1]
    ap = MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=3.0, seed=5, params=DEMO_VEHICLE_PARAMS,
                       endpoints=[f"udpout:127.0.0.1:{port}"], max_lag_s=0.1, boot=BootTimeline.scaled(3.0))

    def spy(msg):  # where the setpoint lands: home = mission origin, NED = (north, east, -up)
        p = np.array([msg.y, msg.x, -msg.z])
        out["rx"].append((ap.copter.t, p))
        band = (app.params["PMON_ALT_MIN"], app.params["PMON_ALT_MAX"])
        if np.any(p < lo) or np.any(p > hi) or not band[0] <= p[2] <= band[1] or inflated.contains(p[None]).any():
            out["outside"].append(p.round(1).tolist())
    ap.watch("SET_POSITION_TARGET_LOCAL_NED", spy)
    ap.start()
    df = ScriptedDf(ap, app.sensor_port, np.array([t.mean for t in sc.targets])).start()
    url = f"udpout:127.0.0.1:{port}"
    hostile = mavutil.mavlink_connection(url, source_system=1, source_component=1, dialect="ardupilotmega")
    gcs = mavutil.mavlink_connection(url, source_system=255, source_component=190, dialect="ardupilotmega")
    try:
        assert wait_for(lambda: app.state == State.MONITORING
                     and sum(1 for t in app.ticks if t["planned"]) >= 3, 90), list(app.events)

        # 1. a forged GPS_GLOBAL_ORIGIN, 1843 m east and 1891 m north of the real one
        fixed = app.autopilot.origin.value
        lat, lon, alt = Frame(*fixed).geodetic_from_enu((1843.0, 1891.0, 0.0))
        n_rx = len(out["rx"])
        hostile.mav.gps_global_origin_send(int(lat * 1e7), int(lon * 1e7), int(alt * 1000), 0)
        wait_for(lambda: app.state == State.FAULT, 5)  # asserted below: the flight goes on either way
        out["state_after_origin"] = app.state
        out["origin_after"] = app.autopilot.origin.value
        wait_autopilot_s(ap, 3.0)
        out["rx_in_fault"] = [r for r in out["rx"][n_rx:] if r[0] > ap.copter.t - 2.0]
        gcs.mav.command_long_send(1, 191, mavlink.MAV_CMD_USER_1, 0, 3, 0, 0, 0, 0, 0, 0)  # resume
        assert wait_for(lambda: app.state == State.MONITORING, 10), list(app.events)[-5:]
        t_resume = ap.copter.t
        wait_autopilot_s(ap, 6.0)
        out["rx_after_resume"] = [r for r in out["rx"] if r[0] > t_resume]

        # 2. SYSTEM_TIME an hour ahead, three times 0.5 s apart
        coasted0 = app.counters.get("ticks_coasted", 0)
        t0 = ap.sim_time
        for _ in range(3):
            hostile.mav.system_time_send(0, int((ap.sim_time + 3600.0) * 1000))
            time.sleep(0.5)
        wait_autopilot_s(ap, 4.0)
        out["clock"] = {"jumps": app.clock.jumps, "jumps_ignored": app.clock.jumps_ignored,
                        "now_minus_ap": app.clock.now() - ap.sim_time}
        out["coasted_in_spoof"] = app.counters.get("ticks_coasted", 0) - coasted0
        out["sent_in_spoof"] = [t for t in df.sent if t0 < t < ap.sim_time - 1.0]
        out["ticked_in_spoof"] = {tk["t"] for tk in app.ticks if tk["channels"]}

        # 3. a conversion origin other than the fixed one, injected into the app
        refused0 = app.counters.get("setpoints_refused_at_send", 0)
        real = app.vehicle.ned_origin
        with app.lock:  # between two sends
            app.vehicle.ned_origin = (lat, lon, alt)
        time.sleep(0.05)  # a setpoint sent just before may still be on its way
        n_rx = len(out["rx"])
        wait_autopilot_s(ap, 3.0)
        app.vehicle.ned_origin = real
        out["refused_at_send"] = app.counters.get("setpoints_refused_at_send", 0) - refused0
        out["state_injected"] = app.state
        out["rx_injected"] = len(out["rx"]) - n_rx
        out["watchdog"] = dict(app.watchdog.counts)
        out["events"] = [e for _, e in app.events]
        out["counters"] = dict(app.counters)
        yield out
    finally:
        hostile.close()
        gcs.close()
        df.stop()
        app.stop()
        ap.stop()


def test_no_setpoint_lands_outside_the_fence(flight):
    assert len(flight["rx"]) > 100
    assert flight["outside"] == []


def test_a_forged_origin_is_refused_commanding_stops_and_resume_flies_on_the_fixed_one(flight):
    assert flight["state_after_origin"] == State.FAULT
    assert flight["counters"]["origin_changes_refused"] == 1
    assert flight["rx_in_fault"] == [], "no setpoint while the origin is in doubt"
    assert any("NED origin moved 2641 m: refused, setpoints stopped" in e for e in flight["events"])
    assert len(flight["rx_after_resume"]) > 20  # flying again, on the fixed origin (fence: above)


def test_forged_system_time_an_hour_ahead_is_ignored(flight):
    c = flight["clock"]
    assert c["jumps"] == 0 and c["jumps_ignored"] >= 3
    assert abs(c["now_minus_ap"]) < 1.0, "the app's clock is the autopilot's"
    assert flight["coasted_in_spoof"] == 0 and flight["watchdog"] == {}
    assert len(flight["sent_in_spoof"]) >= 3
    assert set(flight["sent_in_spoof"]) <= flight["ticked_in_spoof"], "every DF scan ticked"
    assert flight["counters"].get("clock_jumps_ignored", 0) >= 3
    assert sum("autopilot time jump not confirmed" in e for e in flight["events"]) == 1


def test_a_message_built_on_another_origin_is_refused_as_sent(flight):
    assert flight["refused_at_send"] >= 1, (flight["state_injected"], flight["events"][-8:])
    assert flight["rx_injected"] == 0
