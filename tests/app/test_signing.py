"""Who may talk to the app (issue 7, part 3-4): MAVLink 2 signing end to end, the ground-station
system-id allow list, and malformed / unknown / foreign MAVLink traffic. Real loopback sockets.
"""
from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

from onboard.app.mavlink2 import mavlink, mavutil
from sim.mock.autopilot import BootTimeline, MockAutopilot

from onboard.app import signing
from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.config import load_scenario
from onboard.policy import with_policy

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(120)]


# ----------------------------------------------------------------------------- key files
def test_key_file_rules(tmp_path):
    good = tmp_path / "good.key"
    key = signing.make_key_file(good)
    assert oct(os.stat(good).st_mode & 0o777) == "0o600" and signing.load_key(good) == key
    with pytest.raises(FileExistsError):
        signing.make_key_file(good)  # never overwrites a key
    wide = tmp_path / "wide.key"
    wide.write_text(key.hex())
    os.chmod(wide, 0o644)
    with pytest.raises(signing.KeyFileError, match="group/others.*chmod 600"):
        signing.load_key(wide)
    for name, text in (("short", "ab" * 16), ("nothex", "zz" * 32), ("zero", "00" * 32)):
        p = tmp_path / name
        p.write_text(text)
        os.chmod(p, 0o600)
        with pytest.raises(signing.KeyFileError, match=name if name == "zero" else str(p)):
            signing.load_key(p)
    with pytest.raises(signing.KeyFileError, match="cannot read"):
        signing.load_key(tmp_path / "missing.key")


def test_an_autopilot_that_cannot_sign_is_heard_unsigned_and_no_one_else(tmp_path):
    """PX4 v1.16 signs nothing: with ``unsigned_from`` its own packets (1/1) are taken unsigned,
    while a ground station's still need the key, whatever path they take (PX4 forwards them with
    their signature block rewritten, so they fail: tests/firmware/test_px4.py measures it)."""
    key = bytes(range(1, 33))
    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True  # as the app's link: a refused packet is BAD_DATA, not an exception
    signing.configure(rx, key, 1, unsigned_from=((1, 1),))

    def frame(sysid, compid, key_=None):
        tx = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if key_ is not None:
            signing.configure(tx, key_, 2)
        return mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3).pack(tx)

    def heard(buf) -> bool:
        return [m.get_type() for m in rx.parse_buffer(buf) or []] == ["HEARTBEAT"]
    assert heard(frame(1, 1))  # the autopilot, unsigned
    assert not heard(frame(255, 190)) and not heard(frame(1, 2))  # anyone else, unsigned
    assert heard(frame(255, 190, key)) and not heard(frame(255, 191, bytes(32 * [7])))  # signed: by the key
    plain = mavlink.MAVLink(None)
    plain.robust_parsing = True
    signing.configure(plain, key, 1)
    assert [m.get_type() for m in plain.parse_buffer(frame(1, 1)) or []] != ["HEARTBEAT"]  # not without it


def test_pmon_run_refuses_unsafe_key_bad_config_and_bad_args(tmp_path):
    wide = tmp_path / "k"
    wide.write_text("11" * 32)
    os.chmod(wide, 0o644)
    bad_yaml = tmp_path / "bad.yaml"
    paper = (Path(__file__).resolve().parents[2] / "config" / "paper.yaml").read_text()
    # a combination error: the goal region's centre inside obstacle O1
    bad_yaml.write_text(paper.replace("center_m: [550.0, 150.0, 0.0]", "center_m: [400.0, 600.0, 0.0]"))
    cases = [
        (["--signing-key", str(wide)], "readable or writable by group/others"),
        (["--scenario", str(bad_yaml)], "goals[0].center_m: inside obstacle 'O1'"),
        (["--gcs-sysid", "0"], "argument --gcs-sysid: must be in 1..255"),
        (["--df", "nowhere"], "argument --df: want HOST:PORT"),
        (["--param", "PMON_NOPE=1"], "unknown parameter"),
        (["--param", "PMON_ALT=5000"], "out of range"),
    ]
    for extra, msg in cases:
        r = subprocess.run([sys.executable, "-m", "onboard.cli", "run", "--mavlink", "udpin:127.0.0.1:0",
                            "--df", "127.0.0.1:0", *extra],
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 2, (extra, r.stdout, r.stderr)
        assert msg in r.stderr and "Traceback" not in r.stderr, (extra, r.stderr)


# ----------------------------------------------------------------------------- end to end
class Client:
    """A MAVLink client on its own TCP link to the mock autopilot (optionally signing)."""

    def __init__(self, port: int, sysid: int, key: bytes | None = None, link_id: int = 7):
        self.conn = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=sysid,
                                               source_component=190, dialect="ardupilotmega")
        if key is not None:
            signing.apply(self.conn, key, link_id)

    def drain(self, seconds: float, want=None):
        out, deadline = [], time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            m = self.conn.recv_match(blocking=True, timeout=0.1)
            if m is not None and m.get_type() != "BAD_DATA":
                out.append(m)
                if want is not None and want(m):
                    return out
        return out

    def param_set(self, name: str, value: float):
        self.conn.mav.param_set_send(1, 191, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32)

    def close(self):
        self.conn.close()


@pytest.fixture()
def signed_world(tmp_path):
    key_path = tmp_path / "pmon.key"
    key = signing.make_key_file(key_path)
    sc = with_policy(load_scenario("paper"), "paper")
    o = sc.origin
    ap = MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=2.0, signing_key=key,
                       endpoints=["tcpin:127.0.0.1:0"] * 4, boot=BootTimeline.scaled(2.0)).start()
    app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{ap.port('tcpin', 0)}", sensor_port=0,
                               signing_key_path=str(key_path)), sc).start()
    clients = []
    try:
        assert ap.wait_until(lambda s: app.vehicle.sysid == 1, 20), "signed app must find the signed autopilot"
        yield ap, app, key, clients
    finally:
        for c in clients:
            c.close()
        app.stop()
        ap.stop()


def test_signed_gcs_commands_the_app_unsigned_and_wrongly_signed_are_rejected_and_counted(signed_world):
    ap, app, key, clients = signed_world
    assert app.signing_counts()["goodsig"] > 0 and app.link.signing
    ok = Client(ap.port("tcpin", 1), 255, key)
    unsigned = Client(ap.port("tcpin", 2), 255, None)
    forged = Client(ap.port("tcpin", 3), 255, os.urandom(32))
    clients += [ok, unsigned, forged]
    for c in clients:
        c.drain(0.3)
    rejected0 = ap.counters().get("signing_rejected", 0)
    # parameter writes: only the signed one lands
    unsigned.param_set("PMON_CLUTTER", 3.0)
    forged.param_set("PMON_CLUTTER", 4.0)
    unsigned.conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 2989, 0, 0, 0, 0, 0)
    forged.conn.mav.command_long_send(1, 191, mavlink.MAV_CMD_USER_1, 0, 5, 0, 0, 0, 0, 0, 0)
    unsigned.drain(1.0)
    forged.drain(0.5)
    assert app.params["PMON_CLUTTER"] == 1.0
    assert not ap.state().armed, "an unsigned force-arm must not arm the vehicle"
    assert app.machine.launch is None, "a forged launch must not start"
    got = ok.drain(5.0, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "PMON_CLUTTER"
                   and abs(m.param_value - 2.0) < 1e-6) if ok.param_set("PMON_CLUTTER", 2.0) is None else []
    assert got and app.params["PMON_CLUTTER"] == 2.0
    assert ap.counters().get("signing_rejected", 0) - rejected0 >= 4, ap.counters()


def test_app_with_the_wrong_key_hears_nothing_and_sends_nothing_accepted(tmp_path):
    k1, k2 = tmp_path / "a.key", tmp_path / "b.key"
    signing.make_key_file(k1)
    key2 = signing.make_key_file(k2)
    sc = with_policy(load_scenario("paper"), "paper")
    ap = MockAutopilot(speedup=2.0, signing_key=key2, endpoints=["tcpin:127.0.0.1:0"],
                       boot=BootTimeline.scaled(2.0)).start()
    app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{ap.port('tcpin', 0)}", sensor_port=0,
                               signing_key_path=str(k1)), sc).start()
    try:
        time.sleep(2.0)
        assert app.vehicle.sysid is None
        assert app.signing_counts()["rejected"] > 0 and app.counters.get("mavlink_bad_data", 0) > 0
        # it never found its autopilot, so it never spoke (nothing to reject on the other side)
        assert app.link.sent == 0 and ap.counters().get("rx", 0) == 0
    finally:
        app.stop()
        ap.stop()


# ----------------------------------------------------------------------------- allow list + bad MAVLink
def _frame(msgid: int, payload: bytes, sysid: int = 1, compid: int = 1, seq: int = 0, crc_ok: bool = True) -> bytes:
    """A raw MAVLink 2 frame (for message ids pymavlink would not build)."""
    hdr = struct.pack("<BBBBBBBHB", 0xFD, len(payload), 0, 0, seq, sysid, compid, msgid & 0xFFFF, msgid >> 16)
    from pymavlink.generator.mavcrc import x25crc
    crc = x25crc(hdr[1:] + payload)
    extra = mavlink.mavlink_map[msgid].crc_extra if msgid in mavlink.mavlink_map else 0
    crc.accumulate(struct.pack("B", extra))
    return hdr + payload + struct.pack("<H", crc.crc ^ (0 if crc_ok else 0xBEEF))


def test_commands_only_from_configured_gcs_and_bad_mavlink_never_hurts():
    """The app listens on udpin; this test is its autopilot and, on the same port, every kind of
    bad or foreign traffic. The app keeps answering the allowed ground station throughout."""
    sc = with_policy(load_scenario("paper"), "paper")
    app = OnboardApp(AppConfig("udpin:127.0.0.1:0", sensor_port=0, gcs_sysids=(255, 250)), sc).start()
    port = app.link.conn.port.getsockname()[1]
    ap = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1,
                                    dialect="ardupilotmega")
    raw = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        def autopilot_hb():
            ap.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                  mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 0, mavlink.MAV_STATE_STANDBY)
        for _ in range(20):
            autopilot_hb()
            time.sleep(0.02)
            if app.vehicle.sysid == 1:
                break
        assert app.vehicle.sysid == 1
        # a stranger (sysid 66) and a foreign autopilot (sysid 9) try to command the app
        stranger = mavlink.MAVLink(None, srcSystem=66, srcComponent=190)
        pkt = stranger.param_set_encode(1, 191, b"PMON_PD", 0.5, mavlink.MAV_PARAM_TYPE_REAL32).pack(stranger)
        raw.sendto(pkt, ("127.0.0.1", port))
        cmd = stranger.command_long_encode(1, 191, mavlink.MAV_CMD_USER_1, 0, 5, 0, 0, 0, 0, 0, 0).pack(stranger)
        raw.sendto(cmd, ("127.0.0.1", port))
        other_ap = mavlink.MAVLink(None, srcSystem=9, srcComponent=1)
        raw.sendto(other_ap.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                             0, 5, 0).pack(other_ap), ("127.0.0.1", port))
        # garbage: random bytes, truncated frames, bad CRCs, unknown message ids, a flood
        rng = __import__("random").Random(1)
        good_hb = ap.mav.heartbeat_encode(2, 3, 0, 0, 0).pack(ap.mav)
        for i in range(3000):
            kind = i % 5
            if kind == 0:
                data = bytes(rng.randrange(256) for _ in range(rng.randint(1, 300)))
            elif kind == 1:
                data = good_hb[:rng.randint(1, len(good_hb) - 1)]
            elif kind == 2:
                data = _frame(0, b"\x00" * 9, crc_ok=False)
            elif kind == 3:
                data = _frame(rng.choice([4242, 60000, 0xFFFFFF]), os.urandom(rng.randint(0, 40)))
            else:
                data = b"\xfd" * rng.randint(1, 400)
            raw.sendto(data, ("127.0.0.1", port))
            if i % 100 == 99:
                autopilot_hb()
                time.sleep(0.003)
        time.sleep(0.5)
        assert app.params["PMON_PD"] == pytest.approx(sc.sensor.p_detect)
        assert app.machine.launch is None
        assert app.counters.get("rejected_sysid", 0) == 2
        assert app.vehicle.sysid == 1, "a second autopilot does not take over"
        assert app.counters.get("mavlink_bad_data", 0) > 100
        assert app.counters.get("io_errors", 0) == 0
        assert all(th.is_alive() for th in app._threads)
        # the allowed ground station (sysid 250 here) is still obeyed
        gcs = mavlink.MAVLink(None, srcSystem=250, srcComponent=190)
        raw.sendto(gcs.param_set_encode(1, 191, b"PMON_PD", 0.8, mavlink.MAV_PARAM_TYPE_REAL32).pack(gcs),
                   ("127.0.0.1", port))
        deadline = time.monotonic() + 5
        while app.params["PMON_PD"] != pytest.approx(0.8) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert app.params["PMON_PD"] == pytest.approx(0.8)
    finally:
        raw.close()
        ap.close()
        app.stop()
