"""``pmon gcs hub --tak URL``: every estimate and the UAV as CoT, over UDP, TCP and TLS with
pytak, decoded as a TAK client decodes them (XML, and TAK protocol 1 with takproto)."""
from __future__ import annotations

import datetime as dt
import math
import socket
import ssl
import subprocess
import threading
import time
import xml.etree.ElementTree as ET

import pytest

pytest.importorskip("pytak", reason="pytak is in the gcs extra")
takproto = pytest.importorskip("takproto", reason="takproto is in the gcs extra")

from sim.stack.gcs_fake_vehicle import free_udp_port  # noqa: E402
from sim.stack.hub_rig import FRAME, TARGETS, Rig  # noqa: E402
from sim.stack.cot import SIGMA, one_sigma_radius_m, split_xml  # noqa: E402


def parse_time(text: str) -> dt.datetime:
    return dt.datetime.strptime(text, "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=dt.timezone.utc)


class Events:
    """CoT events as they arrive, with the local time of arrival."""

    def __init__(self):
        self.items: list[tuple[float, ET.Element]] = []
        self.lock = threading.Lock()

    def add(self, xml: bytes) -> None:
        ev = ET.fromstring(xml)
        with self.lock:
            self.items.append((time.monotonic(), ev))

    def of(self, uid: str) -> list[tuple[float, ET.Element]]:
        with self.lock:
            return [(t, e) for t, e in self.items if e.get("uid") == uid]

    def wait(self, pred, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pred():
                return True
            time.sleep(0.02)
        return pred()


def udp_receiver(port: int, events: Events, proto: bool, stop: threading.Event):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", port))
    sock.settimeout(0.1)

    def run():
        while not stop.is_set():
            try:
                data = sock.recv(65535)
            except socket.timeout:
                continue
            if proto:  # TAK protocol 1: takproto decodes it to the same event
                events.add(_proto_to_xml(data))
            else:
                for x in split_xml(data)[0]:
                    events.add(x)
        sock.close()
    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t


def _proto_to_xml(data: bytes) -> bytes:
    """A TAK protocol message as CoT XML, through takproto's own decoder (as ATAK decodes)."""
    msg = takproto.parse_proto(data)
    e = msg.cotEvent
    ev = ET.Element("event", {"uid": e.uid, "type": e.type, "how": e.how,
                              "time": _ms(e.sendTime), "start": _ms(e.startTime), "stale": _ms(e.staleTime)})
    ET.SubElement(ev, "point", {"lat": repr(e.lat), "lon": repr(e.lon), "hae": repr(e.hae), "ce": repr(e.ce),
                                "le": repr(e.le)})
    det = ET.SubElement(ev, "detail")
    if e.detail.HasField("contact"):
        ET.SubElement(det, "contact", {"callsign": e.detail.contact.callsign})
    if e.detail.HasField("track"):
        ET.SubElement(det, "track", {"course": repr(e.detail.track.course), "speed": repr(e.detail.track.speed)})
    return ET.tostring(ev)


def _ms(t: int) -> str:
    return dt.datetime.fromtimestamp(t / 1000, dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")


def check_target_events(events: Events, sent_at: dict, ticks) -> dict:
    """Every estimate of every tick arrived within 1 s of its tick, within 1 m, ce within 5 %."""
    r = one_sigma_radius_m(*SIGMA)
    worst = {"latency_s": 0.0, "error_m": 0.0, "ce_rel": 0.0, "n": 0}
    for j, (x, y) in enumerate(TARGETS):
        got = events.of(f"pmon-1-T{j + 1}")
        assert len(got) == len(ticks), (j, len(got))
        for (at, ev), t in zip(got, ticks):
            pt = ev.find("point")
            e, n, _ = FRAME.enu_from_geodetic(float(pt.get("lat")), float(pt.get("lon")), float(pt.get("hae")))
            worst["error_m"] = max(worst["error_m"], math.hypot(e - (x + t), n - (y - t)))
            worst["ce_rel"] = max(worst["ce_rel"], abs(float(pt.get("ce")) - r) / r)
            worst["latency_s"] = max(worst["latency_s"], at - sent_at[t])
            worst["n"] += 1
            assert ev.get("type") == "a-u-G" and ev.find("detail/contact").get("callsign") == f"PMON T{j + 1}"
            assert float(ev.find("detail/track").get("speed")) == pytest.approx(5.0, abs=0.01)
            assert parse_time(ev.get("stale")) > parse_time(ev.get("start"))
    assert worst["error_m"] <= 1.0 and worst["ce_rel"] <= 0.05 and worst["latency_s"] <= 1.0, worst
    return worst


def fly(rig: Rig, ticks) -> dict:
    sent_at = {}
    for t in ticks:
        sent_at[t] = time.monotonic()
        rig.tick(t)
        rig.veh.position(FRAME.origin[0] + 0.001, FRAME.origin[1] + 0.001, FRAME.origin[2] + 40)
        time.sleep(0.3)
    return sent_at


@pytest.mark.timeout(60)
@pytest.mark.parametrize("proto", [False, True], ids=["xml", "takproto"])
def test_cot_over_udp_every_estimate_within_1s_1m_and_ce_within_5pct_then_expires(proto):
    port = free_udp_port()
    events, stop = Events(), threading.Event()
    rx = udp_receiver(port, events, proto, stop)
    rig = Rig(tak_url=f"udp://127.0.0.1:{port}", tak_proto=int(proto), lost_after_s=3.0)
    try:
        ticks = [40.0, 41.0, 42.0, 43.0, 44.0]
        sent_at = fly(rig, ticks)
        assert events.wait(lambda: all(len(events.of(f"pmon-1-T{j + 1}")) >= 5 for j in range(4)), 3)
        worst = check_target_events(events, sent_at, ticks)
        print(f"CoT over UDP ({'takproto' if proto else 'XML'}): {worst['n']} events, worst latency "
              f"{worst['latency_s'] * 1e3:.0f} ms, position {worst['error_m']:.3f} m, ce {worst['ce_rel'] * 100:.3f} %")
        uav = events.of("pmon-1-uav")
        assert uav and uav[-1][1].get("type") == "a-f-A-M-F-Q"
        assert abs(float(uav[-1][1].find("point").get("lat")) - (FRAME.origin[0] + 0.001)) < 1e-6
        # the app falls silent: each target gets a last event already stale
        n = {j: len(events.of(f"pmon-1-T{j + 1}")) for j in range(4)}
        assert events.wait(lambda: all(len(events.of(f"pmon-1-T{j + 1}")) == n[j] + 1 for j in range(4)), 5)
        for j in range(4):
            last = events.of(f"pmon-1-T{j + 1}")[-1][1]
            assert parse_time(last.get("stale")) <= parse_time(last.get("start"))
    finally:
        rig.close()
        stop.set()
        rx.join(timeout=2)


def make_certs(d) -> dict:
    """A CA, a server certificate for 127.0.0.1 and a client certificate (openssl)."""
    def run(*args):
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=d)
    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "1",
        "-subj", "/CN=pmon test CA")
    for name in ("server", "client"):
        run("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out", f"{name}.csr",
            "-subj", f"/CN={'127.0.0.1' if name == 'server' else 'pmon'}")
        (d / f"{name}.ext").write_text("subjectAltName=IP:127.0.0.1\n")
        run("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
            "-out", f"{name}.pem", "-days", "1", "-extfile", f"{name}.ext")
    return {k: str(d / k) for k in ("ca.pem", "server.pem", "server.key", "client.pem", "client.key")}


def tcp_server(events: Events, stop: threading.Event, tls_ctx=None):
    """A CoT stream server on 127.0.0.1 (as a TAK server's TCP or TLS input), one client."""
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    srv.settimeout(0.2)
    state = {"clients": 0, "peer_cert": None}

    def run():
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except socket.timeout:
                continue
            if tls_ctx is not None:
                conn = tls_ctx.wrap_socket(conn, server_side=True)
                state["peer_cert"] = conn.getpeercert()
            state["clients"] += 1
            conn.settimeout(0.2)
            buf = b""
            while not stop.is_set():
                try:
                    data = conn.recv(65535)
                except socket.timeout:
                    continue
                except OSError:
                    break
                if not data:
                    break
                evs, buf = split_xml(buf + data)
                for x in evs:
                    events.add(x)
            conn.close()
        srv.close()
    t = threading.Thread(target=run, daemon=True)
    t.start()
    return srv.getsockname()[1], t, state


@pytest.mark.timeout(90)
@pytest.mark.parametrize("tls", [False, True], ids=["tcp", "tls"])
def test_cot_over_tcp_and_tls_with_client_certificate(tmp_path, tls):
    events, stop = Events(), threading.Event()
    ctx = tls_cfg = None
    if tls:
        c = make_certs(tmp_path)
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        ctx.load_cert_chain(c["server.pem"], c["server.key"])
        ctx.load_verify_locations(c["ca.pem"])
        ctx.verify_mode = ssl.CERT_REQUIRED  # a TAK server wants the client's certificate
        tls_cfg = {"PYTAK_TLS_CLIENT_CERT": c["client.pem"], "PYTAK_TLS_CLIENT_KEY": c["client.key"],
                   "PYTAK_TLS_CLIENT_CAFILE": c["ca.pem"]}
    port, srv, state = tcp_server(events, stop, ctx)
    url = f"{'tls' if tls else 'tcp'}://127.0.0.1:{port}"
    rig = Rig(tak_url=url, tak_tls=tls_cfg or {})
    try:
        ticks = [60.0, 61.0, 62.0]
        sent_at = fly(rig, ticks)
        assert events.wait(lambda: all(len(events.of(f"pmon-1-T{j + 1}")) >= 3 for j in range(4)), 5), \
            rig.hub.summary()["tak"]
        worst = check_target_events(events, sent_at, ticks)
        print(f"CoT over {url.split(':')[0].upper()}: {worst['n']} events, worst latency {worst['latency_s'] * 1e3:.0f} ms")
        if tls:
            assert state["peer_cert"] and dict(x[0] for x in state["peer_cert"]["subject"])["commonName"] == "pmon"
    finally:
        rig.close()
        stop.set()
        srv.join(timeout=2)


@pytest.mark.timeout(60)
def test_an_absent_tak_server_never_stalls_the_hub():
    """TCP to a port nobody listens on: the hub goes on drawing ADSB at the same pace, the
    CoT it cannot send is dropped and counted."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        dead = s.getsockname()[1]
    rig = Rig(tak_url=f"tcp://127.0.0.1:{dead}")
    try:
        for t in range(70, 75):
            rig.tick(float(t))
            time.sleep(0.2)
        assert rig.client.wait(lambda: len([m for m in rig.client.got("ADSB_VEHICLE") if m.emitter_type != 255]) == 20, 3)
        tak = rig.hub.summary()["tak"]
        assert tak["connects"] == 0 and tak["errors"] >= 1 and "Connection" in (tak["last_error"] or "")
    finally:
        rig.close()
