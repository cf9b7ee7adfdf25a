"""The mock autopilot against ArduPilot's own firmware, as the onboard app sees them: the same
procedure (``pmon run --auto-launch`` from the autopilot's boot, ``pmon feed live``, a stretch of
monitoring), flown once against each (sim/stack/procedure.py), and what the app received compared
message by message (``sim.stack.app_tlog.app_view``): the answer to every command it sent, the rates
of what it asked for, what came unasked, the boot (no fix, EKF origin, pre-arm, arming), the
take-off's landed states, the modes, and what the app itself said. A mock that passed where the
firmware fails, or the other way round, fails here.
"""
from __future__ import annotations

import pytest

from sim.firmware.ardupilot import skip_reason
from sim.stack.app_tlog import app_view
from sim.stack.procedure import Mission, MissionConfig

pytestmark = [pytest.mark.ardupilot, pytest.mark.sitl,
              pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")]

MONITOR_S = 30.0  # autopilot s of monitoring compared
ASKED = ("GLOBAL_POSITION_INT", "SYSTEM_TIME", "EXTENDED_SYS_STATE", "SYS_STATUS", "HEARTBEAT")


def _fly(kind: str, out) -> dict:
    # the paper's policy at ArduCopter's stock limits: its 20 m steps are faster than WPNAV_SPEED
    cfg = MissionConfig(autopilot=kind, speedup=3.0, auto_launch=True, feed_duration_s=MONITOR_S + 20, seed=3,
                        app_args=("--policy", "paper"))
    with Mission(cfg, out / kind) as m:
        assert m.wait(lambda o: o.app_state == "monitoring", 120, "monitoring"), m.app_log()[-2000:]
        m.sim_sleep(MONITOR_S)
        status = m.gcs("status")
    view = app_view(m.out / "app.tlog")
    view["crashes"] = m.autopilot_crashes()
    view["status"] = status
    return view


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    out = tmp_path_factory.mktemp("conformance")
    return {kind: _fly(kind, out) for kind in ("ardupilot", "mock")}


def test_every_command_the_app_sends_is_answered_alike(views):
    real, mock = views["ardupilot"]["acks"], views["mock"]["acks"]
    assert set(mock) == set(real), (mock, real)
    for cmd in real:
        # the arming is refused until the EKF is ready, by both; everything else accepted
        assert mock[cmd] == real[cmd], (cmd, mock[cmd], real[cmd])
    assert real["MAV_CMD_COMPONENT_ARM_DISARM"] == ["FAILED", "ACCEPTED"]
    assert views["ardupilot"]["crashes"] == 0 and views["mock"]["crashes"] == 0


def test_the_streams_the_app_asked_for_come_at_the_same_rates_and_nothing_else_unasked(views):
    real, mock = views["ardupilot"], views["mock"]
    assert real["monitoring_s"] >= MONITOR_S - 5 and mock["monitoring_s"] >= MONITOR_S - 5
    for name in ASKED:
        assert mock["rates_hz"].get(name, 0) == pytest.approx(real["rates_hz"].get(name, 0), rel=0.1), \
            (name, mock["rates_hz"], real["rates_hz"])
    assert set(mock["unasked"]) <= set(real["unasked"]), (mock["unasked"], real["unasked"])
    assert "GLOBAL_POSITION_INT" not in real["unasked"] and "EXTENDED_SYS_STATE" not in real["unasked"]


def test_the_boot_and_the_take_off_look_alike(views):
    real, mock = views["ardupilot"], views["mock"]
    for v in (real, mock):
        assert v["no_fix_positions"] > 0  # lat = lon = 0 before the GPS fix
        assert v["landed"] == ["ON_GROUND", "TAKEOFF", "IN_AIR"], v["landed"]
        assert v["prearm"][0] is False and v["prearm"][-1] is True, v["prearm"]
        assert v["modes"][:2] == [0, 4] and v["modes"][-1] == 4, v["modes"]  # STABILIZE, GUIDED
    assert mock["origin_t"] == pytest.approx(real["origin_t"], abs=2.0)
    assert mock["armed_t"] == pytest.approx(real["armed_t"], abs=3.0)


def test_the_speed_warning_reaches_a_ground_station_while_it_holds(views):
    for kind in ("ardupilot", "mock"):
        st = views[kind]["status"]
        assert st.rc == 0 and "WARNING   autopilot speed limit 10 m/s < 20 m/s planned" in st.stdout, st.stdout


def test_the_app_says_the_same_things_and_launches_in_the_same_steps(views):
    def said(v):  # guidance and DF messages depend on the targets, not on the autopilot
        return [s for s in v["app_said"] if not s.startswith(("T1 ", "T2 ", "T3 ", "T4 ", "DF ", "no DF"))]

    def steps(v):  # the launch, in order (other messages come as their replies happen to)
        return [s for s in said(v) if s.startswith(("launch", "monitoring"))]
    real, mock = views["ardupilot"], views["mock"]
    assert steps(mock) == steps(real), (steps(mock), steps(real))
    assert set(said(mock)) == set(said(real)), (said(mock), said(real))
    assert "launch: armed" in steps(real) and steps(real)[-1] == "monitoring started"
