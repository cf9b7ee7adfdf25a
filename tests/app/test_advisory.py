"""Advisory (``pmon run --advise``, the advise action) over loopback with the mock autopilot: the
app tracks and plans from where the vehicle is while someone else flies it, publishes the plan's
next point, and nothing it sends the autopilot is a command, counted on the link by a relay
(sim/stack/link_count.py), not by the app. Refusals; the hand-over to monitoring by one start, through
the mode entry (GUIDED asked, setpoints flow); monitoring back to advisory. The same on
ArduCopter's own firmware flying an AUTO mission: tests/firmware/test_ardupilot_advisory.py."""
from __future__ import annotations

import math
import time

import numpy as np
import pytest

from onboard.app.app import OnboardApp
from onboard.app.app_config import AppConfig
from onboard.app.contract import ADVICE_FIELDS, STAT_FIELDS, Action, Reason, State
from onboard.app.mavlink2 import mavlink
from onboard.config import load_scenario
from onboard.policy import POLICIES
from sim.mock.autopilot import BootTimeline, MockAutopilot, Mode
from sim.stack.link_count import LinkCounter
from sim.mock.multicopter import DEMO_VEHICLE_PARAMS
from sim.firmware.priority import app_config_priority, vehicle_threads
from sim.stack.tcp_proxy import TcpProxy

from tests.support.app_helpers import ScriptedDf, wait_for
from tests.support.mavlink_gcs import Gcs

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(240)]
SPEEDUP = 2.0
CMD = mavlink.MAV_CMD_USER_1


def _app_cmd(gcs: Gcs, action: Action):
    return gcs.command(191, CMD, int(action))


def _stat(m) -> dict:
    return dict(zip(STAT_FIELDS, m.data))


def _fly_to(gcs: Gcs, e: float, n: float, up: float) -> None:
    """The pilot (a ground station, component 190) moves the vehicle in GUIDED: home = the
    mission origin, so NED = (n, e, -up)."""
    gcs.conn.mav.set_position_target_local_ned_send(0, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, 3576,
                                                    n, e, -up, 0, 0, 0, 0, 0, 0, 0, 0)


@pytest.fixture(scope="module")
def flight():
    sc = load_scenario("paper", POLICIES["flight"])
    o = sc.origin
    ap = MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=SPEEDUP, seed=5,
                       endpoints=["tcpin:127.0.0.1:0"] * 2, params=DEMO_VEHICLE_PARAMS, max_lag_s=0.1,
                       boot=BootTimeline.scaled(3.0))
    ap.start()
    vehicle_threads(ap._thread)
    counter = LinkCounter(compid=191)
    proxy = TcpProxy(("127.0.0.1", ap.port("tcpin", 0)), tap=counter.feed)
    app = df = gcs = None
    out: dict = {}
    try:
        app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{proxy.port}", sensor_port=0, seed=1, advise=True,
                                   **app_config_priority()), sc).start()
        df = ScriptedDf(ap, app.sensor_port, np.array([t.mean for t in sc.targets])).start()
        vehicle_threads(df._t)
        gcs = Gcs(ap.port("tcpin", 1))
        assert wait_for(lambda: app.state == State.ADVISORY and app.autopilot.has_position(), 60)
        # refusals on the ground: start (not armed), pause (not monitoring), launch (advisory)
        out["start_on_ground"] = _app_cmd(gcs, Action.START)
        out["pause"] = _app_cmd(gcs, Action.PAUSE)
        out["launch"] = _app_cmd(gcs, Action.LAUNCH)
        out["advise_again"] = _app_cmd(gcs, Action.ADVISE)
        # the pilot flies: GUIDED, arm, take off, then on to a point 80 m east of the start
        assert gcs.command(1, mavlink.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED).result == mavlink.MAV_RESULT_ACCEPTED
        assert wait_for(lambda: gcs.command(1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result
                        == mavlink.MAV_RESULT_ACCEPTED, 60, poll_s=1.0)
        assert gcs.command(1, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 40).result == mavlink.MAV_RESULT_ACCEPTED
        assert ap.wait_until(lambda s: s.pos_enu[2] > 38.0, 60)
        start = np.array(ap.state().pos_enu)
        t_pilot = app.clock.now()
        for _ in range(24):  # 12 s of the pilot's setpoints at 2 Hz: 24 autopilot s, the 80 m flown in ~10
            _fly_to(gcs, start[0] + 80.0, start[1], 40.0)
            time.sleep(0.5)
        out["moved_m"] = float(np.hypot(*(np.array(ap.state().pos_enu[:2]) - start[:2])))
        out["advisory_ticks"] = [t for t in app.ticks if t["t"] > t_pilot]
        out["by_kind_advisory"], out["by_type_advisory"] = counter.snapshot()
        out["stats_advisory"] = [_stat(m) for m in gcs.msgs if m.get_type() == "DEBUG_FLOAT_ARRAY"
                                 and m.name == "PMON_STAT" and m.get_srcComponent() == 191]
        # the pilot hands over from LOITER: one start
        assert gcs.command(1, mavlink.MAV_CMD_DO_SET_MODE, 1, Mode.LOITER).result == mavlink.MAV_RESULT_ACCEPTED
        assert ap.wait_until(lambda s: s.mode == Mode.LOITER, 10)
        time.sleep(1.0)
        out["commands_before_start"] = counter.commands()
        out["start"] = _app_cmd(gcs, Action.START)
        out["monitoring"] = wait_for(lambda: app.state == State.MONITORING and app.stream.setpoint is not None
                                     and ap.state().mode == Mode.GUIDED, 20)
        time.sleep(3.0)
        out["commands_monitoring"] = counter.commands()
        # and back: advisory from monitoring stops the setpoints
        out["advise"] = _app_cmd(gcs, Action.ADVISE)
        time.sleep(1.0)
        out["after_advise"] = counter.commands()
        time.sleep(3.0)
        out["later"] = counter.commands()
        out["state_end"] = app.state
        out["counters"] = dict(app.counters)
        yield out
    finally:
        for x in (df, gcs, app):
            if x is not None:
                x.stop() if hasattr(x, "stop") else x.close()
        proxy.close()
        ap.stop()


def _ok(ack) -> bool:
    return ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED


def test_refusals_in_advisory(flight):
    s = flight["start_on_ground"]
    assert s is not None and s.result == mavlink.MAV_RESULT_DENIED and s.result_param2 == Reason.NOT_ARMED
    for what in ("pause", "launch"):
        a = flight[what]
        assert a is not None and a.result == mavlink.MAV_RESULT_DENIED and a.result_param2 == Reason.WRONG_STATE, what
    assert _ok(flight["advise_again"])  # already in effect: accepted, nothing done


def test_advisory_plans_from_the_vehicle_every_tick_and_commands_nothing(flight):
    ticks = flight["advisory_ticks"]
    assert flight["moved_m"] > 40.0, flight["moved_m"]  # the pilot flew it
    assert len(ticks) >= 15, len(ticks)
    assert all(t["state"] == State.ADVISORY for t in ticks)
    planned = [t for t in ticks if t["next"] is not None]
    assert len(planned) >= len(ticks) - 1, [t["next"] for t in ticks]  # a plan each tick it flew
    for t in planned:  # from where the vehicle was at the scan, not from a plan it does not fly
        assert t["plan_from"] == t["uav_enu"] and not t["sent"] and t["segment"] is None
    # the advised point moves with the vehicle (planned from it, not from the last advice)
    firsts, lasts = np.array(planned[0]["plan_from"][:2]), np.array(planned[-1]["plan_from"][:2])
    assert np.hypot(*(lasts - firsts)) > 30.0
    # nothing but telemetry and reads reached the autopilot from the app, no setpoint among them
    kinds, types = flight["by_kind_advisory"], flight["by_type_advisory"]
    print("advisory, what the app sent its autopilot:", types)
    assert kinds.get("command", 0) == 0, types
    assert kinds.get("telemetry", 0) > 30
    assert flight["commands_before_start"] == {}
    # PMON_STAT carried the advice each tick
    adv = [s for s in flight["stats_advisory"] if s["state"] == State.ADVISORY
           and all(math.isfinite(s[k]) for k in ADVICE_FIELDS)]
    assert len(adv) >= 10
    assert all(math.isnan(s["next_e_m"]) for s in flight["stats_advisory"] if s["state"] == State.ADVISORY)


def test_one_start_hands_over_to_monitoring_and_advise_takes_it_back(flight):
    assert _ok(flight["start"]) and flight["monitoring"]
    sent = flight["commands_monitoring"]
    print("monitoring, the app's commands:", sent)
    assert sent.get("SET_POSITION_TARGET_LOCAL_NED", 0) >= 10
    assert sent.get(f"COMMAND_LONG:{mavlink.MAV_CMD_DO_SET_MODE}", 0) >= 1  # GUIDED asked
    assert _ok(flight["advise"])
    a, b = flight["after_advise"], flight["later"]
    assert flight["state_end"] == State.ADVISORY and a == b, (a, b)  # nothing more sent once advisory
    assert flight["counters"].get("tick_errors", 0) == 0 and flight["counters"].get("io_errors", 0) == 0
