"""The autopilot seam (onboard/app/autopilot_profiles.py): what differs between firmwares comes
from the profile HEARTBEAT.autopilot picks, and the app uses the profile it picked."""
from __future__ import annotations

import math
import time

import pytest

from sim.autopilot import MockAutopilot  # noqa: F401  (sets MAVLINK20 before pymavlink)
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from app_helpers import wait_for

from onboard.app.app import AppConfig, OnboardApp
from onboard.app.autopilot_profiles import ARDUPILOT, PX4, UNKNOWN, profile_for
from onboard.app.clock import ManualClock
from onboard.config import load_scenario

PX4_HOLD = (4 << 16) | (3 << 24)  # AUTO / LOITER
PX4_OFFBOARD = 6 << 16


def test_the_heartbeats_autopilot_type_picks_the_profile():
    assert profile_for(mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA) is ARDUPILOT
    assert profile_for(mavlink.MAV_AUTOPILOT_PX4) is PX4
    assert profile_for(mavlink.MAV_AUTOPILOT_GENERIC) is UNKNOWN and UNKNOWN.limit_params == ()


def test_ardupilot_modes_takeoff_and_limits():
    assert ARDUPILOT.mission_mode == "GUIDED" and ARDUPILOT.in_mission_mode(4)
    assert not ARDUPILOT.in_mission_mode(5) and not ARDUPILOT.in_mission_mode(None)
    assert ARDUPILOT.set_mode_params("guided") == (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4.0)
    assert ARDUPILOT.mode_name(17) == "BRAKE" and ARDUPILOT.mode_number("loiter") == 5
    assert [n for n, _ in ARDUPILOT.limit_params] == ["WPNAV_SPEED", "WPNAV_ACCEL"]
    p = ARDUPILOT.takeoff_params(35.0, 33.0, None, 40.0, 160.0)
    assert p[3] == 0.0 and p[4:] == (35.0, 33.0, 40.0)  # above home; unknown heading sent as 0
    with pytest.raises(ValueError, match="finite"):
        ARDUPILOT.takeoff_params(math.nan, 33.0, 90.0, 40.0, 160.0)
    with pytest.raises(ValueError, match="no mode"):
        ARDUPILOT.set_mode_params("OFFBOARD")


def test_px4_modes_are_main_and_sub_modes_and_its_takeoff_is_amsl():
    assert PX4.mission_mode == "OFFBOARD" and PX4.in_mission_mode(PX4_OFFBOARD)
    assert not PX4.in_mission_mode(PX4_HOLD) and PX4.mode_name(PX4_HOLD) == "LOITER"
    assert PX4.mode_number("OFFBOARD") == PX4_OFFBOARD and PX4.mode_number("GUIDED") is None
    assert PX4.set_mode_params("offboard") == (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6.0, 0.0)
    assert PX4.takeoff_params(35.0, 33.0, 90.0, 40.0, 160.0)[6] == 200.0
    assert [n for n, _ in PX4.limit_params] == ["MPC_XY_CRUISE", "MPC_ACC_HOR"]


def test_prearm_state_from_sys_status():
    bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
    msg = mavlink.MAVLink_sys_status_message(bit, bit, bit, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    assert ARDUPILOT.prearm_ok(msg) is True
    msg.onboard_control_sensors_health = 0
    assert ARDUPILOT.prearm_ok(msg) is False
    msg.onboard_control_sensors_present = 0  # as PX4 leaves it: not reported
    assert PX4.prearm_ok(msg) is None and ARDUPILOT.prearm_ok(None) is None


@pytest.mark.timeout(30)
def test_the_app_flies_by_the_profile_its_autopilot_announced():
    """A PX4 heartbeat: the app reads PX4's limit parameters and counts OFFBOARD as its mode."""
    app = OnboardApp(AppConfig("udpin:127.0.0.1:0", sensor_port=0), load_scenario("paper"),
                     clock=ManualClock(10.0)).start()
    url = f"udpout:127.0.0.1:{app.link.conn.port.getsockname()[1]}"
    px4 = mavutil.mavlink_connection(url, source_system=1, source_component=1, dialect="ardupilotmega")
    try:
        asked = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and len(asked) < 2:
            px4.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                   mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PX4_OFFBOARD, 0)
            m = px4.recv_match(type="PARAM_REQUEST_READ", blocking=True, timeout=0.2)
            if m is not None:
                asked.append(m.param_id)
        assert asked == ["MPC_XY_CRUISE", "MPC_ACC_HOR"]
        assert wait_for(lambda: app.vehicle.profile is PX4 and app.vehicle.in_mission_mode(), 5)
    finally:
        px4.close()
        app.stop()
