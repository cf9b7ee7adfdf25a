"""The documented procedure (docs/SITL.md) flown against ArduPilot's own SITL firmware with the
real programs, and its figures: every scan ticked, every setpoint held by the autopilot, the
takeover reactions, the estimates' error, where the copter flew, the firmware's crashes.

    python bench/ardupilot.py [--params stock|recommended] [--monitor 100] [--speedup 2]
                              [--autopilot ardupilot|mock] [--policy flight|paper] [--out DIR]

The flight is tests/test_ardupilot.py's flight A (sim.procedure.fly_launch_procedure): `pmon gcs
launch` as the autopilot boots, --monitor s of monitoring, a pilot's LOITER and BRAKE each
followed by `pmon gcs resume`. The binary: $PMON_ARDUPILOT_SITL, else ../shared/ardupilot.
Prints a summary and ends with one JSON line.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sim.ardupilot import skip_reason  # noqa: E402
from sim.procedure import RECOMMENDED_PARAMS, Mission, MissionConfig, figures, fly_launch_procedure  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--params", choices=("stock", "recommended"), default="stock",
                    help="autopilot parameters: copter.parm as is, or docs/SITL.md's recommended")
    ap.add_argument("--monitor", type=float, default=100.0, help="autopilot s of monitoring (default 100)")
    ap.add_argument("--speedup", type=float, default=2.0, help="SITL speedup (default 2)")
    ap.add_argument("--autopilot", choices=("ardupilot", "mock"), default="ardupilot")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--policy", choices=("flight", "paper"), default="flight",
                    help="the app's flight policy (pmon run --policy; default flight)")
    ap.add_argument("--out", help="keep the logs here (default: a temporary directory)")
    args = ap.parse_args()
    if not 0 < args.speedup <= 10 or not 10 <= args.monitor <= 3600:
        ap.error("--speedup must be in (0, 10] and --monitor in [10, 3600]")
    if args.autopilot == "ardupilot" and (why := skip_reason()):
        print(f"bench/ardupilot.py: {why}", file=sys.stderr)
        return 2
    cfg = MissionConfig(autopilot=args.autopilot, speedup=args.speedup, seed=args.seed,
                        params=RECOMMENDED_PARAMS if args.params == "recommended" else {},
                        feed_duration_s=args.monitor + 60, app_args=("--policy", args.policy))
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out) if args.out else Path(tmp)
        wall0 = time.monotonic()
        with Mission(cfg, out) as m:
            rec = fly_launch_procedure(m, args.monitor)
        f = figures(m)
        f.update(wall_s=round(time.monotonic() - wall0, 1), params_set=args.params, policy=args.policy,
                 launch_to_monitoring_s=round(rec["start_t"] - (rec["boot_t"] or 0.0), 1),
                 load_avg_1m_end=round(os.getloadavg()[0], 2))
    c = f["containment"]
    print(f"{f['autopilot']} ({args.params} parameters, {args.policy} policy) at {args.speedup:g}x, {f['wall_s']} s wall: "
          f"boot to monitoring {f['launch_to_monitoring_s']} s; {f['scans']} scans, {f['ticks']} ticked, "
          f"{f['ticks_skipped']} skipped, {f['ticks_late']} late of {f['monitoring_ticks']} monitoring ticks "
          f"(setpoint held by the autopilot median {f['setpoint_delay_s_median']} s after the scan); "
          f"copter from the planned point at the next tick median {f['from_plan_at_next_tick_m_median']} m, "
          f"p95 {f['from_plan_at_next_tick_m_p95']} m; "
          f"takeover reactions {f['takeover_reaction_s']} s; RMSE {f['rmse_m']} m; "
          f"{c['outside_area']} of {c['samples']} positions outside the area, {c['in_obstacle']} in an "
          f"obstacle; autopilot crashes {f['autopilot_crashes']}")
    print(json.dumps(f))
    return 0


if __name__ == "__main__":
    sys.exit(main())
