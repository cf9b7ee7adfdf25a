"""The onboard app's MAVLink interface over loopback: parameters, commands with ACKs and
reasons, and DF datagram validation through the real UDP port (mock autopilot, 10x)."""
from __future__ import annotations

import json
import socket

import numpy as np
import pytest

from onboard.app.mavlink2 import mavlink
from sim.mock.autopilot import BootTimeline, MockAutopilot, Mode

from onboard.app.df import datagram as dg
from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.contract import Reason, State
from onboard.app.params import SPECS
from onboard.config import load_scenario
from onboard.policy import with_policy
from tests.support.mavlink_gcs import Gcs
from tests.support.app_helpers import wait_for

pytestmark = pytest.mark.sitl
USER_1 = mavlink.MAV_CMD_USER_1


@pytest.fixture(scope="module")
def rig():
    sc = with_policy(load_scenario("paper"), "paper")
    o = sc.origin
    ap = MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=10.0,
                       endpoints=["tcpin:127.0.0.1:0"] * 2, boot=BootTimeline.scaled(2.0)).start()
    app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{ap.port('tcpin', 0)}", sensor_port=0), sc).start()
    gcs = Gcs(ap.port("tcpin", 1))
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    wait_for(lambda: app.vehicle.ned_origin is not None and app.poses.latest() is not None
             and ap.copter.position_ok, 10)
    try:
        yield ap, app, gcs, sock
    finally:
        sock.close()
        gcs.close()
        app.stop()
        ap.stop()


def param_values(gcs, since, name=None):
    return [m for m in gcs.msgs[since:] if m.get_type() == "PARAM_VALUE" and m.get_srcComponent() == 191
            and (name is None or m.param_id == name)]


@pytest.mark.timeout(60)
def test_parameters_list_read_set_and_refusals(rig):
    ap, app, gcs, _ = rig
    n = len(gcs.msgs)
    gcs.conn.mav.param_request_list_send(1, 191)
    assert gcs.wait(lambda m: len(param_values(gcs, n)) >= len(SPECS), 5) is not None or \
        len(param_values(gcs, n)) >= len(SPECS)
    got = {m.param_id: m for m in param_values(gcs, n)}
    assert set(got) == {s.name for s in SPECS} and all(m.param_count == len(SPECS) for m in got.values())
    assert got["PMON_CLUTTER"].param_value == pytest.approx(1.0)
    # a good set answers with the new value and takes effect
    n = len(gcs.msgs)
    gcs.conn.mav.param_set_send(1, 191, b"PMON_CLUTTER", 2.5, mavlink.MAV_PARAM_TYPE_REAL32)
    m = gcs.wait(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "PMON_CLUTTER", 5, n)
    assert m is not None and m.param_value == pytest.approx(2.5) and app.params["PMON_CLUTTER"] == 2.5
    # out of range: answered with the unchanged value, and a STATUSTEXT saying why
    n = len(gcs.msgs)
    gcs.conn.mav.param_set_send(1, 191, b"PMON_PD", 1.5, mavlink.MAV_PARAM_TYPE_REAL32)
    m = gcs.wait(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "PMON_PD", 5, n)
    assert m is not None and m.param_value == pytest.approx(0.95)
    assert gcs.wait(lambda m: m.get_type() == "STATUSTEXT" and "out of range" in m.text, 5, n)
    # unknown name: a STATUSTEXT; read by name
    n = len(gcs.msgs)
    gcs.conn.mav.param_set_send(1, 191, b"PMON_NOPE", 1.0, mavlink.MAV_PARAM_TYPE_REAL32)
    assert gcs.wait(lambda m: m.get_type() == "STATUSTEXT" and "unknown parameter" in m.text, 5, n)
    gcs.conn.mav.param_request_read_send(1, 191, b"PMON_NR", -1)
    m = gcs.wait(lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "PMON_NR", 5, n)
    assert m is not None and m.param_value == 4
    gcs.conn.mav.param_set_send(1, 191, b"PMON_CLUTTER", 1.0, mavlink.MAV_PARAM_TYPE_REAL32)


@pytest.mark.timeout(90)
def test_commands_are_acknowledged_with_reasons(rig):
    ap, app, gcs, sock = rig
    ack = gcs.command(191, USER_1, 1)  # start on the ground
    assert ack.result == mavlink.MAV_RESULT_DENIED and ack.result_param2 == Reason.NOT_ARMED
    assert gcs.wait(lambda m: m.get_type() == "STATUSTEXT" and "not armed" in m.text, 5)
    ack = gcs.command(191, USER_1, 2)  # pause while idle
    assert ack.result == mavlink.MAV_RESULT_DENIED and ack.result_param2 == Reason.WRONG_STATE
    assert gcs.command(191, USER_1, 4).result == mavlink.MAV_RESULT_ACCEPTED  # stop: already idle
    ack = gcs.command(191, USER_1, 9)
    assert ack.result == mavlink.MAV_RESULT_DENIED and ack.result_param2 == Reason.UNKNOWN_ACTION
    # the pilot flies it up in LOITER; no DF data yet -> temporarily rejected
    assert gcs.command(1, mavlink.MAV_CMD_DO_SET_MODE, 1, Mode.GUIDED).result == 0
    assert gcs.command(1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
    assert gcs.command(1, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 20).result == 0
    assert ap.wait_until(lambda s: s.alt_rel > 19.5, 20)
    assert gcs.command(1, mavlink.MAV_CMD_DO_SET_MODE, 1, Mode.LOITER).result == 0
    assert wait_for(lambda: app.vehicle.custom_mode == Mode.LOITER and app.vehicle.flying(), 5)
    ack = gcs.command(191, USER_1, 1)
    assert ack.result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED and ack.result_param2 == Reason.NO_SENSOR_DATA
    # DF data flowing: good and bad datagrams, each bad one counted by its reason
    t = app.clock.now()
    sent_good = 0
    for k in range(3):  # one scan per second of autopilot time, like a DF
        assert ap.wait_until(lambda s: app.clock.now() >= np.ceil(t) + k, 5)
        for ch in range(4):
            sock.sendto(dg.encode(np.ceil(t) + k, ch, [0.1 * ch]), ("127.0.0.1", app.sensor_port))
            sent_good += 1
    bad = [b"nope", json.dumps({"v": 1, "t": t, "ch": 7, "bearings_rad": []}).encode(),
           json.dumps({"v": 1, "t": t, "ch": 0, "bearings_rad": [9.0]}).encode(), b"x" * 5000]
    for b in bad:
        sock.sendto(b, ("127.0.0.1", app.sensor_port))
    assert ap.wait_until(lambda s: app.scans.accepted == sent_good and app.scans.rejected_total == 4, 10)
    assert {k: v for k, v in app.scans.rejected.items() if v} == {
        "not_json": 1, "unknown_channel": 1, "out_of_range": 1, "too_large": 1}
    # every good scan is used by a tick, or (the first tick sets up the solver: at 10x it
    # overruns) counted as skipped; none is half-used
    def accounted():
        used = [tk for tk in app.ticks if tk["channels"]]
        return sum(len(tk["channels"]) + 4 * tk["skipped_before"] for tk in used)
    assert ap.wait_until(lambda s: accounted() == sent_good, 10)
    assert all(tk["channels"] == [0, 1, 2, 3] for tk in app.ticks if tk["channels"])
    # start: accepted, takes GUIDED back from the pilot; a second start is a no-op
    n = len(gcs.msgs)
    accepted = app.scans.accepted
    for ch in range(4):  # a fresh scan: start needs DF data from the last 3 s
        sock.sendto(dg.encode(np.ceil(app.clock.now()), ch, []), ("127.0.0.1", app.sensor_port))
    assert wait_for(lambda: app.scans.accepted == accepted + 4, 5), app.scans.rejected
    ack = gcs.command(191, USER_1, 1)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED, (ack.result_param2, app.scans.rejected, list(app.events)[-3:])
    assert ap.wait_until(lambda s: s.mode == Mode.GUIDED, 5) and app.state == State.MONITORING
    assert gcs.command(191, USER_1, 1).result == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.command(191, USER_1, 2).result == mavlink.MAV_RESULT_ACCEPTED and app.state == State.PAUSED
    assert gcs.command(191, USER_1, 2).result == mavlink.MAV_RESULT_ACCEPTED
    texts = [m.text for m in gcs.msgs[n:] if m.get_type() == "STATUSTEXT"]
    assert sum("paused" in x for x in texts) == 1, texts  # done once
    assert gcs.command(191, USER_1, 4).result == mavlink.MAV_RESULT_ACCEPTED and app.state == State.IDLE
    # the app's heartbeat reports its state in custom_mode, as component 191
    hb = gcs.wait(lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 191
                  and m.custom_mode == State.IDLE, 5, n)
    assert hb is not None and hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert app.counters.get("io_errors", 0) == 0


def _warned(app, text):
    return any(text in e for _, e in list(app.events))


@pytest.mark.timeout(60)
def test_autopilot_speed_limits_are_read_and_a_slower_vehicle_is_reported(rig):
    """At connection the app reads WPNAV_SPEED / WPNAV_ACCEL. The mock's stock 10 m/s is half of
    the paper's 20 m steps per tick: one warning (the vehicle will lag the setpoints); the jump
    model assumes no acceleration limit, so none about that. A limit or PMON_REACH changed in
    flight is checked again."""
    ap, app, gcs, _ = rig
    wait_for(lambda: app.vehicle.speed_limit_mps is not None and app.vehicle.accel_limit_mps2 is not None, 5)
    assert app.vehicle.speed_limit_mps == pytest.approx(10.0)
    assert app.vehicle.accel_limit_mps2 == pytest.approx(2.5)
    assert _warned(app, "WPNAV_SPEED 10 m/s < 20 planned")
    assert not _warned(app, "WPNAV_ACCEL")
    # changed in flight, by the operator (PMON_REACH) or on the autopilot (WPNAV_SPEED, which
    # ArduPilot re-sends on every link): checked again, each new shortfall said once
    n = len(app.events)
    assert gcs.param_set("PMON_REACH", 10.0).param_value == 10.0
    assert gcs.param_set("PMON_REACH", 15.0).param_value == 15.0
    assert gcs.param_set("PMON_REACH", 15.0).param_value == 15.0
    told = [e for _, e in list(app.events)[n:] if "WPNAV_SPEED" in e]
    assert told == ["PMON: WPNAV_SPEED 10 m/s < 15 planned"]
    gcs.conn.mav.param_set_send(1, 1, b"WPNAV_SPEED", 1200.0, mavlink.MAV_PARAM_TYPE_REAL32)
    assert ap.wait_until(lambda s: _warned(app, "WPNAV_SPEED 12 m/s < 15 planned"), 5)
    gcs.conn.mav.param_set_send(1, 1, b"WPNAV_SPEED", 2000.0, mavlink.MAV_PARAM_TYPE_REAL32)
    assert ap.wait_until(lambda s: app.vehicle.speed_limit_mps == pytest.approx(20.0), 5)
    assert gcs.param_set("PMON_REACH", 20.0).param_value == 20.0
    told = [e for _, e in list(app.events)[n:] if "WPNAV_SPEED" in e]
    assert told == ["PMON: WPNAV_SPEED 10 m/s < 15 planned", "PMON: WPNAV_SPEED 12 m/s < 15 planned"]
    assert app.counters.get("io_errors", 0) == 0


@pytest.mark.timeout(60)
def test_vehicle_motion_plans_at_the_autopilots_limits_capped_by_the_airframes():
    """planning.motion: vehicle capped at 8 m/s, 5 m/s^2 and 5 m/s^3 (what the airframe flies)
    against an autopilot set to 20 m/s, 2.5 m/s^2 and PSC_JERK_XY 2 m/s^3: the planner flies at 8
    m/s, 2.5 m/s^2 and 2 m/s^3, says so to a ground station (on the autopilot's other link,
    connected before the app), warns of nothing (no plan is faster than the autopilot flies),
    follows a limit a ground station changes in flight, and says a jerk that is no limit (0)
    without planning with it."""
    from dataclasses import replace

    sc = with_policy(load_scenario("paper"), "paper")
    sc = replace(sc, planning=replace(sc.planning, motion="vehicle", speed_max_mps=8.0, accel_max_mps2=5.0,
                                      jerk_max_mps3=5.0))
    o = sc.origin
    ap = MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=10.0, endpoints=["tcpin:127.0.0.1:0"] * 2,
                       params={"WPNAV_SPEED": 2000, "WPNAV_ACCEL": 250, "PSC_JERK_XY": 2},
                       boot=BootTimeline.scaled(2.0)).start()
    gcs = Gcs(ap.port("tcpin", 1))
    app = None
    try:
        assert gcs.wait(lambda m: m.get_type() == "HEARTBEAT", 5) is not None
        app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{ap.port('tcpin', 0)}", sensor_port=0), sc).start()
        told = gcs.wait(lambda m: m.get_type() == "STATUSTEXT" and "planning at" in m.text
                        and "2.5 m/s^2, 2 m/s^3" in m.text, 10)
        assert told is not None and told.text == "PMON: planning at 8 m/s, 2.5 m/s^2, 2 m/s^3", told
        assert app.limits.planner == (8.0, 2.5, 2.0) and app.limits.warning is None and app.limits.warnings == 0
        with app.lock:
            motion = app.core.build_setup().motion
            assert (motion.speed_max_mps, motion.accel_max_mps2, motion.jerk_max_mps3) == (8.0, 2.5, 2.0)
            status = app._status()
            assert (status["jerk_limit_mps3"], status["jerk_plan_mps3"]) == (2.0, 2.0)
        since = len(gcs.msgs)
        assert gcs.param_set("WPNAV_SPEED", 500, comp=1) is not None  # the autopilot tells every link
        assert gcs.wait(lambda m: m.get_type() == "STATUSTEXT"
                        and m.text == "PMON: planning at 5 m/s, 2.5 m/s^2, 2 m/s^3", 10, since) is not None
        with app.lock:
            assert app.core.build_setup().motion.speed_max_mps == 5.0
        assert not any("WPNAV" in t for t in gcs.texts())  # no warning: plans never outrun the autopilot
        since = len(gcs.msgs)
        gcs.conn.mav.param_set_send(1, 1, b"PSC_JERK_XY", 0.0, mavlink.MAV_PARAM_TYPE_REAL32)
        told = gcs.wait(lambda m: m.get_type() == "STATUSTEXT" and "PSC_JERK_XY" in m.text, 10, since)
        assert told is not None and told.text.startswith("PMON: autopilot PSC_JERK_XY = 0 is no limit"), told
        with app.lock:
            assert app.core.build_setup().motion.jerk_max_mps3 == 2.0  # the last good one stays
        assert app.counters.get("io_errors", 0) == 0  # one limit known before the other: no handler error
    finally:
        gcs.close()
        if app is not None:
            app.stop()
        ap.stop()
