"""Read PMON_STAT from a ground station: the app's state and health, as ``pmon gcs status`` does.

Shows the ground station's link (``groundstation.gcs_link.GcsLink``): connect to a vehicle, ask
the autopilot for nothing, listen. The onboard app publishes PMON_STAT (a DEBUG_FLOAT_ARRAY, its
fields in docs/MAVLINK.md) once a second; ``AppStatus.from_msg`` decodes it. Without ``--connect``
the script stands up the mock rig itself (``sim.stack.rig``: the mock ArduCopter, the app and the DF
feed, each a process on 127.0.0.1, launching on their own) and reads it from its ground-station port.

Run:
    python examples/read_pmon_stat.py [--connect tcp:127.0.0.1:5762] [--count 5] [--timeout 60]
"""
import argparse
import contextlib

from groundstation.gcs_link import GcsLink
from groundstation.protocol import AppStatus


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", help="a running vehicle's MAVLink URL (default: start the mock rig)")
    ap.add_argument("--count", type=int, default=5, help="PMON_STAT messages to print")
    ap.add_argument("--timeout", type=float, default=60.0, help="wall s to wait for them")
    args = ap.parse_args()

    with contextlib.ExitStack() as stack:
        url = args.connect
        if url is None:
            from sim.stack.rig import Rig, RigConfig
            rig = stack.enter_context(Rig(RigConfig(speedup=2.0, ready_s=4.0, auto_launch=True)))
            url = rig.gcs_url
        gl = stack.enter_context(GcsLink(url, timeout=args.timeout))
        gl.connect()
        stats: list[AppStatus] = []
        gl.on_message(lambda mtype, msg: mtype == "PMON_STAT" and stats.append(AppStatus.from_msg(msg)))
        if not gl.wait_for(lambda: len(stats) >= args.count, args.timeout):
            raise SystemExit(f"only {len(stats)} PMON_STAT from {url} within {args.timeout:g} s")
        for s in stats[:args.count]:
            tick = "-" if s.tick_ms is None else f"{s.tick_ms:.0f} ms"
            phase = f", launch: {s.launch_phase}" if s.launch_phase else ""
            print(f"PMON_STAT state {s.state}{phase}; ticks {s.ticks} (last {tick}); "
                  f"datagrams {s.datagrams_accepted} accepted, {s.datagrams_rejected} rejected; "
                  f"UAV {s.uav_enu and tuple(round(x, 1) for x in s.uav_enu)}")


if __name__ == "__main__":
    main()
