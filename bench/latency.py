"""Setpoint latency and missed ticks of the onboard app, flown against the mock autopilot.

    python -m bench.latency [--duration 600] [--speedup 5]

Mock autopilot and app run in this process (threads, real loopback sockets); the DF feed is a
process of its own (``pmon feed live``, as on the vehicle: its truth world must not hold this
process's GIL while the app ticks). Paper scenario; the app launches by itself. The mock runs
SITL-like (``max_lag_s=0.1``): when the machine cannot sustain the speedup its clock slips
instead of jumping (counted, printed as ``clock_slips``; the achieved speedup is printed too).

Latency: local wall time from a tick's start (its scan is due and handed to the worker) to its
setpoint leaving the socket. Missed (``TickAccount``, the one definition; bench/soak.py uses it
too): a scan sent by the feed that never reached a tick (skipped at an overrun, rejected on
arrival, e.g. as stale, or still pending at shutdown), or a monitoring tick whose setpoint was
not sent or reached the autopilot (the mock's own clock) later than PMON_BUDGET after the scan's
time (or after its arrival when the feed delivered it late; the feed lag is printed). Scans
before monitoring (take-off) are ticked like any other (tracking runs in every state) and count
the same way: a scan not ticked is missed whatever the app's state. Counted as the mission flies
(a tick listener and the autopilot's setpoint handler, in constant memory), so a mission of any
length is counted whole; quantiles come from fixed histograms (0.1 ms / 1 ms bins).
The feed's own lateness (scans it sent > 0.25 s after their time) is printed: a simulator that
cannot keep up makes misses that are not the app's. Last line: JSON figures.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path

from sim.stack.demo import DEMO_READY_S
from sim.stack.rig import Rig, RigConfig
from sim.stack.tick_account import TickAccount, scan_times

ROOT = Path(__file__).resolve().parents[1]


def fly(duration: float, speedup: float, seed: int, cfg_extra: dict | None = None, on_app=None,
        on_setpoint=None, after=None) -> dict:
    """Fly one mission; returns the app, its TickAccount figures, the mock's counters, the feed's.

    ``on_app(app)`` every 0.5 s wall, ``on_setpoint(msg)`` per setpoint the autopilot receives,
    ``after(app)`` when the mission is over (before anything is torn down or read back)."""
    account = TickAccount()

    def received(t, msg):
        account.on_setpoint(t, (msg.x, msg.y, msg.z))
        if on_setpoint is not None:
            on_setpoint(msg)
    with tempfile.TemporaryDirectory() as tmp:
        truth = Path(tmp) / "truth.jsonl"
        # the paper scenario as written (its policy), the demo's vehicle and boot, at the mission
        # origin (the fence checks read the mock's local NED as the mission's ENU), mock and app
        # in this process, the feed a process
        rig = Rig(RigConfig(policy="paper", seed=seed, speedup=speedup, home="origin", ready_s=DEMO_READY_S,
                            ports=2, in_process=True, auto_launch=True, app_config=cfg_extra or {},
                            feed_duration_s=int(duration), out_dir=tmp, truth_path=str(truth)),
                  on_tick=lambda rec: account.on_tick(rec, rig.app.params.settings.app.tick_budget_s), on_setpoint=received)
        with rig:
            ap, app = rig.ap, rig.app
            wall0, t0 = time.monotonic(), ap.sim_time
            while rig.feed.p.poll() is None:
                if on_app is not None:
                    on_app(app)
                time.sleep(0.5)
            # the last scan's tick: wait until nothing is pending or running (bounded)
            deadline = time.monotonic() + 10
            while (app.scans.pending or app.worker.busy) and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(1.5 / speedup)
            if after is not None:
                after(app)
            rig.stop_programs()
            wall = time.monotonic() - wall0
            achieved = (ap.sim_time - t0) / wall
            figures = account.finish(scan_times(truth))
            done = re.search(r"(\d+) sent > [\d.]+ s late \(max ([\d.]+) s", (Path(tmp) / "feed.log").read_text())
            return {"app": app, "figures": figures, "ap_counters": ap.counters(),
                    "achieved_speedup": achieved, "wall_s": wall, "feed_rc": rig.feed.p.returncode,
                    "feed_late_scans": int(done.group(1)) if done else None,
                    "feed_send_lag_s_max": float(done.group(2)) if done else None}


def figures(run: dict, duration: float, speedup: float) -> dict:
    app = run["app"]
    f = run["figures"]
    rejected = {k: v for k, v in app.scans.rejected.items() if v}
    c = app.counters
    return {
        "mission_s": duration, "speedup": speedup, "achieved_speedup": round(run["achieved_speedup"], 2),
        **f, "datagrams_rejected": rejected,
        "feed_late_scans": run["feed_late_scans"], "feed_send_lag_s_max": run["feed_send_lag_s_max"],
        "scans_without_pose": c.get("scans_without_pose", 0), "ticks_coasted": c.get("ticks_coasted", 0),
        "guidance_timeouts": c.get("guidance_timeouts", 0),
        "fallbacks": c.get("fallback_previous", 0) + c.get("fallback_coast", 0),
        "tick_errors": c.get("tick_errors", 0), "io_errors": c.get("io_errors", 0),
        "listener_errors": c.get("listener_errors", 0),
        "clock_slips": run["ap_counters"].get("clock_slips", 0), "wall_s": round(run["wall_s"], 1),
        "load_avg_1m_end": round(os.getloadavg()[0], 2),
    }


def main() -> int:
    ap_ = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap_.add_argument("--duration", type=float, default=60.0, help="mission seconds (default 60: smoke)")
    ap_.add_argument("--speedup", type=float, default=5.0)
    ap_.add_argument("--seed", type=int, default=1)
    args = ap_.parse_args()
    run = fly(args.duration, args.speedup, args.seed)
    f = figures(run, args.duration, args.speedup)
    print(f"{f['monitoring_ticks']} monitoring ticks; latency median {f['latency_ms_median']} ms; "
          f"missed {f['ticks_missed']} (late {f['ticks_late']}, unticked {f['scans_unticked']} of which "
          f"skipped {f['ticks_skipped']}); feed late {f['feed_late_scans']}; "
          f"{f['achieved_speedup']}x achieved, load {f['load_avg_1m_end']}")
    print(json.dumps(f))
    return 0


if __name__ == "__main__":
    sys.exit(main())
