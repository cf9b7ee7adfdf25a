"""Advisory and the hand-over: the app plans and shows its next waypoint, commands nothing, and
one command hands the vehicle over to it.

Shows the app's advise and start actions from a ground station (``groundstation.gcs_commands.
app_action``, what ``pmon gcs advise`` and ``pmon gcs start`` run) and the advised waypoint in
PMON_STAT (``AppStatus.advice_enu``; docs/MAVLINK.md). The app is put in advisory from
monitoring: its setpoints stop, the vehicle holds; while it advises, PMON_STAT has no setpoint
and an advised waypoint planned each tick from where the vehicle is. Then ``start`` takes GUIDED
again and the setpoints flow. Without ``--connect`` the script stands up the mock rig itself
(``sim.stack.rig``: the mock ArduCopter, the app and the DF feed, each a process on 127.0.0.1,
launching on their own) and uses its ground-station port. (``pmon run --advise`` starts the app
in advisory instead, for a flight a pilot or a mission flies from the start.)

Run:
    python examples/advise_and_hand_over.py [--connect tcp:127.0.0.1:5762] [--count 3] [--timeout 90]
"""
import argparse
import contextlib

from groundstation.gcs_commands import app_action
from groundstation.gcs_link import GcsLink
from groundstation.protocol import AppStatus


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--connect", help="a running vehicle's MAVLink URL (default: start the mock rig)")
    ap.add_argument("--count", type=int, default=3, help="advised waypoints to print")
    ap.add_argument("--timeout", type=float, default=90.0, help="wall s to wait for each step")
    args = ap.parse_args()

    with contextlib.ExitStack() as stack:
        url = args.connect
        if url is None:
            from sim.stack.rig import Rig, RigConfig
            rig = stack.enter_context(Rig(RigConfig(speedup=2.0, ready_s=4.0, auto_launch=True)))
            url = rig.gcs_url
        gl = stack.enter_context(GcsLink(url, timeout=10.0))
        gl.connect()
        stats: list[AppStatus] = []
        gl.on_message(lambda mtype, msg: mtype == "PMON_STAT" and stats.append(AppStatus.from_msg(msg)))
        if not gl.wait_for(lambda: gl.v.app_state == "monitoring", args.timeout):
            raise SystemExit(f"the app is {gl.v.app_state or 'unheard'}, not monitoring, after {args.timeout:g} s")
        print(app_action(gl, "advise").text)
        stats.clear()
        advised = lambda: [s for s in stats if s.state == "advisory" and s.advice_enu is not None]  # noqa: E731
        if not gl.wait_for(lambda: len(advised()) >= args.count, args.timeout):
            raise SystemExit(f"only {len(advised())} advised waypoints within {args.timeout:g} s")
        for s in advised()[:args.count]:
            e, n, u = s.advice_enu
            print(f"advisory: t={s.last_tick_time_s:.1f} s, UAV {tuple(round(x, 1) for x in s.uav_enu or ())}, "
                  f"advised waypoint ({e:.1f}, {n:.1f}, {u:.1f}) m, setpoint {s.next_enu or 'none'}")
        print(app_action(gl, "start").text)


if __name__ == "__main__":
    main()
