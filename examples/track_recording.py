"""Track targets from a recorded datagram file: the core's particle filters on recorded bearings.

Shows the tracking half of a tick without a vehicle: each scan of a truth JSONL (what
``pmon feed live`` and ``pmon demo`` record, docs/DATAGRAM.md; read and checked by
``sim.stack.feed.read_recording``) updates every target's belief from where the UAV was, with the
paper's filter (``--policy paper``); the estimates are compared with the recorded truth. ``examples/data/paper_seed7_20s.jsonl`` is 20
scans of ``pmon demo --duration 20 --seed 7`` (the UAV climbing from its start, then
monitoring). The same file can be sent to a running app: ``pmon feed replay FILE --to HOST:PORT``.

Run:
    python examples/track_recording.py [FILE] [--seed 1]
"""
import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from onboard.config import load_scenario
from onboard.core.monitor import MonitorSetup, Scan, initial_state, tick
from onboard.policy import with_policy
from sim.stack.feed import read_recording

HERE = Path(__file__).parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("file", nargs="?", default=str(HERE / "data" / "paper_seed7_20s.jsonl"))
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    records = [json.loads(line) for line in open(args.file) if line.strip()]
    header = records[0].get("header", {})
    truth = {r["t"]: r for r in records if "t" in r}  # uav_enu and the true targets per scan time
    scans = defaultdict(dict)  # t -> {channel: bearings (rad)}, checked as the app checks them
    for t, ch, bearings in read_recording(args.file):
        scans[t][ch] = np.asarray(bearings)

    setup = MonitorSetup.from_scenario(with_policy(load_scenario(header.get("scenario", "paper")), "paper"))
    rng = np.random.default_rng(args.seed)
    state = initial_state(setup, rng)
    for t in sorted(scans):
        per_ch = tuple(scans[t].get(j, np.empty(0)) for j in range(setup.n_targets))
        state, result = tick(setup, state, [Scan(np.asarray(truth[t]["uav_enu"]), per_ch)], rng)
        err = np.linalg.norm(result.means[:, :2] - np.asarray(truth[t]["targets"])[:, :2], axis=1)
        print(f"t {t:5.1f} s  error per target (m): " + " ".join(f"{e:6.1f}" for e in err))
    print(f"{len(scans)} scans from {Path(args.file).name}; "
          f"final RMSE over targets {np.sqrt(np.mean(err ** 2)):.1f} m")


if __name__ == "__main__":
    main()
