"""How soon ``pmon run`` tells a service manager it is ready, and how often it feeds the watchdog:
the app started as systemd would start it (``$NOTIFY_SOCKET``, ``$WATCHDOG_USEC``), its notify
datagrams received here with their time since the exec (no autopilot: ``udpin`` on a free port).

    python -m bench.service_start [--runs 3] [--watchdog-s 10]
"""
from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time


def once(watchdog_s: float, pings: int) -> list[tuple[float, str]]:
    d = tempfile.mkdtemp(prefix="pmon-notify-", dir="/tmp")  # AF_UNIX paths: <= 107 bytes
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.bind(os.path.join(d, "notify"))
        sock.settimeout(60)
        t0 = time.monotonic()
        env = {**os.environ, "NOTIFY_SOCKET": os.path.join(d, "notify"), "WATCHDOG_USEC": str(int(watchdog_s * 1e6))}
        proc = subprocess.Popen([sys.executable, "-m", "onboard.cli", "run", "--mavlink", "udpin:127.0.0.1:0",
                                 "--df", "127.0.0.1:0"], env=env, stdout=subprocess.DEVNULL)
        got: list[tuple[float, str]] = []
        try:
            while sum(m == "WATCHDOG=1" for _, m in got) < pings:
                m = sock.recv(256).decode()
                got.append((time.monotonic() - t0, m))
        finally:
            proc.terminate()
            proc.wait(10)
        return got
    finally:
        sock.close()
        shutil.rmtree(d, ignore_errors=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--watchdog-s", type=float, default=10.0)
    args = ap.parse_args()
    for _ in range(args.runs):
        got = once(args.watchdog_s, 3)
        ready = next(t for t, m in got if m == "READY=1")
        pings = [t for t, m in got if m == "WATCHDOG=1"]
        gaps = ", ".join(f"{b - a:.2f}" for a, b in zip(pings, pings[1:]))
        print(f"READY=1 {ready:.2f} s after the exec; WATCHDOG=1 every {gaps} s (WatchdogSec {args.watchdog_s:g})")
    print(f"load average {os.getloadavg()[0]:.1f}, {os.cpu_count()} CPUs")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
