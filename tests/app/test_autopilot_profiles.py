"""The autopilot seam (onboard/app/autopilot/profiles.py): what differs between firmwares comes
from the profile HEARTBEAT.autopilot picks, and the app uses the profile it picked."""
from __future__ import annotations

import math
import time

import pytest

from onboard.app.mavlink2 import mavlink, mavutil

from tests.support.app_helpers import wait_for

from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.autopilot.profiles import ARDUPILOT, PX4, UNKNOWN, profile_for
from onboard.app.autopilot.clock import ManualClock
from onboard.config import load_scenario
from onboard.policy import with_policy

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
    assert not PX4.in_mission_mode(PX4_HOLD) and PX4.mode_name(PX4_HOLD) == "AUTO.LOITER"
    assert PX4.mode_number("OFFBOARD") == PX4_OFFBOARD and PX4.mode_number("GUIDED") is None
    assert PX4.set_mode_params("offboard") == (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 6.0, 0.0)
    assert PX4.takeoff_params(35.0, 33.0, 90.0, 40.0, 160.0)[6] == 200.0
    assert [n for n, _ in PX4.limit_params] == ["MPC_XY_VEL_MAX", "MPC_ACC_HOR"]


def test_px4_mode_names_both_ways_and_the_modes_it_lacks_said_plainly():
    """PX4's own names and the everyday ones map to its main/sub modes; ArduCopter's names that
    PX4 has no mode for are refused with what to use instead (LOITER = 5 would be PX4's ACRO,
    BRAKE = 17 is ACKed and does nothing, GUIDED = 4 is AUTO.MISSION: measured on v1.16)."""
    for name in ("hold", "HOLD", "loiter", "AUTO.LOITER"):
        assert PX4.mode_number(name) == PX4_HOLD and PX4.set_mode_params(name)[1:] == (4.0, 3.0)
    assert PX4.mode_name(3 << 16) == "POSCTL" and PX4.mode_number("position") == 3 << 16
    assert PX4.mode_name((4 << 16) | (2 << 24)) == "AUTO.TAKEOFF" and PX4.mode_name(PX4_OFFBOARD) == "OFFBOARD"
    assert PX4.mode_name((4 << 16) | (11 << 24)) == "PX4 mode 4.11"  # unknown sub mode: its numbers
    assert PX4.hold_mode == "AUTO.LOITER" and ARDUPILOT.hold_mode == "BRAKE"
    assert PX4.no_mode("brake") == "PX4 has no mode BRAKE: use AUTO.LOITER (Hold; pmon gcs hold)"
    assert "the app flies OFFBOARD" in PX4.no_mode("GUIDED")
    with pytest.raises(ValueError, match="PX4 has no mode BRAKE"):
        PX4.set_mode_params("BRAKE")
    assert ARDUPILOT.no_mode("OFFBOARD").startswith("ArduPilot has no mode OFFBOARD (its modes: ")
    # the launch: PX4 arms in Hold, its take-off mode is its own; ArduCopter's is GUIDED
    assert PX4.in_launch_mode(PX4_HOLD) and not PX4.in_launch_mode((4 << 16) | (2 << 24))
    assert PX4.in_launch_mode((4 << 16) | (2 << 24), own=True) and not PX4.in_launch_mode(3 << 16, own=True)
    assert ARDUPILOT.in_launch_mode(4) and not ARDUPILOT.in_launch_mode(5, own=True)


def test_prearm_state_from_sys_status():
    bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
    msg = mavlink.MAVLink_sys_status_message(bit, bit, bit, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    assert ARDUPILOT.prearm_ok(msg) is True
    msg.onboard_control_sensors_health = 0
    assert ARDUPILOT.prearm_ok(msg) is False
    msg.onboard_control_sensors_present = 0  # as PX4 leaves it: ArduPilot's reading says "not reported"
    assert ARDUPILOT.prearm_ok(msg) is None and ARDUPILOT.prearm_ok(None) is None
    # PX4 v1.16 sets the health bit (not the present bit) when it can arm
    assert PX4.prearm_ok(msg) is False
    msg.onboard_control_sensors_health = bit
    assert PX4.prearm_ok(msg) is True and PX4.prearm_ok(None) is None


def test_px4_sends_integer_parameters_bytewise_and_com_obl_rc_act_is_checked():
    """COM_OBL_RC_ACT 5 arrives as the float whose bytes are the int 5 (7e-45); ArduPilot sends
    the value itself whatever its type."""
    import struct
    as_bytes = struct.unpack("<f", struct.pack("<i", 5))[0]
    msg = mavlink.MAVLink_param_value_message(b"COM_OBL_RC_ACT", as_bytes, mavlink.MAV_PARAM_TYPE_INT32, 1, 0)
    assert PX4.param_value(msg) == 5.0 and ARDUPILOT.param_value(msg) == pytest.approx(7e-45, rel=0.1)
    msg = mavlink.MAVLink_param_value_message(b"MPC_XY_VEL_MAX", 12.0, mavlink.MAV_PARAM_TYPE_REAL32, 1, 0)
    assert PX4.param_value(msg) == 12.0
    assert PX4.param_warning("COM_OBL_RC_ACT", 5) is None
    for bad in (0, 1, 2):  # PX4's default 0 is Position mode: with no RC it sinks (measured: 22 m in 20 s)
        assert "set 5 (Hold)" in PX4.param_warning("COM_OBL_RC_ACT", bad)
    assert PX4.checked_params == ("COM_OBL_RC_ACT",) and ARDUPILOT.checked_params == ()


@pytest.mark.timeout(30)
def test_the_app_flies_by_the_profile_its_autopilot_announced():
    """A PX4 heartbeat: the app reads PX4's limit parameters and counts OFFBOARD as its mode."""
    app = OnboardApp(AppConfig("udpin:127.0.0.1:0", sensor_port=0), with_policy(load_scenario("paper"), "paper"),
                     clock=ManualClock(10.0)).start()
    url = f"udpout:127.0.0.1:{app.link.conn.port.getsockname()[1]}"
    px4 = mavutil.mavlink_connection(url, source_system=1, source_component=1, dialect="ardupilotmega")
    try:
        asked = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and len(asked) < 3:
            px4.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                                   mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, PX4_OFFBOARD, 0)
            m = px4.recv_match(type="PARAM_REQUEST_READ", blocking=True, timeout=0.2)
            if m is not None:
                asked.append(m.param_id)
        assert asked == ["MPC_XY_VEL_MAX", "MPC_ACC_HOR", "COM_OBL_RC_ACT"]
        assert wait_for(lambda: app.vehicle.profile is PX4 and app.vehicle.in_mission_mode(), 5)
    finally:
        px4.close()
        app.stop()
