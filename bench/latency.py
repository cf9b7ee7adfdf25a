"""Setpoint latency and missed ticks of the onboard app, flown against the mock autopilot.

    python bench/latency.py [--duration 600] [--speedup 5]

Mock autopilot and app run in this process (threads, real loopback sockets); the DF feed is a
process of its own (``pmon feed live``, as on the vehicle: its truth world must not hold this
process's GIL while the app ticks). Paper scenario; the app launches by itself. The mock runs
SITL-like (``max_lag_s=0.1``): when the machine cannot sustain the speedup its clock slips
instead of jumping (counted, printed as ``clock_slips``; the achieved speedup is printed too).

Latency: local wall time from a tick's start (its scan is due and handed to the worker) to its
setpoint leaving the socket. Missed: a scan skipped (overrun), a monitoring tick whose setpoint
reached the autopilot (the mock's own clock) later than PMON_BUDGET after the scan's time (or
after its arrival when the feed delivered it late; the feed lag is printed), or a scan sent by
the feed that never reached a tick. Every scan is accounted for: ticked, skipped, or rejected
on arrival (by reason), or still pending at shutdown. Last line: JSON figures.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sim.autopilot import MockAutopilot  # noqa: E402  (sets MAVLINK20 first)
from onboard.app.app import AppConfig, OnboardApp  # noqa: E402
from onboard.config import load_scenario  # noqa: E402
from onboard.demo import DEMO_VEHICLE_PARAMS  # noqa: E402


def fly(duration: float, speedup: float, seed: int, cfg_extra: dict | None = None, on_app=None,
        on_setpoint=None) -> dict:
    """Fly one mission; returns the app, the autopilot's received setpoints and the feed's scans."""
    sc = load_scenario("paper")
    o = sc.origin
    rx: list[tuple[float, tuple]] = []
    with tempfile.TemporaryDirectory() as tmp, \
            MockAutopilot(home=(o.lat_deg, o.lon_deg, o.alt_m), speedup=speedup, seed=seed,
                          endpoints=["tcpin:127.0.0.1:0"] * 2, params=DEMO_VEHICLE_PARAMS,
                          max_lag_s=0.1) as ap:
        orig = ap._on_set_position_target_local_ned

        def spy(link, msg):
            rx.append((ap.copter.t, (msg.x, msg.y, msg.z)))
            if on_setpoint is not None:
                on_setpoint(msg)
            orig(link, msg)
        ap._on_set_position_target_local_ned = spy
        app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{ap.port('tcpin', 0)}", sensor_port=0,
                                   auto_launch=True, seed=seed, **(cfg_extra or {})), sc).start()
        truth = Path(tmp) / "truth.jsonl"
        wall0, t0 = time.monotonic(), ap.sim_time
        feed = subprocess.Popen(
            [sys.executable, "-m", "sim.feed", "live", "--mavlink", f"tcp:127.0.0.1:{ap.port('tcpin', 1)}",
             "--to", f"127.0.0.1:{app.sensor_port}", "--seed", str(seed + 1), "--duration", str(int(duration)),
             "--wait-armed", "--truth", str(truth)], cwd=ROOT, stdout=subprocess.DEVNULL)
        try:
            while feed.poll() is None:
                if on_app is not None:
                    on_app(app)
                time.sleep(0.5)
            # the last scan's tick: wait until nothing is pending or running (bounded)
            deadline = time.monotonic() + 10
            while (app.scans.pending or app._worker_busy) and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(1.5 / speedup)
        finally:
            if feed.poll() is None:
                feed.terminate()
            feed.wait(timeout=10)
            app.stop()
        wall = time.monotonic() - wall0
        achieved = (ap.sim_time - t0) / wall
        scans = [json.loads(line) for line in open(truth) if '"header"' not in line]
        return {"app": app, "rx": rx, "scans": scans, "ap_counters": ap.counters(),
                "achieved_speedup": achieved, "wall_s": wall, "feed_rc": feed.returncode}


def received_at(rx, tick, i0: int) -> tuple[float | None, int]:
    """Autopilot time the mock first received this tick's setpoint (home = mission origin, so
    local NED = (north, east, -up)); scans rx from index i0 (ticks come in time order)."""
    e, n, u = tick["next"]
    while i0 < len(rx) and rx[i0][0] < tick["t"]:
        i0 += 1
    for i in range(i0, len(rx)):
        x, y, z = rx[i][1]
        if abs(x - n) < 0.01 and abs(y - e) < 0.01 and abs(z + u) < 0.01:
            return rx[i][0], i0
    return None, i0


def figures(run: dict, duration: float, speedup: float) -> dict:
    app = run["app"]
    ticks = [t for t in app.ticks if t["channels"]]
    planned = [t for t in ticks if t["planned"]]
    budget = app.params["PMON_BUDGET"]
    lat = [t["latency_ms"] for t in planned if t["latency_ms"] is not None]
    late, delays, lags, i0 = [], [], [], 0
    for t in planned:
        r, i0 = received_at(run["rx"], t, i0)
        start = max(t["t"], t["arrived_t"] if t["arrived_t"] is not None else t["t"])
        lags.append(start - t["t"])
        if r is None or not t["sent"]:
            late.append(t["t"])
            continue
        delays.append(r - start)
        if r - start > budget:
            late.append(t["t"])
    skipped = sum(t["skipped_before"] for t in ticks)
    scan_times = {r["t"] for r in run["scans"]}
    ticked = {t["t"] for t in ticks}
    rejected = {k: v for k, v in app.scans.rejected.items() if v}
    unticked = sorted(scan_times - ticked)
    c = app.counters
    return {
        "mission_s": duration, "speedup": speedup, "achieved_speedup": round(run["achieved_speedup"], 2),
        "scans": len(scan_times), "ticks": len(ticks), "monitoring_ticks": len(planned),
        "latency_ms_median": round(float(np.median(lat)), 1) if lat else None,
        "latency_ms_p95": round(float(np.percentile(lat, 95)), 1) if lat else None,
        "latency_ms_max": round(float(np.max(lat)), 1) if lat else None,
        "setpoint_delay_s_median": round(float(np.median(delays)), 3) if delays else None,
        "setpoint_delay_s_max": round(float(np.max(delays)), 3) if delays else None,
        "feed_lag_s_max": round(float(np.max(lags)), 3) if lags else None,
        "tick_ms_median": round(float(np.median([t["tick_ms"] for t in ticks])), 1) if ticks else None,
        "ticks_missed": len(late) + skipped + len(unticked),
        "ticks_late": len(late), "ticks_skipped": skipped, "scans_unticked": len(unticked),
        "unticked_t": unticked[:20], "datagrams_rejected": rejected,
        "scans_without_pose": c.get("scans_without_pose", 0), "ticks_coasted": c.get("ticks_coasted", 0),
        "guidance_timeouts": c.get("guidance_timeouts", 0),
        "fallbacks": c.get("fallback_previous", 0) + c.get("fallback_coast", 0),
        "tick_errors": c.get("tick_errors", 0), "io_errors": c.get("io_errors", 0),
        "clock_slips": run["ap_counters"].get("clock_slips", 0), "wall_s": round(run["wall_s"], 1),
    }


def main() -> int:
    ap_ = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap_.add_argument("--duration", type=float, default=60.0, help="mission seconds (default 60: smoke)")
    ap_.add_argument("--speedup", type=float, default=5.0)
    ap_.add_argument("--seed", type=int, default=1)
    args = ap_.parse_args()
    run = fly(args.duration, args.speedup, args.seed)
    f = figures(run, args.duration, args.speedup)
    print(f"{f['monitoring_ticks']} monitoring ticks; latency median {f['latency_ms_median']} ms; "
          f"missed {f['ticks_missed']} (late {f['ticks_late']}, skipped {f['ticks_skipped']}, "
          f"unticked {f['scans_unticked']})")
    print(json.dumps(f))
    return 0


if __name__ == "__main__":
    sys.exit(main())
