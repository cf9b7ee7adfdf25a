"""PX4 SITL as sim/firmware/px4.py runs it: the simulated / wall time ratio at each speed factor, what the
relay to the host's loopback costs (its CPU, PX4's), and a TIMESYNC round trip through the relay
against a client inside PX4's namespace (a fresh PX4 for each: PX4 keeps the first peer of a link).

    python -m bench.px4_link [--speeds 1,3,5,8] [--seconds 20] [--pings 200]

Prints a line per figure and one JSON line at the end. Needs PMON_PX4_SITL (or ../shared/px4)
and a network namespace (root, or unprivileged user namespaces).
"""
from __future__ import annotations

import os

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from onboard.app.mavlink2 import mavutil
from sim.firmware.px4 import Px4Sitl, find_sitl, links_of, skip_reason


def _cpu_s(pid: int) -> float:
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _px4_pid(sitl: Px4Sitl) -> int:
    relay = sitl.proc.pid
    return int(open(f"/proc/{relay}/task/{relay}/children").read().split()[0])


def _latest_time(conn) -> tuple[float, float]:
    """(wall s, PX4 s) of the first message timed after the backlog is read."""
    while conn.recv_match(blocking=False) is not None:
        pass
    while True:
        m = conn.recv_match(type=["ATTITUDE", "SYSTEM_TIME"], blocking=True, timeout=1.0)
        if m is not None:
            return time.monotonic(), m.time_boot_ms / 1000.0


def ratio(speed: float, seconds: float) -> dict:
    wd = tempfile.TemporaryDirectory(prefix="pmon-px4-bench-")  # not the ULogs: a bench of its own
    s = Px4Sitl(find_sitl(), speed=speed, workdir=Path(wd.name)).start()
    try:
        conn = mavutil.mavlink_connection(s.url("api"), source_system=245, source_component=191)
        relay, px4 = s.proc.pid, _px4_pid(s)
        time.sleep(3.0)
        w0, t0 = _latest_time(conn)
        c0 = (_cpu_s(relay), _cpu_s(px4))
        n, end = 0, time.monotonic() + seconds
        while time.monotonic() < end:
            n += conn.recv_match(blocking=True, timeout=0.5) is not None
        w1, t1 = _latest_time(conn)
        c1 = (_cpu_s(relay), _cpu_s(px4))
        conn.close()
        span = w1 - w0
        return {"speed": speed, "sim_per_wall": round((t1 - t0) / span, 3), "messages_per_wall_s": round(n / span),
                "relay_cpu_pct": round(100 * (c1[0] - c0[0]) / span, 1),
                "px4_cpu_pct": round(100 * (c1[1] - c0[1]) / span, 1)}
    finally:
        s.stop()
        wd.cleanup()


PING = r"""
import os, sys, time, json, statistics
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
c = mavutil.mavlink_connection(sys.argv[1], source_system=245, source_component=191)
rtts = []
for _ in range(int(sys.argv[2])):
    t = time.monotonic_ns()
    c.mav.timesync_send(0, t)
    end = time.monotonic() + 0.5
    while time.monotonic() < end:
        m = c.recv_match(type="TIMESYNC", blocking=True, timeout=0.1)
        if m is not None and m.tc1 != 0 and m.ts1 == t:
            rtts.append((time.monotonic_ns() - t) / 1e6)
            break
    time.sleep(0.02)
print(json.dumps(rtts))
"""


def round_trip(path: str, pings: int) -> dict:
    """TIMESYNC round trips (ms) from a client on the host through the relay, or from one inside
    PX4's namespace straight to its port (``nsenter``), on a fresh PX4 at 1x."""
    wd = tempfile.TemporaryDirectory(prefix="pmon-px4-bench-")
    s = Px4Sitl(find_sitl(), speed=1, workdir=Path(wd.name)).start()
    try:
        time.sleep(3.0)
        if path == "relay":
            argv = [sys.executable, "-c", PING, s.talk_url("api"), str(pings)]
        else:
            port = links_of(s.instance)["api"][0]
            argv = ["nsenter", "-t", str(s.proc.pid), "-n", "-U", "--preserve-credentials", sys.executable, "-c",
                    PING, f"udpout:127.0.0.1:{port}", str(pings)] if os.geteuid() != 0 else \
                ["nsenter", "-t", str(s.proc.pid), "-n", sys.executable, "-c", PING, f"udpout:127.0.0.1:{port}",
                 str(pings)]
        out = subprocess.run(argv, capture_output=True, text=True, timeout=120, env=dict(os.environ, PYTHONPATH=""))
        rtts = json.loads(out.stdout.strip().splitlines()[-1]) if out.returncode == 0 else []
        if not rtts:
            return {"path": path, "error": (out.stderr.strip().splitlines() or ["no answer"])[-1]}
        rtts.sort()
        return {"path": path, "n": len(rtts), "median_ms": round(statistics.median(rtts), 3),
                "p95_ms": round(rtts[int(0.95 * (len(rtts) - 1))], 3)}
    finally:
        s.stop()
        wd.cleanup()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--speeds", default="1,3,5,8", help="speed factors (default 1,3,5,8)")
    ap.add_argument("--seconds", type=float, default=20.0, help="wall s measured per speed (default 20)")
    ap.add_argument("--pings", type=int, default=200, help="TIMESYNC round trips per path (default 200)")
    args = ap.parse_args()
    if (why := skip_reason()) is not None:
        print(f"bench/px4_link.py: {why}", file=sys.stderr)
        return 2
    out = {"load_avg_1m_start": round(os.getloadavg()[0], 2), "ratios": [], "round_trips": []}
    for sp in (float(x) for x in args.speeds.split(",")):
        r = ratio(sp, args.seconds)
        out["ratios"].append(r)
        print(f"speed {sp:g}: {r['sim_per_wall']} simulated s per wall s; relay {r['relay_cpu_pct']} % of a core, "
              f"PX4 {r['px4_cpu_pct']} %; {r['messages_per_wall_s']} messages/s on the offboard link", flush=True)
    for path in ("relay", "namespace"):
        r = round_trip(path, args.pings)
        out["round_trips"].append(r)
        print(f"TIMESYNC round trip, {path}: " + ", ".join(f"{k} {v}" for k, v in r.items() if k != "path"), flush=True)
    out["load_avg_1m_end"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
