"""Where the copter's distance from the plan comes from, tick by tick, in a flight's run log
(``python -m bench.ardupilot --out DIR`` keeps it; docs/SITL.md, "Following the plan").

    python -m bench.follow_ticks DIR [--ticks] [--step 3.0]

For each monitoring tick that ``sim.stack.procedure.follow_errors_m`` scores: the distance from the
planned point to the vehicle at the next scan, split along and across the planned velocity; the
plan's start after the scan (segment t0 minus the scan's time); its velocity change over the
tick; and the step of its acceleration from the last segment's end (0 with a continuous
acceleration). Prints the ticks (``--ticks``), then the summary: median, p95, the along-track
median, the start's lag, the ticks whose acceleration stepped by ``--step`` m/s^2 or more and
their median distance against the others', and how many of the top 10 % stepped. Ends with one
JSON line.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from onboard.core.setpoint import plan_setpoint

ROOT = Path(__file__).resolve().parents[1]


def _state(seg: dict, at: float):
    d = min(max(at - seg["t0"], 0.0), seg["tick_s"])
    return plan_setpoint(seg["p0"][:2], seg["v0"], seg["v1"], seg["tick_s"], d, seg.get("a0"))


def ticks(recs: list[dict]) -> list[dict]:
    """One row per scored tick (the pairs sim.stack.procedure.follow_errors_m takes)."""
    rows, last = [], None
    for a, b in zip(recs, recs[1:]):
        seg = a.get("segment")
        if not (a["sent"] and a["next"] and b["planned"] and b["uav_enu"] and seg
                and abs(b["t"] - a["t"] - 1.0) < 1e-6):
            last = seg
            continue
        err = np.asarray(b["uav_enu"][:2]) - np.asarray(a["next"][:2])
        v1 = np.asarray(seg["v1"], float)
        u = v1 / max(float(np.linalg.norm(v1)), 1e-9)
        acc0 = _state(seg, seg["t0"])[2]
        step = None if last is None or seg["t0"] - last["t0"] > 1.5 * last["tick_s"] \
            else float(np.linalg.norm(acc0 - _state(last, seg["t0"])[2]))
        rows.append({"t": a["t"], "m": float(np.linalg.norm(err)), "along_m": float(err @ u),
                     "across_m": float(u[0] * err[1] - u[1] * err[0]), "start_lag_s": seg["t0"] - a["t"],
                     "dv_mps": float(np.linalg.norm(v1 - np.asarray(seg["v0"]))), "acc_step_mps2": step})
        last = seg
    return rows


def summary(rows: list[dict], step_min: float) -> dict:
    m = np.array([r["m"] for r in rows])
    stepped = np.array([r["acc_step_mps2"] is not None and r["acc_step_mps2"] >= step_min for r in rows])
    top = m >= np.percentile(m, 90)
    med = (lambda x: round(float(np.median(x)), 2) if len(x) else None)
    return {"ticks": len(rows), "median_m": med(m), "p95_m": round(float(np.percentile(m, 95)), 2),
            "max_m": round(float(m.max()), 2), "along_median_m": med([r["along_m"] for r in rows]),
            "start_lag_s_median": round(float(np.median([r["start_lag_s"] for r in rows])), 3),
            "stepped": int(stepped.sum()), "stepped_median_m": med(m[stepped]),
            "others_median_m": med(m[~stepped]), "top10": int(top.sum()), "top10_stepped": int((top & stepped).sum())}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", help="a bench/ardupilot.py --out directory (its run.jsonl)")
    ap.add_argument("--ticks", action="store_true", help="print every tick")
    ap.add_argument("--step", type=float, default=3.0, help="an acceleration step counted, m/s^2 (default 3)")
    args = ap.parse_args()
    path = Path(args.dir) / "run.jsonl"
    if not path.exists():
        print(f"bench/follow_ticks.py: no run log {path}", file=sys.stderr)
        return 2
    rows = ticks([json.loads(line) for line in open(path) if line.strip()])
    if not rows:
        print(f"bench/follow_ticks.py: no scored tick in {path}", file=sys.stderr)
        return 2
    if args.ticks:
        print("t [s]   m      along  across  start lag [s]  |dv| [m/s]  acc step [m/s^2]")
        for r in rows:
            s = "-" if r["acc_step_mps2"] is None else f"{r['acc_step_mps2']:.2f}"
            print(f"{r['t']:6.1f} {r['m']:5.2f} {r['along_m']:6.2f} {r['across_m']:6.2f} "
                  f"{r['start_lag_s']:8.3f} {r['dv_mps']:10.2f}  {s}")
    f = summary(rows, args.step)
    print(f"{f['ticks']} ticks: from the plan median {f['median_m']} m, p95 {f['p95_m']} m, max {f['max_m']} m; "
          f"along the track median {f['along_median_m']} m; plan started {f['start_lag_s_median']} s after its scan "
          f"(median); {f['stepped']} ticks with an acceleration step >= {args.step:g} m/s^2: median "
          f"{f['stepped_median_m']} m against {f['others_median_m']} m; of the top 10 % ({f['top10']}), "
          f"{f['top10_stepped']} stepped")
    print(json.dumps(f))
    return 0 if math.isfinite(f["median_m"]) else 1


if __name__ == "__main__":
    sys.exit(main())
