"""The hub's CoT through a real TAK server to a second TAK client of it: what an ATAK on the
same server receives. Measured with FreeTAKServer 2.2.1 (pip install freetakserver; its TCP CoT
port on 127.0.0.1, docs/OPERATING.md "TAK" says how it was started).

    python -m bench.tak_server --port 18087

A TCP client announces itself to the server (a takPong-style hello, pytak.hello_event), then
``pmon gcs hub --tak tcp://127.0.0.1:PORT`` (tests/gcs/test_gcs_hub.py's loopback vehicle: four
targets, 1 Hz ticks) sends three ticks; the client counts what the server relays: position
error (m), ce against the 1-sigma ellipse's radius, latency from the tick. One JSON line.
"""
import argparse
import json
import math
import socket
import time
import warnings
import xml.etree.ElementTree as ET

warnings.simplefilter("ignore")
import pytak

from sim.stack.hub_rig import FRAME, TARGETS, Rig
from sim.stack.cot import SIGMA, one_sigma_radius_m, split_xml

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("--port", type=int, required=True, help="the TAK server's TCP CoT port on 127.0.0.1")
PORT = ap.parse_args().port
rx = socket.create_connection(("127.0.0.1", PORT), timeout=5)
rx.sendall(pytak.hello_event(f"pmon-test-receiver-{time.time_ns()}"))  # announce ourselves as a client
time.sleep(1.0)
rig = Rig(tak_url=f"tcp://127.0.0.1:{PORT}")
got, buf, sent = {}, b"", {}
try:
    time.sleep(2.0)
    for t in (80.0, 81.0, 82.0):
        sent[t] = time.monotonic(); rig.tick(t); time.sleep(1.0)
    rx.settimeout(0.5)
    deadline = time.monotonic() + 6
    arrivals = []
    while time.monotonic() < deadline:
        try:
            data = rx.recv(65535)
        except socket.timeout:
            continue
        if not data:
            break
        evs, buf = split_xml(buf + data)
        for x in evs:
            arrivals.append((time.monotonic(), ET.fromstring(x)))
    r = one_sigma_radius_m(*SIGMA)
    rows = []
    for at, ev in arrivals:
        uid = ev.get("uid")
        if not uid.startswith("pmon-1-T"):
            continue
        j = int(uid[-1]) - 1
        pt = ev.find("point")
        e, n, _ = FRAME.enu_from_geodetic(float(pt.get("lat")), float(pt.get("lon")), float(pt.get("hae")))
        best = min((math.hypot(e - (TARGETS[j][0] + t), n - (TARGETS[j][1] - t)), t) for t in sent)
        rows.append({"uid": uid, "err_m": round(best[0], 3), "ce_rel": abs(float(pt.get("ce")) - r) / r,
                     "latency_s": round(at - sent[best[1]], 3), "callsign": ev.find("detail/contact").get("callsign") if ev.find("detail/contact") is not None else None})
    print(json.dumps({"events_from_fts": len(arrivals), "targets": len(rows),
                      "max_err_m": max((x["err_m"] for x in rows), default=None),
                      "max_ce_rel": max((x["ce_rel"] for x in rows), default=None),
                      "max_latency_s": max((x["latency_s"] for x in rows), default=None),
                      "uids": sorted({x["uid"] for x in rows}), "tak": rig.hub.summary()["tak"]}))
finally:
    rig.close(); rx.close()
