"""A picture of MAVProxy's map with the targets as traffic, headless (Xvfb): docs/mavproxy_map.png.

    python -m bench.mavproxy_map_shot --mavproxy-python PYTHON [--out docs/mavproxy_map.png]

PYTHON runs MAVProxy 1.8.74 with its map module (wxPython and OpenCV: Debian's python3-wxgtk4.0
and python3-opencv in a venv made with --system-site-packages). The vehicle is the hub tests'
loopback vehicle (tests/gcs/test_gcs_hub.py: the app's four targets on the paper scenario);
``pmon gcs hub`` serves MAVProxy; Xvfb is the display. No map tiles (no internet): the
targets, their 1-sigma circles and the vehicle on MAVProxy's blank background.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mavproxy-python", required=True)
    ap.add_argument("--out", default=str(ROOT / "docs" / "mavproxy_map.png"))
    ap.add_argument("--display", default=":97")
    args = ap.parse_args()
    if shutil.which("Xvfb") is None:
        print("no Xvfb (Debian: apt-get install xvfb)")
        return 2
    from sim.stack.hub_rig import FRAME, Rig

    xvfb = subprocess.Popen(["Xvfb", args.display, "-screen", "0", "1280x800x24", "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rig = mp = None
    try:
        time.sleep(1.0)
        rig = Rig(lost_after_s=30.0)
        env = dict(os.environ, DISPLAY=args.display, PYTHONUNBUFFERED="1")
        lat, lon, _ = FRAME.geodetic_from_enu((600.0, 650.0, 40.0))  # the UAV mid-area: the map follows it
        mp = subprocess.Popen([args.mavproxy_python, "-m", "MAVProxy.mavproxy", f"--master=udpout:127.0.0.1:{rig.sport}",
                               "--non-interactive", "--no-state", "--map",
                               ],
                              stdout=open("/tmp/mavproxy_map_shot.log", "w"), stderr=subprocess.STDOUT,
                              stdin=subprocess.DEVNULL, env=env, cwd="/tmp")
        t0 = time.monotonic()
        t = 500.0
        while time.monotonic() - t0 < 25:
            rig.veh.heartbeat()
            rig.veh.position(lat, lon, FRAME.origin[2] + 40)
            if time.monotonic() - t0 > 8:  # MAVProxy draws traffic it first hears once its map is open
                k = t - 500.0  # four targets driving past the UAV, within its default 1 km-wide view
                near = [(600.0 - 150 + 3 * k, 650.0 + 120), (600.0 + 140, 650.0 + 60 - 2 * k),
                        (600.0 + 40 - 3 * k, 650.0 - 140), (600.0 - 170, 650.0 - 60 + 2 * k)]
                rig.tick(t, targets=[(x - t, y + t) for x, y in near])  # tick() moves them by (+t, -t)
                t += 1.0
            time.sleep(0.5)
        from PIL import ImageGrab
        img = ImageGrab.grab(xdisplay=args.display).crop((0, 0, 800, 660))  # MAVProxy's map window
        img.save(args.out)
        print(f"map: {args.out} ({img.size[0]}x{img.size[1]})")
    finally:
        if mp is not None:
            mp.terminate()
            mp.wait(timeout=10)
        if rig is not None:
            rig.close()
        xvfb.terminate()
        xvfb.wait(timeout=10)
    return 0


if __name__ == "__main__":
    sys.exit(main())
