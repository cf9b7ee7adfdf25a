"""Signing holds against a forged timestamp (issue 23, part 2): verify, then store.

pymavlink 2.4.50 stores a stream's timestamp before it checks the signature, so one packet with
a wrong signature and a timestamp near 2^48 makes every genuine packet of that stream "old".
onboard/app/signing.py's ``check_signature`` (bound by ``configure``) checks first. Shown:

  * against pymavlink's own signing, no sockets: frames pymavlink signs are accepted; on a
    stream of correctly signed frames (fresh, replayed, reordered, new streams from the past)
    its verdicts are pymavlink's, frame by frame; after forged frames on every link id, every
    genuine frame is still accepted, while pymavlink's own check rejects them all (the test
    fails on the old code);
  * over real UDP sockets, a hostile peer sending the forgeries (every link id, the genuine
    sender's system and component ids, a timestamp of 2^48 - 1) into a signed link of the
    onboard app (posing as the autopilot), of the ground station (posing as the vehicle) and
    of the mock autopilot (posing as the ground station): afterwards 0 genuine packets are
    rejected (bad signatures counted = forgeries sent) and the link works on.
"""
from __future__ import annotations

import os
import random
import socket
import time

import pytest

from onboard.app.mavlink2 import mavlink, mavutil
from sim.mock.autopilot import MockAutopilot

from tests.support.app_helpers import wait_for

from groundstation.gcs_link import GcsLink
from onboard.app import signing
from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.config import load_scenario
from onboard.policy import with_policy

FAR_FUTURE = (1 << 48) - 1


def signer(key: bytes, link_id: int, sysid: int = 1, compid: int = 1, timestamp: int | None = None):
    """A pymavlink encoder that signs the way pymavlink does (its own MAVLinkSigning)."""
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    mav.signing.secret_key = key
    mav.signing.link_id = link_id
    mav.signing.sign_outgoing = True
    mav.signing.timestamp = signing.timestamp_now() if timestamp is None else timestamp
    return mav


def heartbeat(mav) -> bytes:
    return bytes(mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                      mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4, 4).pack(mav))


def forgeries(sysid: int, compid: int) -> list[bytes]:
    """One HEARTBEAT per link id, signed with a random key, timestamp 2^48 - 1: CRC good, signature bad."""
    out = []
    for link_id in range(256):
        out.append(heartbeat(signer(os.urandom(32), link_id, sysid, compid, FAR_FUTURE)))
    return out


def receivers(key: bytes):
    """(pymavlink's own check, ours): two parsers with the same key and timestamp."""
    ours = mavlink.MAVLink(None)
    ours.robust_parsing = True
    signing.configure(ours, key, link_id=9, sign_outgoing=False)
    stock = mavlink.MAVLink(None)
    stock.robust_parsing = True
    stock.signing.secret_key = key
    stock.signing.timestamp = ours.signing.timestamp
    stock.signing.allow_unsigned_callback = lambda mav, msg_id: msg_id in signing.ALLOW_UNSIGNED
    assert "check_signature" not in vars(stock) and "check_signature" in vars(ours)
    return stock, ours


def accepted(rx, frame: bytes) -> bool:
    msgs = rx.parse_buffer(frame) or []
    assert len(msgs) == 1
    return msgs[0].get_type() != "BAD_DATA"


# ----------------------------------------------------------------------------- no sockets
def test_verdicts_are_pymavlinks_on_correctly_signed_frames():
    key = os.urandom(32)
    stock, ours = receivers(key)
    rng = random.Random(5)
    now = stock.signing.timestamp
    senders = [signer(key, 1, 1, 1), signer(key, 2, 1, 1), signer(key, 1, 255, 190),
               signer(key, 3, 1, 191, now - 2 * 6000 * 1000)]  # a new stream 2 minutes behind: refused
    sent: list[bytes] = []
    verdicts = {True: 0, False: 0}
    for _ in range(3000):
        r = rng.random()
        if r < 0.6 or not sent:
            frame = heartbeat(rng.choice(senders))
        elif r < 0.8:
            frame = rng.choice(sent)  # a replay
        else:
            frame = sent[-rng.randint(1, min(5, len(sent)))]  # reordered: an earlier one again
        sent.append(frame)
        a, b = accepted(stock, frame), accepted(ours, frame)
        assert a == b, "our check disagrees with pymavlink's on a correctly signed frame"
        verdicts[a] += 1
    assert verdicts[True] > 1000 and verdicts[False] > 500, verdicts
    assert ours.signing.stream_timestamps == stock.signing.stream_timestamps
    assert ours.signing.timestamp == stock.signing.timestamp


def test_forged_timestamp_on_every_link_id_rejects_no_genuine_frame_afterwards():
    key = os.urandom(32)
    stock, ours = receivers(key)
    genuine = signer(key, 7)
    for rx in (stock, ours):
        assert accepted(rx, heartbeat(genuine))  # the stream exists before the attack
    for frame in forgeries(1, 1):
        assert not accepted(ours, frame) and not accepted(stock, frame)
    after = [heartbeat(genuine) for _ in range(100)]
    assert sum(accepted(ours, f) for f in after) == 100
    assert ours.signing.stream_timestamps[(7, 1, 1)] < FAR_FUTURE
    assert ours.signing.timestamp < FAR_FUTURE, "our own timestamp was not dragged along"
    # pymavlink's own check stored 2^48 - 1 for the stream: it rejects them all
    assert sum(accepted(stock, f) for f in after) == 0
    assert stock.signing.stream_timestamps[(7, 1, 1)] == FAR_FUTURE


# ----------------------------------------------------------------------------- real sockets


def _send_all(port: int, frames: list[bytes], between=lambda: time.sleep(0.01)) -> None:
    """The hostile peer: every frame from its own socket, in chunks of 32 (``between`` them: the
    receiver's socket buffer holds ~250 small datagrams; a lost forgery would look like a
    genuine packet rejected in the counts)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for i, f in enumerate(frames):
            s.sendto(f, ("127.0.0.1", port))
            if i % 32 == 31:
                between()
    finally:
        s.close()


@pytest.fixture()
def key_file(tmp_path):
    path = tmp_path / "pmon.key"
    return path, signing.make_key_file(path)


@pytest.mark.sitl
@pytest.mark.timeout(120)
def test_app_keeps_its_autopilot_after_forged_autopilot_packets(key_file):
    path, key = key_file
    sc = with_policy(load_scenario("paper"), "paper")
    o = sc.origin
    app = OnboardApp(AppConfig("udpin:127.0.0.1:0", sensor_port=0, signing_key_path=str(path),
                               link_timeout_s=1.0), sc).start()
    port = app.link.conn.port.getsockname()[1]
    ap = MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=2.0, signing_key=key,
                       endpoints=[f"udpout:127.0.0.1:{port}"]).start()
    try:
        assert wait_for(lambda: app.vehicle.sysid == 1 and app.signing_counts()["goodsig"] > 20, 20)
        before = app.signing_counts()
        frames = forgeries(1, 1)
        _send_all(port, frames)
        assert wait_for(lambda: app.signing_counts()["badsig"] - before["badsig"] >= len(frames), 10)
        mid = app.signing_counts()
        time.sleep(3.0)  # 3 link timeouts
        after = app.signing_counts()
        assert after["badsig"] - before["badsig"] == len(frames), "a genuine packet was rejected"
        assert after["goodsig"] - mid["goodsig"] > 40, (mid, after)
        assert app.counters.get("link_losses", 0) == 0 and not app.autopilot.link_lost
    finally:
        app.stop()
        ap.stop()


@pytest.mark.sitl
@pytest.mark.timeout(120)
def test_ground_station_keeps_its_vehicle_after_forged_vehicle_packets(key_file):
    _path, key = key_file
    gl = GcsLink("udpin:127.0.0.1:0", timeout=10.0, signing_key=key)
    port = gl.link.conn.port.getsockname()[1]
    ap = MockAutopilot(speedup=2.0, signing_key=key, endpoints=[f"udpout:127.0.0.1:{port}"]).start()
    try:
        gl.connect()
        mav = gl.link.mav
        before = signing.counts(mav)
        frames = forgeries(1, 1)
        _send_all(port, frames, lambda: gl.pump(0.01))  # GcsLink reads when pumped
        gl.wait_for(lambda: signing.counts(mav)["badsig"] - before["badsig"] >= len(frames), 10)
        mid = signing.counts(mav)
        acks = [gl.command(None, mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
                for _ in range(5)]  # the vehicle still answers its ground station
        gl.wait_for(lambda: False, 2.0)
        after = signing.counts(mav)
        assert all(a.result == "ACCEPTED" for a in acks), acks
        assert after["badsig"] - before["badsig"] == len(frames), "a genuine packet was rejected"
        assert after["goodsig"] - mid["goodsig"] >= 10, (mid, after)  # 5 ACKs, 5 AUTOPILOT_VERSIONs, heartbeats
    finally:
        gl.close()
        ap.stop()


@pytest.mark.sitl
@pytest.mark.timeout(120)
def test_mock_autopilot_keeps_obeying_its_ground_station_after_forged_gcs_packets(key_file):
    _path, key = key_file
    ap = MockAutopilot(speedup=2.0, signing_key=key, endpoints=["udpin:127.0.0.1:0"]).start()
    port = ap.port("udpin", 0)
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190,
                                     dialect="ardupilotmega")
    signing.apply(gcs, key, link_id=1)
    try:
        gcs.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        assert gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=10) is not None
        rejected0 = ap.counters().get("signing_rejected", 0)
        frames = forgeries(255, 190)
        _send_all(port, frames)
        assert wait_for(lambda: ap.counters().get("signing_rejected", 0) - rejected0 >= len(frames), 10)
        answered = 0
        for i in range(10):
            gcs.mav.param_request_read_send(1, 1, b"WPNAV_SPEED", -1)
            m = gcs.recv_match(type="PARAM_VALUE", blocking=True, timeout=3)
            answered += m is not None and m.param_id == "WPNAV_SPEED"
        assert answered == 10
        assert ap.counters().get("signing_rejected", 0) - rejected0 == len(frames), "a genuine packet was rejected"
    finally:
        gcs.close()
        ap.stop()
