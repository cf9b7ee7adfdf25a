"""Send one setpoint to ArduCopter SITL: the MAVLink the onboard app sends, once, by hand.

Shows the autopilot edge: ArduPilot's own SITL firmware (``sim.firmware.ardupilot.ArduPilotSitl``, on
127.0.0.1, booted at the paper scenario's UAV start), the ground station's link and commands
(GUIDED, arm once the pre-arm checks pass, take off), then one SET_POSITION_TARGET_LOCAL_NED
built as the app builds it (``onboard.app.autopilot.setpoint_stream.message``: NED metres at the
autopilot's origin, position only), and the copter flying to it (LOCAL_POSITION_NED).

Needs an ArduCopter SITL build: ``$PMON_ARDUPILOT_SITL`` (or ../shared/ardupilot/arducopter).
Run:
    PMON_ARDUPILOT_SITL=/path/to/arducopter python examples/sitl_setpoint.py [--north 30 --east 20 --alt 10]
"""
import argparse
import math

from groundstation.gcs_commands import arm, takeoff
from groundstation.gcs_link import GcsLink
from onboard.app.mavlink_connection import mavlink
from onboard.app.autopilot.setpoint_stream import message
from onboard.config import load_scenario
from sim.firmware.ardupilot import ArduPilotSitl, find_binary, home_of, skip_reason


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--north", type=float, default=30.0, help="m from the origin")
    ap.add_argument("--east", type=float, default=20.0, help="m from the origin")
    ap.add_argument("--alt", type=float, default=10.0, help="m above home")
    ap.add_argument("--speedup", type=float, default=10.0, help="SITL s per wall s")
    args = ap.parse_args()
    if skip_reason():
        raise SystemExit(skip_reason())

    with ArduPilotSitl(find_binary(), home_of(load_scenario("paper")), speedup=args.speedup) as sitl, \
            GcsLink(sitl.url(0), timeout=60.0) as gl:
        gl.connect()
        print(arm(gl, wait=True).text)
        print(takeoff(gl, args.alt, wait=True).text)
        gl.stream(mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 4.0)
        target = (args.north, args.east, -args.alt)  # NED, m
        now = gl.v.get("SYSTEM_TIME").time_boot_ms / 1000 if gl.v.get("SYSTEM_TIME") else 0.0
        gl.send(message(gl.link.mav, now, gl.v.sysid, gl.v.autopilot_comp, target))
        print(f"setpoint sent: N {target[0]:g} E {target[1]:g} D {target[2]:g} m")

        def distance() -> float:
            p = gl.v.get("LOCAL_POSITION_NED")
            return math.inf if p is None else math.dist((p.x, p.y, p.z), target)
        if not gl.wait_for(lambda: distance() < 1.0, 60.0):
            raise SystemExit(f"not at the setpoint within 60 s: {distance():.1f} m away")
        p = gl.v.get("LOCAL_POSITION_NED")
        print(f"at the setpoint: N {p.x:.1f} E {p.y:.1f} D {p.z:.1f} m ({distance():.2f} m off)")


if __name__ == "__main__":
    main()
