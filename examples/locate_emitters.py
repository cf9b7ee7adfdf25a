"""Locate two emitters from a recording: a simulated KrakenSDR ``mydata.csv`` and the flight's tlog.

Shows ``pmon locate``'s API (docs/LOCATE.md): a lawnmower flown 300-605 m from two stationary
emitters is written as KrakenSDR records it and as a tlog (``sim.stack.locate_recording``), then read,
aligned and tracked by the app's own filter (``groundstation.locate.locate``); each emitter's
final estimate, its 95 % ellipse and its error against the truth are printed. The same from a
shell: ``pmon locate DIR/mydata.csv DIR/flight.tlog --scenario DIR/scenario.yaml``.

Run:
    python examples/locate_emitters.py [--seed 7] [--dir DIR]
"""
import argparse
import tempfile

import numpy as np

from groundstation.locate import Request, ellipse95, locate
from onboard.config import load_scenario
from onboard.policy import DEFAULT, with_policy
from sim.stack.locate_recording import write_recording


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--dir", help="where the recording is written (default: a temporary directory)")
    args = ap.parse_args()

    folder = args.dir or tempfile.mkdtemp(prefix="pmon-locate-")
    rec = write_recording(folder, args.seed)
    sc = with_policy(load_scenario(str(rec["scenario"])), DEFAULT)
    found, log = locate(Request(str(rec["mydata"]), str(rec["tlog"]), sc))
    print(f"{rec['frames']} KrakenSDR frames, {len(found.times)} ticks, poses from {log.kind}")
    for j, target in enumerate(sc.targets):
        m, c = found.final_means[j], found.final_covs[j]
        major, minor, az = ellipse95(c[:2, :2])
        err = np.hypot(*(m[:2] - rec["truth_m"][j]))
        print(f"{target.name}: E {m[0]:.1f} N {m[1]:.1f} m, 95 % ellipse {major:.1f} x {minor:.1f} m "
              f"at {az:.0f} deg, error {err:.1f} m")


if __name__ == "__main__":
    main()
