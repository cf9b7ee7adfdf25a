"""PX4's events (EVENT, message 410) in words (onboard/app/autopilot/px4_events.py): frames recorded from
PX4 v1.16 SITL's offboard link (tests/data/px4_events.json), its build's metadata where it is
(../shared/px4/etc/extras/all_events.json.xz), and the app saying why PX4 refuses to arm."""
from __future__ import annotations

import json
import lzma
import time
from pathlib import Path

import pytest

from onboard.app.mavlink2 import mavlink, mavutil

from tests.support.app_helpers import wait_for

from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.autopilot.px4_events import EventMetadata, EventMetadataError, decode_event
from onboard.config import load_scenario
from onboard.policy import with_policy
from sim.firmware.px4 import find_sitl

FRAMES = json.loads((Path(__file__).resolve().parents[1] / "data" / "px4_events.json").read_text())["events"]
HOLD = (4 << 16) | (3 << 24)
OFFBOARD = 6 << 16


def _metadata_file() -> Path | None:
    folder = find_sitl()
    p = folder / "etc" / "extras" / "all_events.json.xz" if folder else None
    return p if p is not None and p.is_file() else None


META = _metadata_file()
needs_meta = pytest.mark.skipif(META is None, reason="no PX4 build with etc/extras/all_events.json.xz "
                                "($PMON_PX4_SITL or ../shared/px4)")


def unknown(frame_hex: str):
    """The frame as pymavlink 2.4.50 hands it to the app: an UNKNOWN_410 message."""
    mav = mavlink.MAVLink(None)
    msgs = mav.parse_buffer(bytes.fromhex(frame_hex))
    assert msgs and msgs[0].get_type() == "UNKNOWN_410"
    return msgs[0]


def test_recorded_frames_decode_by_common_xmls_layout():
    ev = decode_event(unknown(FRAMES[0]["frame"]))
    assert ev.id == 0x0102089D and ev.component == 1 and ev.sequence >= 0
    # a frame cut short, and a frame that is not an EVENT, are None (never an exception)
    m = unknown(FRAMES[0]["frame"])
    m._msgbuf = bytearray(bytes(m.get_msgbuf())[:9])
    assert decode_event(m) is None
    hb = mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3)
    hb.pack(mavlink.MAVLink(None))
    assert decode_event(hb) is None


@needs_meta
def test_every_recorded_event_reads_as_px4s_console_says_it():
    meta = EventMetadata.load(META)
    for f in FRAMES:
        d = meta.describe(decode_event(unknown(f["frame"])))
        assert d is not None and d.text == f["text"], f
    by_text = {f["text"]: meta.describe(decode_event(unknown(f["frame"]))) for f in FRAMES}
    gps = by_text["Navigation error: No valid global position estimate"]
    assert gps.group == "arming_check" and meta.blocks(gps, HOLD) and not meta.blocks(gps, OFFBOARD)
    off = by_text["No offboard signal"]
    assert meta.blocks(off, OFFBOARD) and not meta.blocks(off, HOLD)
    assert by_text["Arming check summary event"].summary


def test_unreadable_metadata_is_refused_in_one_line_naming_the_file(tmp_path):
    with pytest.raises(EventMetadataError, match="missing.json.xz: cannot read"):
        EventMetadata.load(tmp_path / "missing.json.xz")
    bad = tmp_path / "bad.json.xz"
    bad.write_bytes(lzma.compress(b"{not json"))
    with pytest.raises(EventMetadataError, match="bad.json.xz: cannot read PX4 event metadata"):
        EventMetadata.load(bad)
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({"components": {}}))
    with pytest.raises(EventMetadataError, match="no events in it"):
        EventMetadata.load(empty)


def _px4_peer(app):
    """A scripted PX4 on the app's link: heartbeat (Hold, disarmed), position, origin, pre-arm
    health bit set; every ARM answered TEMPORARILY_REJECTED followed by the recorded report."""
    url = f"udpout:127.0.0.1:{app.link.conn.port.getsockname()[1]}"
    px4 = mavutil.mavlink_connection(url, source_system=1, source_component=1, dialect="ardupilotmega")
    frames = [bytes.fromhex(f["frame"]) for f in FRAMES
              if f["text"] in ("Arming denied: Resolve system health failures first", "Arming check summary event",
                               "No offboard signal", "Navigation error: No valid global position estimate")]
    bit = mavlink.MAV_SYS_STATUS_PREARM_CHECK
    t0 = time.monotonic()

    def beat():
        tb = int((time.monotonic() - t0) * 1000) + 5000
        px4.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                               mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, HOLD, 3)
        px4.mav.sys_status_send(0, 0, bit, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
        px4.mav.global_position_int_send(tb, 351468000, 334126000, 160000, 0, 0, 0, 0, 0)
        px4.mav.gps_global_origin_send(351468000, 334126000, 160000, 0)
        px4.mav.extended_sys_state_send(0, mavlink.MAV_LANDED_STATE_ON_GROUND)
        for _ in range(20):
            m = px4.recv_match(type="COMMAND_LONG", blocking=False)
            if m is None:
                break
            if m.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                px4.mav.command_ack_send(m.command, mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
                for f in frames:
                    px4.write(f)
    return px4, beat


@pytest.mark.timeout(60)
@pytest.mark.parametrize("with_meta", [True, False])
def test_the_launch_says_why_px4_refuses_to_arm(with_meta):
    """With the build's metadata the launch names the check that blocks arming in the vehicle's
    mode (Hold: the global position, not the offboard signal that blocks OFFBOARD only); without
    it, that PX4 refused and where to look."""
    if with_meta and META is None:
        pytest.skip("no PX4 event metadata here")
    cfg = AppConfig("udpin:127.0.0.1:0", sensor_port=0, auto_launch=True,
                    px4_events_path=str(META) if with_meta else None)
    app = OnboardApp(cfg, with_policy(load_scenario("paper"), "paper")).start()
    px4, beat = _px4_peer(app)
    want = ("launch: arming refused: PX4 check: Navigation error: No valid global position estimate" if with_meta
            else "launch: arming refused: refused by PX4 (see its console / events)")
    try:
        def said():
            beat()
            return any(want in text for _, text in list(app.events))
        assert wait_for(said, 30, poll_s=0.1), list(app.events)
    finally:
        px4.close()
        app.stop()
