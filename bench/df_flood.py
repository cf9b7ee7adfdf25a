"""The onboard app's DF input under hostile floods, flown against the mock autopilot (issue 23).

    python -m bench.df_flood [--speedup 1] [--seconds 10]

One mission like bench/latency.py (mock autopilot + app in this process, ``pmon feed live`` as
the DF, a process of its own), the app accepting DF datagrams from host 127.0.0.1 (any port:
``--df-from 127.0.0.1``). Once it monitors, a hostile sender (a process of its own,
``python -m bench.df_flood send``) floods the DF port, one phase after the other:

  overflow  200 datagrams/s from 127.0.0.1 (an accepted host): integers too large for a float
            in ``t`` or a bearing (these raised OverflowError in the parser and stopped the io
            loop before issue 23);
  foreign   20 000 datagrams/s from 127.0.0.2 (not an accepted host): valid-looking datagrams.

Printed per phase: datagrams sent and the rate achieved, what the app did with them (rejected by
reason, dropped unparsed by reason), datagrams the kernel dropped on the DF socket (its drops
counter in /proc/net/udp), the CPU the DF reader thread used (and per datagram), the longest gap between the setpoints the autopilot received and
between the app's heartbeats; for the whole mission: bench/latency.py's missed ticks (a scan of
the feed not ticked, or a monitoring tick's setpoint late; 0 = every good scan used), errors
counted by the app's contained handlers, and log records carrying a traceback. Last line: JSON.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

OVERFLOW = [
    b'{"v":1,"t":1' + b"0" * 400 + b',"ch":0,"bearings_rad":[]}',
    b'{"v":1,"t":100.0,"ch":1,"bearings_rad":[0.5,-1' + b"0" * 400 + b']}',
]
FOREIGN = [b'{"v":1,"t":100.0,"ch":0,"bearings_rad":[0.5]}']
PAYLOADS = {"overflow": OVERFLOW, "foreign": FOREIGN}


def send(to: tuple[str, int], src_host: str, rate_hz: float, duration_s: float, kind: str) -> dict:
    """Send ``kind`` datagrams at ``rate_hz`` for ``duration_s`` from ``src_host`` (paced every
    ms against the wall clock, so the rate holds on average whatever a sendto costs)."""
    import socket

    payloads = PAYLOADS[kind]
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((src_host, 0))
    sent = errors = 0
    t0 = time.monotonic()
    try:
        while True:
            elapsed = time.monotonic() - t0
            if elapsed >= duration_s:
                break
            due = int(rate_hz * elapsed) + 1
            while sent < due:
                try:
                    s.sendto(payloads[sent % len(payloads)], to)
                except OSError:  # ENOBUFS / ECONNREFUSED (ICMP from a closed port): count, go on
                    errors += 1
                sent += 1
            time.sleep(0.001)
    finally:
        s.close()
    wall = time.monotonic() - t0
    return {"sent": sent, "send_errors": errors, "wall_s": round(wall, 3), "rate_hz": round(sent / wall, 1)}


def udp_drops(port: int) -> int:
    """The kernel's drops counter of the IPv4 UDP socket bound to ``port`` (/proc/net/udp)."""
    with open("/proc/net/udp") as f:
        next(f)
        for line in f:
            cols = line.split()
            if int(cols[1].split(":")[1], 16) == port:
                return int(cols[-1])
    return 0


def thread_cpu_s(native_id: int | None) -> float:
    """CPU seconds (user + system) a thread of this process has used (/proc/self/task/ID/stat)."""
    if native_id is None:
        return float("nan")
    with open(f"/proc/self/task/{native_id}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class TracebackCounter(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.n = 0
        self.first: str | None = None

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info:
            self.n += 1
            self.first = self.first or record.getMessage()


def _sender(ph: dict, port: int) -> subprocess.Popen:
    """The sender process of one phase (``python -m bench.df_flood send``), its figures on stdout."""
    return subprocess.Popen(
        [sys.executable, "-m", "bench.df_flood", "send", "--to", f"127.0.0.1:{port}",
         "--src", ph["src"], "--rate", str(ph["rate_hz"]), "--seconds", str(ph["seconds"]),
         "--kind", ph["kind"]], cwd=ROOT, stdout=subprocess.PIPE, text=True)


def _phase_figures(ph: dict, sent: dict, b: dict, a: dict, setpoints: list[float], hb_age: float) -> dict:
    """One phase's figures: what was sent, and the app's counters after (``a``) less before (``b``)."""
    gaps = [y - x for x, y in zip(setpoints[b["sp_n"]:], setpoints[b["sp_n"] + 1:a["sp_n"]])]
    return {
        "name": ph["name"], "kind": ph["kind"], "src": ph["src"], **sent,
        "rejected": {k: a["rejected"][k] - b["rejected"][k] for k in a["rejected"]
                     if a["rejected"][k] != b["rejected"][k]},
        "dropped_unparsed": {k: a["dropped"][k] - b["dropped"][k] for k in a["dropped"]
                             if a["dropped"][k] != b["dropped"][k]},
        "kernel_drops": a["kernel_drops"] - b["kernel_drops"],
        "reader_cpu_s": round(a["reader_cpu_s"] - b["reader_cpu_s"], 2),
        "reader_us_per_datagram": round((a["reader_cpu_s"] - b["reader_cpu_s"]) * 1e6
                                        / max(a["received"] - b["received"], 1), 2),
        "setpoints": a["sp_n"] - b["sp_n"],
        "setpoint_gap_s_max": round(max(gaps), 3) if gaps else None,
        "heartbeat_age_s_max": round(hb_age, 2),
        "handler_errors": a["errors"] - b["errors"],
        "mission_s": round((a["t"] or 0) - (b["t"] or 0), 1),
    }


def flood(phases: list[dict], speedup: float, seed: int = 1, warm_ticks: int = 3, log=print) -> dict:
    """Fly, and once the app monitors (``warm_ticks`` planned ticks in), run each phase
    (``{"name", "kind", "rate_hz", "seconds", "src"}``) one after the other from a sender
    process; returns the figures (see the module doc)."""
    from bench import latency
    from onboard.app.contract import State
    from onboard.app.df.udp_input import Source

    tb = TracebackCounter()
    logging.getLogger("pmon").addHandler(tb)
    out = {"phases": []}
    st = {"i": 0, "proc": None, "t0": None, "before": None, "hb_age": 0.0, "done": False}
    setpoints: list[float] = []  # autopilot time of each setpoint received

    def on_app(app):
        if st["done"]:
            return
        monitoring = app.state == State.MONITORING and sum(1 for t in app.ticks if t["planned"]) >= warm_ticks
        proc = st["proc"]
        if proc is None:
            if not monitoring:
                return
            ph = phases[st["i"]]
            st["before"], st["hb_age"], st["t0"] = _snapshot(app, setpoints), 0.0, time.monotonic()
            st["proc"] = _sender(ph, app.sensor_port)
            log(f"phase {ph['name']}: {ph['rate_hz']:g} datagrams/s from {ph['src']} for {ph['seconds']:g} s "
                f"(mission t {app.clock.now():.0f} s)")
            return
        st["hb_age"] = max(st["hb_age"], app.mono() - app.publisher.heartbeat_local)
        if proc.poll() is None:
            return
        time.sleep(1.0)  # let the app drain what is queued
        sent = json.loads(proc.stdout.read().strip().splitlines()[-1])
        out["phases"].append(_phase_figures(phases[st["i"]], sent, st["before"], _snapshot(app, setpoints), setpoints,
                                            st["hb_age"]))
        log(f"  {out['phases'][-1]}")
        st["proc"], st["i"] = None, st["i"] + 1
        st["done"] = st["i"] == len(phases)

    # mission s from arming (the feed's duration): the launch (monitoring ~20 s after boot,
    # measured), each phase (its wall seconds + ~2 s to read it back), a margin
    duration = 40.0 + sum(p["seconds"] + 3.0 for p in phases) * speedup
    try:
        run = latency.fly(duration, speedup, seed, cfg_extra={"df_sources": (Source("127.0.0.1"),)},
                          on_app=on_app, on_setpoint=lambda msg: setpoints.append(time.monotonic()),
                          after=lambda app: out.update(_app_end(app)))
    finally:
        logging.getLogger("pmon").removeHandler(tb)
        if st["proc"] is not None and st["proc"].poll() is None:
            st["proc"].kill()
    out["phases_done"] = len(out["phases"]) == len(phases)
    return {**out, **_run_figures(run, tb, speedup)}


def _snapshot(app, setpoints: list[float]) -> dict:
    """The app's DF and setpoint counts now (a phase's figures are two of these apart)."""
    return {"rejected": dict(app.scans.rejected), "dropped": dict(app.df.dropped),
            "kernel_drops": udp_drops(app.sensor_port), "sp_n": len(setpoints),
            "t": app.clock.now(), "errors": app.errors.total, "received": app.df.received,
            "reader_cpu_s": thread_cpu_s(app.df.thread_id)}


def _app_end(app) -> dict:
    """The app's errors and state at the end of the flight."""
    from onboard.app.contract import State
    return {"app_errors": dict(app.errors.counts), "io_errors": app.counters.get("io_errors", 0),
            "tick_errors": app.counters.get("tick_errors", 0), "watchdog": dict(app.watchdog.counts),
            "state_end": State(app.state).name}


def _run_figures(run: dict, tb, speedup: float) -> dict:
    """The flight's tick figures, the tracebacks logged, the speed-up asked and achieved."""
    f = run["figures"]
    out = {k: f[k] for k in ("scans", "ticks", "monitoring_ticks", "ticks_missed", "ticks_late",
                             "scans_unticked", "ticks_skipped")}
    out["tracebacks_logged"] = tb.n
    out["first_traceback"] = tb.first
    out["speedup"] = speedup
    out["achieved_speedup"] = round(run["achieved_speedup"], 2)
    out["load_avg_1m_end"] = round(os.getloadavg()[0], 2)
    return out


PHASES = [
    {"name": "overflow", "kind": "overflow", "rate_hz": 200.0, "src": "127.0.0.1"},
    {"name": "foreign", "kind": "foreign", "rate_hz": 20000.0, "src": "127.0.0.2"},
]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd")
    s = sub.add_parser("send", help="the hostile sender (one phase); prints one JSON line")
    s.add_argument("--to", required=True, metavar="HOST:PORT")
    s.add_argument("--src", default="127.0.0.1", help="source address to bind")
    s.add_argument("--rate", type=float, required=True, help="datagrams/s")
    s.add_argument("--seconds", type=float, required=True)
    s.add_argument("--kind", choices=sorted(PAYLOADS), required=True)
    p.add_argument("--speedup", type=float, default=1.0, help="mock autopilot speedup (default 1)")
    p.add_argument("--seconds", type=float, default=10.0, help="wall seconds per phase (default 10)")
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args(argv)
    if args.cmd == "send":
        host, _, port = args.to.rpartition(":")
        print(json.dumps(send((host, int(port)), args.src, args.rate, args.seconds, args.kind)), flush=True)
        return 0
    phases = [dict(ph, seconds=args.seconds) for ph in PHASES]
    r = flood(phases, args.speedup, args.seed)
    print(f"missed ticks {r['ticks_missed']} ({r['scans']} scans, {r['ticks']} ticked, "
          f"{r['monitoring_ticks']} monitoring); tracebacks {r['tracebacks_logged']}, io errors "
          f"{r['io_errors']}, tick errors {r['tick_errors']}; {r['achieved_speedup']}x, "
          f"load {r['load_avg_1m_end']}")
    print(json.dumps(r))
    return 0


if __name__ == "__main__":
    sys.exit(main())
