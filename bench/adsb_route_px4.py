"""What PX4 (v1.16.0 SITL, SIH quad, ../shared/px4) does with ADSB_VEHICLE that passes through
it, against the hub route that never sends it there: a short pymavlink-driven flight (the app
does not speak PX4 yet).

    python -m bench.adsb_route_px4 [--instance 8] [--traff-avoid 1] [--inject 15] [--hub 15]

PX4 runs as ``run-sih.sh INSTANCE 1 WORKDIR`` with ``PX4_PARAM_NAV_TRAFF_AVOID`` (0 off, 1 warn:
the default, 2 return, 3 land, 4 hold). This process is a companion on the Offboard/API link
(PX4 listens on 14580+N) and a second client on the payload link (14280+N) watches what PX4
forwards. Arm, take off to 20 m (Hold), then:

B. the hub route: a stand-in for the app publishes PMON_TGT of four targets 60-250 m from the
   vehicle on the ground, through PX4 (which forwards it, -f) to ``pmon gcs hub`` on the
   payload link; a pymavlink ground station on the hub gets their ADSB_VEHICLE; --hub s.
A. the autopilot route: the same targets' ADSB_VEHICLE sent into PX4 on the companion link at
   1 Hz for --inject s.

For each: PX4's mode changes (HEARTBEAT), STATUSTEXT, ADSB_VEHICLE and EVENT (410) messages
it sends, on both links. Prints a summary and one JSON line. Keep it short: every PX4
instance's GCS link sends to 127.0.0.1:14550.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from onboard.app.mavlink2 import mavutil
from onboard.app.mavlink_connection import mavlink

ROOT = Path(__file__).resolve().parents[1]

RUN_SIH = ROOT.parent.parent / "shared" / "px4" / "run-sih.sh" if not (ROOT.parent / "shared").exists() \
    else ROOT.parent / "shared" / "px4" / "run-sih.sh"
PX4_ENV = "PMON_PX4_RUN_SIH"


class Watch:
    """Everything one link hears from PX4, with local receive times."""

    def __init__(self, url: str, sysid: int, comp: int):
        self.conn = mavutil.mavlink_connection(url, source_system=sysid, source_component=comp,
                                               dialect="ardupilotmega")
        self.lock = threading.Lock()
        self.rows: list = []  # (local s, type, msg)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        hb = 0.0
        while not self.stop.is_set():
            if time.monotonic() - hb > 0.5:
                hb = time.monotonic()
                try:
                    self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
                                                 0, 0, 0)
                except OSError:
                    pass
            try:
                m = self.conn.recv_match(blocking=True, timeout=0.05)
            except OSError:
                continue
            if m is not None:
                with self.lock:
                    self.rows.append((time.monotonic(), m.get_type(), m))

    def since(self, t0: float, t1: float = math.inf, mtype: str | None = None) -> list:
        with self.lock:
            return [m for t, ty, m in self.rows if t0 <= t <= t1 and (mtype is None or ty == mtype)]

    def close(self):
        self.stop.set()
        self.thread.join(timeout=2)
        self.conn.close()


def modes(rows) -> list:
    out = []
    for m in rows:
        if m.get_srcComponent() == 1 and m.autopilot == mavlink.MAV_AUTOPILOT_PX4:
            if not out or out[-1] != (m.custom_mode, bool(m.base_mode & 128)):
                out.append((m.custom_mode, bool(m.base_mode & 128)))
    return out


def mode_name(cm: int) -> str:
    main, sub = (cm >> 16) & 0xFF, (cm >> 24) & 0xFF
    names = {(4, 3): "Hold", (4, 2): "Takeoff", (4, 5): "Return", (4, 6): "Land", (6, 0): "Offboard",
             (3, 0): "Position", (2, 0): "Altitude", (4, 4): "Mission"}
    return names.get((main, sub), f"main {main} sub {sub}")


def counts(watch: Watch, t0: float, t1: float) -> dict:
    rows = watch.since(t0, t1)
    hb = [m for m in rows if m.get_type() == "HEARTBEAT"]
    return {"modes": [(mode_name(c), a) for c, a in modes(hb)],
            "statustext": [m.text for m in rows if m.get_type() == "STATUSTEXT"],
            "adsb_vehicle": len([m for m in rows if m.get_type() == "ADSB_VEHICLE"]),
            "events_410": len([m for m in rows if m.get_type() == "UNKNOWN_410"])}


def command(w: Watch, cmd: int, *params, timeout=3.0) -> int | None:
    p = list(params) + [0.0] * (7 - len(params))
    t0 = time.monotonic()
    w.conn.mav.command_long_send(w.sysid, 1, cmd, 0, *p)
    while time.monotonic() - t0 < timeout:
        for m in w.since(t0, mtype="COMMAND_ACK"):
            if m.command == cmd:
                return m.result
        time.sleep(0.05)
    return None


TARGETS = [(60.0, 40.0), (-120.0, 80.0), (200.0, -150.0), (-90.0, -230.0)]  # ENU m from home


def _take_off(comp: Watch) -> tuple[tuple[float, float, float], float]:
    """Wait for PX4's position, arm, take off 20 m and wait for Hold: (home (lat, lon, alt AMSL),
    the local time it was flying)."""
    deadline = time.monotonic() + 30
    while not comp.since(0, mtype="HEARTBEAT") and time.monotonic() < deadline:
        time.sleep(0.2)
    gp = None
    while gp is None and time.monotonic() < deadline:
        gps = [m for m in comp.since(0, mtype="GLOBAL_POSITION_INT") if m.lat != 0]
        gp = gps[-1] if gps else None
        time.sleep(0.2)
    home = (gp.lat * 1e-7, gp.lon * 1e-7, (gp.alt - gp.relative_alt) * 1e-3)
    for _ in range(20):  # armable ~5 s after start
        if command(comp, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == 0:
            break
        time.sleep(1.0)
    command(comp, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, home[2] + 20)
    t_up = time.monotonic()
    while time.monotonic() - t_up < 40:  # 3 m/s up, then PX4 holds by itself
        hbs = [m for m in comp.since(t_up, mtype="HEARTBEAT") if m.get_srcComponent() == 1]
        if hbs and time.monotonic() - t_up > 3 and mode_name(hbs[-1].custom_mode) == "Hold":
            break
        time.sleep(0.2)
    time.sleep(1.0)
    return home, time.monotonic()


def _hub_route(comp: Watch, n: int, wd: Path, home, frame, seconds: float) -> dict:
    """B: the hub on the payload link, the stand-in app publishing PMON_TGT on the companion link."""
    import re

    from groundstation import adsb as A
    from sim.stack.gcs_fake_vehicle import free_udp_port, target_values

    port = free_udp_port()
    paper = (ROOT / "onboard" / "data" / "paper.yaml").read_text()  # the mission at PX4's home
    scenario = wd / "px4_home.yaml"
    scenario.write_text(re.sub(r"^origin: \{[^}]*\}", f"origin: {{lat_deg: {home[0]:.7f}, lon_deg: "
                               f"{home[1]:.7f}, alt_m: {home[2]:.2f}}}", paper, flags=re.M))
    hubproc = subprocess.Popen([sys.executable, "-m", "onboard.cli", "gcs", "hub", "--scenario", str(scenario),
                                "--connect",
                                f"udpin:127.0.0.1:{14030 + n}", "--serve", f"udp:127.0.0.1:{port}", "--json",
                                "--timeout", "10", "--sysid", str(n + 1)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env=dict(os.environ, PYTHONUNBUFFERED="1"))
    client = None
    try:
        client = Watch(f"udpout:127.0.0.1:{port}", 240, 190)
        tb0 = time.monotonic()
        k = 0
        while time.monotonic() - tb0 < seconds:
            comp.conn.mav.srcSystem = n + 1  # the app speaks as the vehicle's system, component 191
            for j, (x, y) in enumerate(TARGETS):
                data = target_values(x + k, y - k, 1.0, -1.0, 20.0, 15.0, 0.0, since=0.2, t=100.0 + k)
                comp.conn.mav.debug_float_array_send(int((100 + k) * 1e6), b"PMON_TGT", j, data + [0.0] * 44)
            comp.conn.mav.srcSystem = 245
            k += 1
            time.sleep(1.0)
        tb1 = time.monotonic()
        hubproc.send_signal(signal.SIGINT)
        out, err = hubproc.communicate(timeout=15)
        try:
            summary = json.loads(out.strip().splitlines()[-1])
        except (ValueError, IndexError):
            summary = {"error": (out + err)[-400:]}
        got = [m for m in client.since(tb0, tb1, "ADSB_VEHICLE") if m.emitter_type != A.OA_DB_EMITTER]
        errs = []
        for m in got:
            j = (m.ICAO_address - A.MARKER_BASE) % 16
            e, nn, _ = frame.enu_from_geodetic(m.lat * 1e-7, m.lon * 1e-7, m.altitude * 1e-3)
            x, y = TARGETS[j]
            errs.append(min(math.hypot(e - (x + kk), nn - (y - kk)) for kk in range(k)))
        return {"seconds": round(tb1 - tb0, 1), "ticks": k, "adsb_to_client": len(got),
                "max_error_m": round(max(errs), 4) if errs else None,
                "hub_adsb_sent": summary.get("adsb_sent"), "hub_refused": summary.get("estimates_refused"),
                "hub_error": summary.get("error"),
                **counts(comp, tb0, tb1)}
    finally:
        if client is not None:
            client.close()
        if hubproc.poll() is None:
            hubproc.kill()


def _autopilot_route(comp: Watch, payload: Watch, frame, seconds: float) -> dict:
    """A: the targets' ADSB_VEHICLE into PX4 on the companion link at 1 Hz."""
    from groundstation import adsb as A
    from groundstation.estimates import check
    from sim.stack.gcs_fake_vehicle import target_values

    def estimate(j, x, y):
        class T:
            array_id = j
            data = target_values(x, y, 1.0, -1.0, 20.0, 15.0, 0.0, since=0.0, t=1.0)

            def get_srcComponent(self):
                return 191
        return check(T(), frame)[0]

    ta0 = time.monotonic()
    mav = A.encoder(250)  # an ADS-B receiver of another system, as a transponder would send
    sent = 0
    while time.monotonic() - ta0 < seconds:
        for j, (x, y) in enumerate(TARGETS):
            est = estimate(j, x, y)
            frame_bytes = A.pack(mav, [A.marker(mav, est)])[0]
            comp.conn.write(frame_bytes)
            sent += 1
        time.sleep(1.0)
    time.sleep(3.0)
    ta1 = time.monotonic()
    return {"seconds": round(ta1 - ta0, 1), "adsb_sent_to_px4": sent, **counts(comp, ta0, ta1),
            "forwarded_to_payload_link": counts(payload, ta0, ta1)["adsb_vehicle"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--instance", type=int, default=8)
    ap.add_argument("--traff-avoid", type=int, default=None, help="NAV_TRAFF_AVOID (default: PX4's, 1 warn)")
    ap.add_argument("--inject", type=float, default=15.0)
    ap.add_argument("--hub", type=float, default=15.0)
    args = ap.parse_args()
    run_sih = Path(os.environ.get(PX4_ENV, RUN_SIH))
    if not run_sih.is_file():
        print(f"no PX4 SITL: set {PX4_ENV} to run-sih.sh")
        return 2
    from onboard.app.autopilot.pose import Frame

    n = args.instance
    wd = Path(tempfile.mkdtemp(prefix="pmon-px4-"))
    env = dict(os.environ)
    if args.traff_avoid is not None:
        env["PX4_PARAM_NAV_TRAFF_AVOID"] = str(args.traff_avoid)
    px4 = subprocess.Popen(["sh", str(run_sih), str(n), "1", str(wd)], stdout=open(wd / "px4.log", "w"),
                           stderr=subprocess.STDOUT, env=env)
    res: dict = {"instance": n, "NAV_TRAFF_AVOID": args.traff_avoid if args.traff_avoid is not None else "default"}
    comp = payload = None
    try:
        comp = Watch(f"udpout:127.0.0.1:{14580 + n}", 245, 191)
        comp.sysid = n + 1
        payload = Watch(f"udpin:127.0.0.1:{14030 + n}", 246, 191)
        home, t_flying = _take_off(comp)
        frame = Frame(*home)
        payload.close()  # B: the hub takes the payload link
        res["hub_route"] = _hub_route(comp, n, wd, home, frame, args.hub)
        payload = Watch(f"udpin:127.0.0.1:{14030 + n}", 246, 191)  # A: watched again
        res["autopilot_route"] = _autopilot_route(comp, payload, frame, args.inject)
        res["modes_before"] = counts(comp, t_flying - 5, t_flying)["modes"]
    finally:
        for w in (comp, payload):
            if w is not None:
                w.close()
        px4.send_signal(signal.SIGTERM)
        try:
            px4.wait(timeout=15)
        except subprocess.TimeoutExpired:
            px4.kill()
    log = (wd / "px4.log").read_text(errors="replace")
    res["px4_log_traffic_lines"] = [line.strip()[:160] for line in log.splitlines()
                                    if any(w in line.lower() for w in ("traffic", "adsb", "collision", "transponder"))][:12]
    print(json.dumps(res, indent=1))
    print(json.dumps(res))
    return 0

if __name__ == "__main__":
    sys.exit(main())
