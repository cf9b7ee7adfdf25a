"""Which route puts the targets on a ground station's map without the autopilot taking them as
traffic: measured on ArduCopter SITL (4.4.0-dev, ../shared/ardupilot) with the real programs.

    python -m bench.adsb_route [--avoidance on|off] [--monitor 60] [--inject 20] [--speedup 2]

One flight (sim.stack.procedure.Mission: SITL, ``pmon run``, ``pmon feed live``, ``pmon gcs launch``):

B. the hub route: ``pmon gcs hub`` on the vehicle's SERIAL6 serves a pymavlink ground station
   for --monitor autopilot s of monitoring; the client checks one ADSB_VEHICLE per target per
   tick within 1 m of the PMON_TGT it was made from; the observer (SERIAL5) counts the
   autopilot's mode changes, COLLISION messages, ADSB_VEHICLE and avoidance texts.
A. the autopilot route: the same targets' ADSB_VEHICLE (adsb.marker of the app's latest
   estimates) sent into the autopilot on SERIAL2 at 1 Hz for --inject s, as a ground station
   or companion forwarding them to the vehicle would; the same counts.

``--avoidance on`` sets ADSB_TYPE 1 (MAVLink receiver), AVD_ENABLE 1 and warn/fail distances
of 1000 m (the area is 1 km: every target is "near"), with ArduCopter's default AVD_F_ACTION;
``--action N`` sets AVD_F_ACTION (2 climb/descend, 3 move horizontally, 4 perpendicular, 5 RTL,
6 hover); ``off`` flies copter.parm as is. Prints a summary and one JSON line.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from sim.firmware.ardupilot import skip_reason
from sim.stack.procedure import Mission, MissionConfig
from sim.stack.hub_route import AVOIDANCE, Recorder, hub_route, mode_changes

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--avoidance", choices=("on", "off"), default="on")
    ap.add_argument("--monitor", type=float, default=60.0, help="autopilot s of monitoring with the hub (default 60)")
    ap.add_argument("--inject", type=float, default=20.0, help="autopilot s of ADSB_VEHICLE into the autopilot (default 20)")
    ap.add_argument("--action", type=int, help="AVD_F_ACTION with --avoidance on (default: ArduCopter's)")
    ap.add_argument("--speedup", type=float, default=2.0)
    ap.add_argument("--out", help="keep the logs here (default: a temporary directory)")
    args = ap.parse_args()
    if (why := skip_reason()):
        print(why)
        return 2
    out = Path(args.out or tempfile.mkdtemp(prefix="pmon-adsb-route-"))
    params = dict(AVOIDANCE) if args.avoidance == "on" else {}
    if args.action is not None and params:
        params["AVD_F_ACTION"] = args.action
    res = fly(params, args.monitor, args.inject, args.speedup, out)
    print(json.dumps(res, indent=1))
    print(json.dumps(res))
    return 0


def fly(params: dict, monitor_s: float, inject_s: float, speedup: float, out: Path) -> dict:
    """One flight: --monitor s of the hub route, then --inject s of the autopilot route (0:
    none). Returns the figures (the JSON line)."""
    from groundstation import adsb as A
    from groundstation.estimates import check
    from onboard.app.autopilot.pose import Frame

    cfg = MissionConfig(speedup=speedup, params=params, feed_duration_s=monitor_s + inject_s + 150)
    res: dict = {"avoidance": "on" if params else "off", "params": params, "speedup": speedup}
    with Mission(cfg, out) as m:
        rec = Recorder(m.observer)
        frame = Frame(m.sc.origin.lat_deg, m.sc.origin.lon_deg, m.sc.origin.alt_m)
        launch = m.gcs("launch")
        if not m.wait(lambda o: o.app_state == "monitoring", 200, "monitoring"):
            raise RuntimeError(f"not monitoring: {launch.stderr} {m.observer.app_texts()}")
        res["hub"] = hub_route(m, rec, monitor_s)
        if inject_s <= 0:
            return res
        # ---- A: into the autopilot
        from onboard.app.mavlink_connection import Link, mavlink
        link = Link(m.sitl.url(2), source_system=255, source_component=190)
        mav = A.encoder(1)
        ta0 = m.observer.t
        sent = 0
        while (m.observer.t or 0) - ta0 < inject_s:
            link.send(link.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
            with m.observer.lock:
                latest = {}
                for t, j, x, y, sx, sy in m.observer.estimates:
                    latest[j] = (x, y, sx, sy)
            for j, (x, y, sx, sy) in latest.items():
                from sim.stack.gcs_fake_vehicle import target_values

                class _T:  # the app's estimate as PMON_TGT carries it
                    array_id = j
                    data = target_values(x, y, 0.0, 0.0, sx, sy, 0.0, since=0.0, t=1.0)

                    def get_srcComponent(self):
                        return 191
                est, _ = check(_T(), frame)
                if est is not None:
                    link.send(A.marker(mav, est))
                    sent += 1
            m.sim_sleep(1.0)
        ta1 = m.observer.t
        link.close()
        m.sim_sleep(5.0)
        res["autopilot_route"] = {"autopilot_s": [ta0, ta1], "adsb_sent_to_autopilot": sent,
                                  "mode_changes": mode_changes(m, ta0, (m.observer.t or ta1)),
                                  **rec.counts(ta0, m.observer.t or ta1)}
        res["app_texts_after_inject"] = m.observer.app_texts(ta0)[-5:]
    return res


if __name__ == "__main__":
    sys.exit(main())
