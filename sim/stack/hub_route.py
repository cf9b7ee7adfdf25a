"""The hub route of a monitoring flight (sim.stack.procedure.Mission): ``pmon gcs hub`` on the vehicle's
spare port with a pymavlink ground station on it, what that client got matched to the app's
estimates, and what the flight's observer heard meanwhile (bench/adsb_route.py, and the stock
flight's test)."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time

from sim.stack.procedure import Mission

AVOIDANCE = {"ADSB_TYPE": 1, "AVD_ENABLE": 1, "AVD_W_DIST_XY": 1000, "AVD_F_DIST_XY": 1000}


class Recorder:
    """What the observer's link hears besides what sim.stack.mission_clients.Observer keeps."""

    def __init__(self, observer):
        self.lock = threading.Lock()
        self.collisions: list = []
        self.adsb: list = []
        self.avoid_texts: list = []
        orig = observer._on

        def on(msg):
            mtype = msg.get_type()
            with self.lock:
                if mtype == "COLLISION":
                    self.collisions.append((observer.t, msg.id, msg.action, msg.threat_level))
                elif mtype == "ADSB_VEHICLE":
                    self.adsb.append((observer.t, msg.get_srcSystem(), msg.get_srcComponent(), msg.ICAO_address))
                elif mtype == "STATUSTEXT" and any(w in msg.text for w in ("ADSB", "Avoid", "avoid", "threat")):
                    self.avoid_texts.append((observer.t, msg.text))
            orig(msg)
        observer._on = on

    def counts(self, t0: float, t1: float) -> dict:
        with self.lock:
            def within(rows):
                return [r for r in rows if r[0] is not None and t0 <= r[0] <= t1]
            return {"collision_msgs": len(within(self.collisions)),
                    "collision_actions_threats": sorted({(r[2], r[3]) for r in within(self.collisions)}),
                    "collision_ids": sorted({hex(r[1]) for r in within(self.collisions)}),
                    "adsb_vehicle_on_observer": len(within(self.adsb)),
                    "avoidance_texts": [x for _, x in within(self.avoid_texts)]}


def mode_changes(m: Mission, t0: float, t1: float) -> list:
    with m.observer.lock:
        modes = list(m.observer.modes)
    return [(round(t, 1), mode) for t, mode, _ in modes if t is not None and t0 < t <= t1]


class HubClient:
    """A pymavlink ground station on the hub's port: the ADSB_VEHICLE it gets, matched to the
    PMON_TGT (forwarded by the hub) each was made from."""

    def __init__(self, port: int):
        from onboard.app.mavlink_connection import mavlink
        from onboard.app.mavlink2 import mavutil
        self.mavlink = mavlink
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=240,
                                               source_component=190, dialect="ardupilotmega")
        self.last_tgt: dict[int, object] = {}
        self.ticks: dict[int, set] = {}
        self.markers: dict[int, list] = {}
        self.closing = threading.Event()  # no new tick counted: the markers of those counted still come
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        from groundstation import adsb as A
        hb = 0.0
        while not self.stop.is_set():
            if time.monotonic() - hb > 1.0:
                hb = time.monotonic()
                self.conn.mav.heartbeat_send(6, 8, 0, 0, 0)
            m = self.conn.recv_match(blocking=True, timeout=0.1)
            if m is None:
                continue
            t = m.get_type()
            if t == "DEBUG_FLOAT_ARRAY" and m.name == "PMON_TGT" and m.get_srcComponent() == 191:
                self.last_tgt[m.array_id] = m
                if not self.closing.is_set():
                    self.ticks.setdefault(m.array_id, set()).add(round(m.data[13], 3))
            elif t == "ADSB_VEHICLE" and m.emitter_type != A.OA_DB_EMITTER:
                j = (m.ICAO_address - A.MARKER_BASE) % 16
                tgt = self.last_tgt.get(j)
                if self.closing.is_set() and (tgt is None or round(tgt.data[13], 3) not in self.ticks.get(j, ())):
                    continue  # made from a tick after the window
                self.markers.setdefault(j, []).append((m, tgt))

    def close(self, grace_s: float = 0.5):
        """Stop counting ticks, then receive ``grace_s`` (wall s) more for the markers the hub
        makes from the last ones counted (else a tick counted just before the end has its marker
        in flight: one tick more than markers, a race of the window's edge, not a lost marker)."""
        self.closing.set()
        time.sleep(grace_s)
        self.stop.set()
        self.thread.join(timeout=2)
        self.conn.close()


def hub_route(m: Mission, rec: Recorder, monitor_s: float, during=None) -> dict:
    """The hub route on a monitoring flight: ``pmon gcs hub`` on the spare port (SERIAL6) with a
    pymavlink ground station on it for ``monitor_s`` autopilot s (``during(m)`` runs at its start,
    inside that time); what the client got, matched to the estimates, and what the observer
    heard in that window (``rec``: a Recorder on the flight's observer from its start)."""
    from groundstation.estimates import check
    from onboard.app.autopilot.pose import Frame
    from sim.stack.gcs_fake_vehicle import free_udp_port

    frame = Frame(m.sc.origin.lat_deg, m.sc.origin.lon_deg, m.sc.origin.alt_m)
    port = free_udp_port()
    hub = subprocess.Popen([sys.executable, "-m", "onboard.cli", "gcs", "hub", "--connect", m.spare_url,
                            "--serve", f"udp:127.0.0.1:{port}", "--json", "--timeout", "20"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                           env=dict(os.environ, PYTHONUNBUFFERED="1"))
    client = HubClient(port)
    tb0 = m.observer.t
    if during is not None:
        during(m)
    m.sim_sleep(monitor_s - ((m.observer.t or tb0) - tb0))
    tb1 = m.observer.t
    client.close()
    hub.send_signal(signal.SIGINT)
    try:
        hub_out, hub_err = hub.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        hub.kill()  # never leave it holding the autopilot's port for the next flight
        hub.communicate()
        raise
    summary = json.loads(hub_out.strip().splitlines()[-1])
    errors, per_tick = [], {}
    for j, rows in client.markers.items():
        per_tick[f"T{j + 1}"] = {"adsb": len(rows), "ticks": len(client.ticks.get(j, ()))}
        for msg, tgt in rows:
            est, _ = check(tgt, frame) if tgt is not None else (None, None)
            if est is None:
                continue
            e, n, _ = frame.enu_from_geodetic(msg.lat * 1e-7, msg.lon * 1e-7, msg.altitude * 1e-3)
            errors.append(math.hypot(e - est.x_m, n - est.y_m))
    return {"autopilot_s": [tb0, tb1], "per_target": per_tick,
            "max_error_m": round(max(errors), 4) if errors else None, "matched": len(errors),
            "mode_changes": mode_changes(m, tb0, tb1), **rec.counts(tb0, tb1),
            "hub_summary": {k: summary.get(k) for k in ("adsb_sent", "forwarded_to_vehicle",
                                                         "estimates_refused", "echoed_targets_dropped")}}
