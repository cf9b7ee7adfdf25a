"""The documented procedure (docs/SITL.md) flown against ArduPilot's or PX4's own SITL firmware
with the real programs, and its figures: every scan ticked, every setpoint held by the autopilot,
the takeover reactions, the copter from the planned point at the next tick, the estimates' error,
where the copter flew, the firmware's crashes.

    python -m bench.ardupilot [--autopilot ardupilot|px4|mock] [--params stock|recommended]
                              [--monitor 100] [--speedup 2] [--policy flight|paper] [--seed 1] [--out DIR]
                              [--rt-priority N]

The flight is tests/firmware/test_ardupilot.py's flight A (sim.stack.procedure.fly_launch_procedure): `pmon gcs
launch` as the autopilot boots, --monitor s of monitoring, a pilot's takeovers each followed by
`pmon gcs resume`: ArduCopter's LOITER and BRAKE; on PX4 (tests/firmware/test_px4.py's flight A) Hold and
POSCTL, with a pilot's sticks live from the start of monitoring (PX4 takes POSCTL only with
manual control). The binaries: $PMON_ARDUPILOT_SITL, else ../shared/ardupilot; $PMON_PX4_SITL,
else ../shared/px4. ``recommended``: docs/SITL.md's parameters (ArduCopter: the demo vehicle's;
PX4: COM_OBL_RC_ACT 5). Prints a summary and ends with one JSON line.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from sim.firmware.ardupilot import skip_reason
from sim.stack.procedure import RECOMMENDED_PARAMS, Mission, MissionConfig, figures, fly_launch_procedure
from sim.firmware.px4 import RECOMMENDED_PARAMS as PX4_RECOMMENDED
from sim.firmware.px4 import skip_reason as px4_skip_reason

ROOT = Path(__file__).resolve().parents[1]

# a pilot's takeovers, each followed by resume
TAKEOVERS = {"px4": (("mode", "HOLD"), ("mode", "POSCTL")), "ardupilot": (("mode", "LOITER"), ("hold",)),
             "mock": (("mode", "LOITER"), ("hold",))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--params", choices=("stock", "recommended"), default="stock",
                    help="autopilot parameters: copter.parm as is, or docs/SITL.md's recommended")
    ap.add_argument("--monitor", type=float, default=100.0, help="autopilot s of monitoring (default 100)")
    ap.add_argument("--speedup", type=float, default=2.0, help="SITL speedup (default 2)")
    ap.add_argument("--autopilot", choices=("ardupilot", "px4", "mock"), default="ardupilot")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--policy", choices=("flight", "paper"), default="flight",
                    help="the app's flight policy (pmon run --policy; default flight)")
    ap.add_argument("--out", help="keep the logs here (default: a temporary directory)")
    ap.add_argument("--rt-priority", type=int, default=0,
                    help="pmon run --rt-priority N: the app's io thread and worker at SCHED_FIFO (default 0: normal)")
    args = ap.parse_args()
    if not 0 < args.speedup <= 10 or not 10 <= args.monitor <= 3600:
        ap.error("--speedup must be in (0, 10] and --monitor in [10, 3600]")
    problem = {"ardupilot": skip_reason, "px4": px4_skip_reason}.get(args.autopilot, lambda: None)()
    if problem:
        print(f"bench/ardupilot.py: {problem}", file=sys.stderr)
        return 2
    recommended = PX4_RECOMMENDED if args.autopilot == "px4" else RECOMMENDED_PARAMS
    cfg = MissionConfig(autopilot=args.autopilot, speedup=args.speedup, seed=args.seed,
                        params=recommended if args.params == "recommended" else {},
                        feed_duration_s=args.monitor + 60, app_args=("--policy", args.policy)
                        + (("--rt-priority", str(args.rt_priority)) if args.rt_priority else ()))
    sticks = (lambda m, rec: m.take_sticks()) if args.autopilot == "px4" else None
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out) if args.out else Path(tmp)
        wall0 = time.monotonic()
        with Mission(cfg, out) as m:
            rec = fly_launch_procedure(m, args.monitor, during=sticks, takeovers=TAKEOVERS[args.autopilot])
        f = figures(m)
        f.update(wall_s=round(time.monotonic() - wall0, 1), params_set=args.params, policy=args.policy,
                 launch_to_monitoring_s=round(rec["start_t"] - (rec["boot_t"] or 0.0), 1),
                 load_avg_1m_end=round(os.getloadavg()[0], 2))
    c = f["containment"]
    print(f"{f['autopilot']} ({args.params} parameters, {args.policy} policy, seed {args.seed}) at {args.speedup:g}x, "
          f"{f['wall_s']} s wall: "
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
