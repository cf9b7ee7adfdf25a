"""Status texts longer than MAVLink's 50 characters arrive whole: the app sends MAVLink 2
STATUSTEXT chunks (id, chunk_seq), the ground station reassembles them."""
from __future__ import annotations

import time

import pytest

from onboard.app.mavlink2 import mavlink
from sim.mock.autopilot import BootTimeline, MockAutopilot

from groundstation.gcs_link import GcsLink
from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.gcs.statustext import CHUNK, Reassembler, chunks, send_statustext
from onboard.config import load_scenario
from onboard.policy import with_policy

LONG = "PMON: arming refused: PreArm: Need Position Estimate (EKF not ready, GPS 0 sats)"


class _Msg:
    """A STATUSTEXT as pymavlink decodes one (text without its null padding)."""

    def __init__(self, text: bytes, msg_id: int, seq: int, src=(1, 191)):
        self.text, self.id, self.chunk_seq, self._src = text.decode(), msg_id, seq, src

    def get_srcSystem(self):
        return self._src[0]

    def get_srcComponent(self):
        return self._src[1]


def test_chunks_split_at_50_bytes_and_always_mark_the_end():
    assert chunks("short") == [b"short"]
    assert chunks("x" * 50) == [b"x" * 50]  # fits: one message, id 0, as before
    parts = chunks(LONG)
    assert [len(p) for p in parts] == [50, len(LONG) - 50]
    assert b"".join(parts).decode() == LONG
    exact = chunks("y" * 100)
    assert exact == [b"y" * 50, b"y" * 50, b""]  # an empty last chunk says the text ended
    accents = chunks("é" * 40)  # 80 bytes: never cut inside a character
    assert all(p.decode() for p in accents) and "".join(p.decode() for p in accents) == "é" * 40
    assert len(chunks("z" * 10_000)) <= 8 and b"".join(chunks("z" * 10_000)).endswith(b"...")


def test_reassembler_joins_in_any_order_and_does_not_lose_a_text_with_a_lost_chunk():
    r = Reassembler(timeout_s=0.5)
    parts = chunks(LONG)
    assert r.feed(_Msg(parts[1], 7, 1)) == []
    assert r.feed(_Msg(parts[0], 7, 0)) == [LONG]
    assert r.feed(_Msg(b"plain", 0, 0)) == ["plain"]
    # the last chunk lost: what arrived comes out after the timeout, marked
    long2 = chunks("A" * 120)
    assert r.feed(_Msg(long2[0], 9, 0)) == []
    assert r.feed(_Msg(long2[1], 9, 1)) == []
    time.sleep(0.6)
    assert r.expire() == ["A" * 100 + "[...]"]
    # two senders using the same id do not mix
    assert r.feed(_Msg(parts[0], 3, 0, src=(1, 1))) == []
    assert r.feed(_Msg(b"other", 3, 1, src=(2, 1))) == []
    assert r.feed(_Msg(parts[1], 3, 1, src=(1, 1))) == [LONG]


@pytest.mark.timeout(60)
def test_the_apps_long_text_reaches_pmon_gcs_whole():
    """The app's own say() over a real MAVLink link (mock autopilot's routing, as ArduPilot
    routes) to pmon gcs's link: the old code cut it at 50 characters."""
    sc = with_policy(load_scenario("paper"), "paper")
    o = sc.origin
    ap = MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=10.0,
                       endpoints=["tcpin:127.0.0.1:0"] * 2, boot=BootTimeline.scaled(2.0)).start()
    app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{ap.port('tcpin', 0)}", sensor_port=0), sc).start()
    try:
        with GcsLink(f"tcp:127.0.0.1:{ap.port('tcpin', 1)}", timeout=10) as gl:
            gl.connect()
            assert gl.wait_for(lambda: app.vehicle.sysid is not None, 10)
            # the autopilot forwards a broadcast only to links it has heard a system on
            # (ArduPilot's routing, as the mock's): wait for the app's PMON_STAT to reach us, or a
            # text said before our first heartbeat is routed is lost (3 failures in 20 runs)
            assert gl.wait_for(lambda: gl.v.n_stat > 0, 10)
            t0 = time.monotonic()
            app.say(LONG.removeprefix("PMON: "), mavlink.MAV_SEVERITY_WARNING)
            assert gl.wait_for(lambda: LONG in gl.texts_since(t0, 191), 5), gl.texts_since(t0, 191)
            assert not any(t == LONG[:CHUNK] for t in gl.texts_since(t0, 191))
    finally:
        app.stop()
        ap.stop()


def test_send_statustext_encodes_mavlink2_extension_fields():
    sent = []

    class L:
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)

        def send(self, m):
            sent.append(m)
    send_statustext(L(), 4, LONG)
    send_statustext(L(), 4, "short")
    ids = {m.id for m in sent[:-1]}
    assert len(ids) == 1 and ids != {0} and [m.chunk_seq for m in sent[:-1]] == [0, 1]
    assert sent[-1].id == 0
    # the bytes on the wire carry id and chunk_seq (MAVLink 2 extensions), decoded back
    parser = mavlink.MAVLink(None)
    back = [parser.decode(bytearray(m.pack(L.mav))) for m in sent]
    assert [(b.id, b.chunk_seq) for b in back] == [(m.id, m.chunk_seq) for m in sent]


def test_the_conformance_view_reads_the_apps_chunked_texts_whole(tmp_path):
    """sim.stack.app_tlog.app_view (tests/firmware/test_conformance.py) took each chunk of a long text as a
    text of its own: 'ifted' of 'T2 guidance failed 3 ticks: previous plan shifted' failed the
    comparison with ArduPilot's SITL (measured)."""
    import struct

    from sim.stack.app_tlog import app_view

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    text = "PMON: T2 guidance failed 3 ticks: previous plan shifted (x)"
    with open(tmp_path / "app.tlog", "wb") as f:
        for seq, part in enumerate(chunks(text)):
            f.write(struct.pack(">Q", 1) + mavlink.MAVLink_statustext_message(6, part, 7, seq).pack(mav))
        f.write(struct.pack(">Q", 2) + mavlink.MAVLink_statustext_message(6, b"PMON: short", 0, 0).pack(mav))
    assert len(chunks(text)) == 2
    assert app_view(tmp_path / "app.tlog")["app_said"] == ["T2 guidance failed 3 ticks: previous plan shifted",
                                                           "short"]
