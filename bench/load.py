"""The onboard app under background load: a short mock-autopilot flight (bench/latency.py's, the
app and the mock in this process, the DF feed a process) or the documented procedure on a
firmware's SITL (``--procedure ardupilot|px4``: bench/ardupilot.py, every program a process)
beside N busy processes at normal priority (and, with ``--disk`` and ``--udp-mbps``, a disk writer
and a video-like UDP stream), with or without the app's real-time threads.

    python -m bench.load [--busy 2] [--disk] [--udp-mbps R] [--duration 100] [--speedup 1] [--rt-priority 0]
    python -m bench.load --procedure ardupilot [--busy 2] [--duration 100] [--speedup 2] [--rt-priority 0]

``--rt-priority N``: the app's io thread at SCHED_FIFO N and its worker at N - 1 (as ``pmon run
--rt-priority``), and the simulated vehicle (the mock's thread, the feed process: on a vehicle
they are other computers) at N + 1, so the busy processes compete with the companion's
programs only. Prints the ticks the app missed (TickAccount: skipped, late, unticked), its
overruns by stage, each stage's time (median, p95, max ms over the flight's ticks), the load
average, and the processes that used the most CPU beside it (other work on the machine).
Last line: JSON figures.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

from bench import latency

from onboard.app.contract import OVERRUN_STAGES
from onboard.app.realtime import set_fifo

ROOT = Path(__file__).resolve().parents[1]

BUSY = "while True: pass"
# a logger or a recorder: 4 MiB written and fsynced, over and over, to a file of its own
DISK = ("import os, sys, tempfile\n"
        "fd, path = tempfile.mkstemp(prefix='pmon-load-'); os.unlink(path); block = os.urandom(4 << 20)\n"
        "while True:\n    os.lseek(fd, 0, 0); os.write(fd, block); os.fsync(fd)\n")
# a video-like stream: RATE Mbit/s of 1316-byte datagrams (7 MPEG-TS packets) to a loopback sink
UDP = ("import socket, sys, time\n"
       "rate = float(sys.argv[1]) * 1e6 / 8 / 1316\n"
       "sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); sink.bind(('127.0.0.1', 0))\n"
       "s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM); payload = bytes(1316); t = time.monotonic()\n"
       "while True:\n"
       "    s.sendto(payload, sink.getsockname()); sink.recv(2048); t += 1 / rate\n"
       "    d = t - time.monotonic()\n"
       "    if d > 0: time.sleep(d)\n")


def _background(args) -> list[subprocess.Popen]:
    """The load beside the flight: ``--busy`` CPU-bound processes, ``--disk`` a writer, ``--udp-mbps``
    a stream; all at normal priority."""
    procs = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(args.busy)]
    if args.disk:
        procs.append(subprocess.Popen([sys.executable, "-c", DISK]))
    if args.udp_mbps > 0:
        procs.append(subprocess.Popen([sys.executable, "-c", UDP, str(args.udp_mbps)]))
    return procs


def _vehicle_side_fifo(app, rig_feed_pid: int | None, priority: int) -> list[str]:
    """The mock's thread and the feed process at SCHED_FIFO ``priority``: what went wrong, if anything."""
    problems = []
    for th in threading.enumerate():
        if th.name == "mock-autopilot" and th.native_id is not None and not set_fifo(th.native_id, priority).ok:
            problems.append("mock thread")
    if rig_feed_pid is not None:
        res = subprocess.run(["chrt", "-a", "-f", "-p", str(priority), str(rig_feed_pid)], capture_output=True)
        if res.returncode != 0:
            problems.append("feed process")
    return problems


def _quantiles(xs: list[float]) -> dict:
    if not xs:
        return {"median": None, "p95": None, "max": None}
    s = sorted(xs)
    return {"median": round(s[len(s) // 2], 1), "p95": round(s[min(int(0.95 * len(s)), len(s) - 1)], 1),
            "max": round(s[-1], 1)}


def _top_cpu(exclude: set[int], n: int = 6) -> list[str]:
    """The processes with the most CPU (cumulative share since their start), this bench's excluded."""
    out = subprocess.run(["ps", "-eo", "pid,pcpu,etimes,args", "--sort=-pcpu"], capture_output=True, text=True).stdout
    rows = []
    for line in out.splitlines()[1:]:
        pid, pcpu, etimes, cmd = line.split(None, 3)
        if int(pid) not in exclude and float(pcpu) >= 5.0:
            rows.append(f"{cmd[:70]} {pcpu}% (up {etimes} s)")
    return rows[:n]


def _descendants() -> dict[int, list[bytes]]:
    """This process's descendants: pid -> argv."""
    parent, argv = {}, {}
    for pid in (int(d) for d in os.listdir("/proc") if d.isdigit()):
        try:
            with open(f"/proc/{pid}/stat") as f:
                parent[pid] = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                argv[pid] = f.read().split(b"\0")
        except (OSError, ValueError, IndexError):
            continue
    out, frontier = {}, {os.getpid()}
    while frontier:
        frontier = {p for p, pp in parent.items() if pp in frontier and p not in out}
        out.update({p: argv.get(p, []) for p in frontier})
    return out


def procedure(args) -> int:
    """bench/ardupilot.py beside the busy processes; with --rt-priority the SITL firmware and the
    feed (the vehicle side) at FIFO N + 1, found among the descendants as they start."""
    import tempfile
    import time
    if args.speedup == 1.0:
        args.speedup = 2.0  # the procedure's own default, the firmware tests' speed
    busy = _background(args)
    boosted: set[int] = set()
    with tempfile.TemporaryDirectory() as out:
        argv = [sys.executable, "-m", "bench.ardupilot", "--autopilot", args.procedure,
                "--monitor", f"{args.duration:g}", "--speedup", f"{args.speedup:g}", "--seed", str(args.seed),
                "--out", out, "--rt-priority", str(args.rt_priority)]
        try:
            proc = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True, cwd=ROOT)
            while proc.poll() is None:
                if args.rt_priority > 0:
                    for pid, a in _descendants().items():
                        vehicle = any(x.endswith((b"arducopter", b"px4")) for x in a[:1]) or b"sim.stack.feed" in a
                        if vehicle and pid not in boosted:
                            boosted.add(pid)
                            subprocess.run(["chrt", "-a", "-f", "-p", str(args.rt_priority + 1), str(pid)],
                                           capture_output=True)
                time.sleep(0.5)
            top = _top_cpu({os.getpid(), *(p.pid for p in busy)})
            lines = proc.stdout.read().splitlines()
        finally:
            for p in busy:
                p.kill()
                p.wait()
        recs = [json.loads(line) for line in Path(out, "run.jsonl").read_text().splitlines()] \
            if Path(out, "run.jsonl").exists() else []
    if proc.returncode != 0 or not lines:
        print(f"bench/load.py: bench/ardupilot.py failed ({proc.returncode})", file=sys.stderr)
        return 1
    f = json.loads(lines[-1])
    overruns: dict[str, int] = {}
    for r in recs:
        if r.get("overrun"):
            overruns[r["overrun"]] = overruns.get(r["overrun"], 0) + 1
    stages = {s: _quantiles([r["stage_ms"][s] for r in recs if r.get("stage_ms") and r["channels"]])
              for s in OVERRUN_STAGES[1:]}
    out_ = {"procedure": args.procedure, "busy": args.busy, "disk": args.disk, "udp_mbps": args.udp_mbps,
            "rt_priority": args.rt_priority, "speedup": args.speedup,
            "cpus": os.cpu_count(), "vehicle_side_boosted": len(boosted),
            **{k: f.get(k) for k in ("monitoring_ticks", "ticks", "scans", "ticks_skipped", "ticks_late",
                                     "setpoint_delay_s_median", "autopilot_crashes", "wall_s")},
            "overruns": overruns, "stage_ms": stages, "load_avg_1m_end": round(os.getloadavg()[0], 2),
            "beside": top}
    print(lines[-2] if len(lines) > 1 else "")
    print(f"{args.busy} busy processes, rt priority {args.rt_priority or 'none'}: overruns {overruns or 'none'}")
    for s, q in stages.items():
        print(f"  {s:10s} median {q['median']} ms, p95 {q['p95']} ms, max {q['max']} ms")
    print(f"  beside it: {', '.join(top) or 'nothing above 5 % CPU'}")
    print(json.dumps(out_))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--busy", type=int, default=2, help="busy processes at normal priority beside the flight")
    ap.add_argument("--disk", action="store_true", help="and a process writing and fsyncing 4 MiB over and over")
    ap.add_argument("--udp-mbps", type=float, default=0.0, metavar="R",
                    help="and a process streaming R Mbit/s of UDP datagrams over loopback (video-like)")
    ap.add_argument("--duration", type=float, default=100.0, help="mission seconds of DF scans (default 100)")
    ap.add_argument("--speedup", type=float, default=1.0)
    ap.add_argument("--rt-priority", type=int, default=0, help="0: normal scheduling (default)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--procedure", choices=("mock", "ardupilot", "px4"), default="mock",
                    help="mock: the in-process mock flight (default); ardupilot, px4: bench/ardupilot.py's "
                    "procedure on that SITL (--duration s of monitoring, --speedup default 2)")
    args = ap.parse_args()
    if args.procedure != "mock":
        return procedure(args)
    busy = _background(args)
    state: dict = {"fifo_problems": None, "records": []}

    def on_app(app):
        if args.rt_priority > 0 and state["fifo_problems"] is None:
            state["fifo_problems"] = _vehicle_side_fifo(
                app, next((p for p, a in _descendants().items() if b"sim.stack.feed" in a), None), args.rt_priority + 1)

    def after(app):
        state["records"] = list(app.ticks)
    try:
        extra = {"rt_priority": args.rt_priority} if args.rt_priority > 0 else {}
        run = latency.fly(args.duration, args.speedup, args.seed, cfg_extra=extra, on_app=on_app, after=after)
        top = _top_cpu({os.getpid(), *(p.pid for p in busy)})
    finally:
        for p in busy:
            p.kill()
            p.wait()
    f = latency.figures(run, args.duration, args.speedup)
    app, recs = run["app"], state["records"]
    c = app.counters
    stages = {s: _quantiles([r["stage_ms"][s] for r in recs if r.get("stage_ms") and r["channels"]])
              for s in OVERRUN_STAGES[1:]}
    out = {"busy": args.busy, "disk": args.disk, "udp_mbps": args.udp_mbps, "rt_priority": args.rt_priority, "cpus": os.cpu_count(),
           "app_threads": {k: o.text for k, o in app.realtime.items()},
           "vehicle_side_fifo_problems": state["fifo_problems"],
           "monitoring_ticks": f["monitoring_ticks"], "ticks_missed": f["ticks_missed"],
           "ticks_late": f["ticks_late"], "ticks_skipped": f["ticks_skipped"], "scans_unticked": f["scans_unticked"],
           "overruns": {s: c.get(f"overruns_{s}", 0) for s in OVERRUN_STAGES if c.get(f"overruns_{s}", 0)},
           "stage_ms": stages, "latency_ms_median": f["latency_ms_median"],
           "achieved_speedup": f["achieved_speedup"], "clock_slips": f["clock_slips"],
           "feed_late_scans": f["feed_late_scans"], "wall_s": f["wall_s"],
           "load_avg_1m_end": f["load_avg_1m_end"], "beside": top}
    print(f"{args.busy} busy processes, rt priority {args.rt_priority or 'none'}: {out['monitoring_ticks']} "
          f"monitoring ticks, missed {out['ticks_missed']} (late {out['ticks_late']}, skipped "
          f"{out['ticks_skipped']}), overruns {out['overruns'] or 'none'}; load {out['load_avg_1m_end']}")
    for s, q in stages.items():
        print(f"  {s:10s} median {q['median']} ms, p95 {q['p95']} ms, max {q['max']} ms")
    print(f"  beside it: {', '.join(top) or 'nothing above 5 % CPU'}")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
