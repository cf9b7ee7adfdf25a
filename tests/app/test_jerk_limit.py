"""The planner's jerk is the autopilot's own (ArduCopter's PSC_JERK_XY, capped as the firmware
caps it), read at connection with WPNAV_SPEED / WPNAV_ACCEL, capped by the scenario's
planning.jerk_max_mps3 (0 there: the acceleration steps, whatever the autopilot); PX4's OFFBOARD
shapes no jerk (onboard/app/autopilot/profiles.py). A value that is no limit is said and not used."""
from __future__ import annotations

import math
import time
from dataclasses import replace

import pytest

from onboard.app.mavlink2 import mavlink

from onboard.app.autopilot.profiles import ARDUPILOT, PX4, UNKNOWN, arducopter_jerk_xy
from onboard.app.app_config import AppConfig
from onboard.app.autopilot.side import AutopilotSide
from onboard.app.context import AppContext
from onboard.app.counters import Counters
from onboard.app.autopilot.plan_limits import PlanLimits
from onboard.app.autopilot.vehicle import Vehicle
from onboard.config import load_scenario
from onboard.policy import vehicle_motion, with_policy
from sim.mock.multicopter import limits_from_params

STOCK = {"WPNAV_SPEED": 1000.0, "WPNAV_ACCEL": 250.0, "PSC_JERK_XY": 5.0, "ATC_ACCEL_R_MAX": 110000.0,
         "ATC_ACCEL_P_MAX": 110000.0}


def test_ardupilots_jerk_is_psc_jerk_xy_capped_by_the_attitude_loop():
    """Stock: 5 (the attitude loop's cap, 0.5 sqrt(2.5 g 19.2 rad/s^2) = 10.8, does not bind); a
    slow-rolling copter (ATC_ACCEL_R_MAX 20000 cdeg/s^2) caps 5 at 0.5 sqrt(2.5 g 3.49) = 4.62;
    the demo's 20 at 0.5 sqrt(5 g 19.2) = 15.3. Until PSC_JERK_XY is read: none; until the caps'
    parameters are: PSC_JERK_XY alone. The simulated copter flies with the same figure."""
    assert ARDUPILOT.jerk_limit({}) is None and ARDUPILOT.jerk_limit({"WPNAV_ACCEL": 250.0}) is None
    assert ARDUPILOT.jerk_limit({"PSC_JERK_XY": 2.0}) == 2.0
    assert ARDUPILOT.jerk_limit(STOCK) == 5.0
    slow = {**STOCK, "ATC_ACCEL_R_MAX": 20000.0}
    assert ARDUPILOT.jerk_limit(slow) == pytest.approx(0.5 * math.sqrt(2.5 * 9.80665 * math.radians(200.0)))
    assert ARDUPILOT.jerk_limit(slow) == pytest.approx(4.625, abs=1e-3)
    demo = {**STOCK, "WPNAV_ACCEL": 500.0, "PSC_JERK_XY": 20.0}
    assert ARDUPILOT.jerk_limit(demo) == pytest.approx(15.34, abs=0.01)
    for params in (STOCK, slow, demo):
        assert ARDUPILOT.jerk_limit(params) == pytest.approx(limits_from_params(params).jerk_xy_max())
    assert arducopter_jerk_xy(7.0, 2.5, 0.0) == 7.0  # no angular acceleration limit: no cap
    assert ARDUPILOT.jerk_params == ("PSC_JERK_XY", "ATC_ACCEL_R_MAX", "ATC_ACCEL_P_MAX")


def test_px4_and_an_unknown_autopilot_shape_no_jerk():
    assert PX4.jerk_params == () and PX4.jerk_limit({"MPC_JERK_MAX": 8.0, "MPC_JERK_AUTO": 4.0}) is None
    assert UNKNOWN.jerk_params == () and UNKNOWN.jerk_limit(STOCK) is None


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 0.0, -5.0, 0.05, 5000.0])
def test_a_psc_jerk_xy_that_is_no_limit_is_refused(value):
    assert ARDUPILOT.limit_refusal("PSC_JERK_XY", value) is not None


def test_limits_that_are_limits_are_taken():
    for name, value in (("PSC_JERK_XY", 2.0), ("PSC_JERK_XY", 0.1), ("PSC_JERK_XY", 1000.0), ("WPNAV_ACCEL", 250.0),
                        ("WPNAV_SPEED", 5000.0), ("ATC_ACCEL_R_MAX", 110000.0)):
        assert ARDUPILOT.limit_refusal(name, value) is None, (name, value)
    for value in (math.nan, 0.0, -250.0):
        assert ARDUPILOT.limit_refusal("WPNAV_ACCEL", value) == "not a positive number"
        assert PX4.limit_refusal("MPC_ACC_HOR", value) == "not a positive number"


def test_the_planners_jerk_is_the_smaller_and_a_scenarios_zero_stays_zero():
    pl = with_policy(load_scenario("paper"), "flight").planning
    assert pl.jerk_max_mps3 == 5.0
    assert vehicle_motion(pl, 10.0, 2.5, 2.0).jerk_max_mps3 == 2.0
    assert vehicle_motion(pl, 10.0, 2.5, 20.0).jerk_max_mps3 == 5.0
    assert vehicle_motion(pl, 10.0, 2.5).jerk_max_mps3 == 5.0  # unknown: the scenario's
    steps = replace(pl, jerk_max_mps3=0.0)
    assert vehicle_motion(steps, 10.0, 2.5, 2.0).jerk_max_mps3 == 0.0


class _Events:
    def __init__(self):
        self.limits = 0

    def on_limits(self):
        self.limits += 1


def _side(profile=ARDUPILOT):
    said, events = [], _Events()
    vehicle = Vehicle(sysid=1, compid=1, profile=profile)
    ctx = AppContext(AppConfig(""), None, None, time.monotonic, None, Counters(),
                     lambda text, severity=None, once=None: said.append((text, once)), None)
    side = AutopilotSide(ctx, None, vehicle, events)
    return side, said, events


def _param(name: str, value: float):
    return mavlink.MAVLink_param_value_message(name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32, 100, 0)


def test_the_autopilot_side_reads_the_jerk_with_the_other_limits_and_says_a_bad_one():
    side, said, events = _side()
    for name in ("WPNAV_SPEED", "WPNAV_ACCEL", "PSC_JERK_XY"):
        side.on_param_value(_param(name, {"WPNAV_SPEED": 2000.0, "WPNAV_ACCEL": 250.0, "PSC_JERK_XY": 2.0}[name]))
    v = side.vehicle
    assert (v.speed_limit_mps, v.accel_limit_mps2, v.jerk_limit_mps3) == (20.0, 2.5, 2.0) and events.limits == 3
    side.on_param_value(_param("ATC_ACCEL_R_MAX", 20000.0))
    side.on_param_value(_param("ATC_ACCEL_P_MAX", 110000.0))
    assert v.jerk_limit_mps3 == 2.0  # the cap, 4.62, does not bind
    side.on_param_value(_param("PSC_JERK_XY", 8.0))
    assert v.jerk_limit_mps3 == pytest.approx(4.625, abs=1e-3)  # now it does
    assert said == []
    for bad in (math.nan, 0.0, -3.0, 1e6):
        side.on_param_value(_param("PSC_JERK_XY", bad))
    assert v.jerk_limit_mps3 == pytest.approx(4.625, abs=1e-3) and events.limits == 6  # the last good one stays
    texts = [t for t, _ in said]
    assert len(texts) == 4 and all(t.startswith("autopilot PSC_JERK_XY = ") and "no limit" in t for t in texts)
    assert "= nan is no limit (not a positive number)" in texts[0] and "outside 0.1-1000 m/s^3" in texts[3]
    side.on_param_value(_param("WPNAV_ACCEL", math.nan))  # the other limits alike
    assert v.accel_limit_mps2 == 2.5 and "autopilot WPNAV_ACCEL = nan is no limit" in said[-1][0]
    assert side.counters["limit_params_refused"] == 5


def test_a_bad_first_psc_jerk_xy_leaves_the_scenarios_jerk():
    side, said, _ = _side()
    side.on_param_value(_param("PSC_JERK_XY", -1.0))
    assert side.vehicle.jerk_limit_mps3 is None and len(said) == 1


def test_plan_limits_plan_at_the_autopilots_jerk_and_say_it():
    sc = with_policy(load_scenario("paper"), "flight")
    side, said, _ = _side()
    limits = PlanLimits(sc, None, side.vehicle, lambda text, *a, **k: said.append((text, None)))
    for name, value in (("WPNAV_SPEED", 1000.0), ("WPNAV_ACCEL", 250.0)):
        side.on_param_value(_param(name, value))
    limits.check()
    assert limits.planner == (9.0, 2.5, 5.0) and said[-1][0] == "planning at 9 m/s, 2.5 m/s^2, 5 m/s^3"
    side.on_param_value(_param("PSC_JERK_XY", 2.0))
    limits.check()
    assert limits.planner == limits.plan == (9.0, 2.5, 2.0) and said[-1][0] == "planning at 9 m/s, 2.5 m/s^2, 2 m/s^3"
    steps = replace(sc, planning=replace(sc.planning, jerk_max_mps3=0.0))
    limits = PlanLimits(steps, None, side.vehicle, lambda text, *a, **k: said.append((text, None)))
    limits.check()
    assert limits.planner == (9.0, 2.5, 0.0) and said[-1][0] == "planning at 9 m/s, 2.5 m/s^2, acceleration steps"


def test_an_angular_acceleration_limit_set_off_lifts_the_cap_and_is_no_refusal():
    """ATC_ACCEL_R_MAX = 0 is ArduCopter's "no angular acceleration limit" (the cap's is_positive
    fails): a setting, not a bad value, and the jerk is PSC_JERK_XY uncapped."""
    side, said, _ = _side()
    for name, value in (("WPNAV_ACCEL", 250.0), ("PSC_JERK_XY", 8.0), ("ATC_ACCEL_R_MAX", 20000.0),
                        ("ATC_ACCEL_P_MAX", 110000.0)):
        side.on_param_value(_param(name, value))
    assert side.vehicle.jerk_limit_mps3 == pytest.approx(4.625, abs=1e-3)
    side.on_param_value(_param("ATC_ACCEL_R_MAX", 0.0))
    assert side.vehicle.jerk_limit_mps3 == 8.0 and said == []
    side.on_param_value(_param("ATC_ACCEL_P_MAX", -1.0))  # negative is still no value
    assert side.vehicle.jerk_limit_mps3 == 8.0 and len(said) == 1
