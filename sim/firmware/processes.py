"""The programs of a SITL flight as child processes: ``Proc`` (any program, its output collected
and logged), ``MockProcess`` (the mock autopilot, ``python -m sim.mock.autopilot``, with the interface
and port layout of sim.firmware.ardupilot.ArduPilotSitl, so a flight starts either the same way). The
parts of sim/stack/rig.py's stack of processes."""
from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping


def log_tail(path: Path, start: int, n: int = 4) -> str:
    """The last ``n`` non-empty lines a program printed since byte ``start`` of its log, joined by
    " | ": what a boot failure's one-line error quotes."""
    try:
        with open(path, "rb") as f:
            f.seek(start)
            text = f.read()[-4000:].decode("utf-8", "replace")
    except OSError as exc:
        return f"its log unreadable: {exc}"
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return " | ".join(lines[-n:]) or "it printed nothing"


class Proc:
    """A child process whose stdout lines are collected on a thread."""

    def __init__(self, name: str, argv: list[str], log_path: Path, priority: int = 0):
        """``priority``: started at SCHED_FIFO ``priority`` (0: normal scheduling; sim/firmware/priority.py)."""
        from sim.firmware.priority import fifo_argv

        self.name = name
        self.lines: "queue.Queue[str]" = queue.Queue()
        self.log = open(log_path, "w", buffering=1)
        env = dict(os.environ, PYTHONUNBUFFERED="1", MAVLINK20="1")
        self.p = subprocess.Popen(fifo_argv(argv, priority), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        self._t = threading.Thread(target=self._pump, daemon=True)
        self._t.start()

    def _pump(self) -> None:
        for line in self.p.stdout:
            self.log.write(line)
            self.lines.put(line.rstrip("\n"))

    def wait_line(self, pattern: str, timeout: float) -> re.Match:
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                if self.p.poll() is not None:
                    break
                continue
            if m := rx.search(line):
                return m
        raise RuntimeError(f"{self.name} did not print /{pattern}/ within {timeout:.0f} s "
                           f"(exit code {self.p.poll()}); see {self.log.name}")

    def stop(self, timeout: float = 5.0) -> None:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)
            try:
                self.p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(timeout=5)
        self._t.join(timeout=2)
        self.log.close()


@dataclass(frozen=True)
class MockLinks:
    """The mock process's MAVLink links on 127.0.0.1: ``tcp`` TCP ports (``MockProcess.port``);
    ``udp_out``: also stream to a ground station listening on udp PORT; ``udpin``: also listen on
    a UDP port (``MockProcess.udpin_port``)."""
    tcp: int
    udp_out: int | None = None
    udpin: bool = False


class MockProcess:
    """The mock autopilot (``python -m sim.mock.autopilot``, ArduCopter's boot by default) as a process
    with ArduPilotSitl's interface and port layout, so a Mission flies either."""

    def __init__(self, home: tuple[float, ...], speedup: float, params: Mapping[str, float],
                 links: MockLinks, log_path: Path, seed: int = 1, ready_s: float | None = None,
                 signing_key_path: str | None = None):
        """``ready_s``: autopilot s until it can arm (None: ArduCopter's); ``signing_key_path``:
        MAVLink 2 signing."""
        self.home, self.speedup, self.params, self.ports = home, speedup, dict(params), links.tcp
        self.log_path, self.seed, self.ready_s, self.udp_out = log_path, seed, ready_s, links.udp_out
        self.udpin, self.signing_key_path = links.udpin, signing_key_path
        self.proc = None
        self._ports: list[int] = []
        self.udpin_port: int | None = None
        self.boots = 0

    def start(self) -> "MockProcess":
        argv = [sys.executable, "-m", "sim.mock.autopilot", "--speedup", f"{self.speedup:g}",
                f"--home={self.home[0]},{self.home[1]},{self.home[2]}", "--seed", str(self.seed),
                "--max-lag", "0.1"]
        argv += ["--tcp", "127.0.0.1:0"] * self.ports
        argv += [f"--param={k}={v}" for k, v in self.params.items()]
        if self.ready_s is not None:
            argv += ["--ready-after", f"{self.ready_s:g}"]
        if self.udp_out is not None:
            argv += ["--udp", f"127.0.0.1:{self.udp_out}"]
        if self.udpin:
            argv += ["--udpin", "127.0.0.1:0"]
        if self.signing_key_path is not None:
            argv += ["--signing-key", str(self.signing_key_path)]
        from sim.firmware.priority import vehicle_priority

        self.proc = Proc("mock autopilot", argv, self.log_path, vehicle_priority())
        m = self.proc.wait_line(r"mock autopilot up: (.*)", 20)
        self._ports = [int(x) for x in re.findall(r"tcpin:127\.0\.0\.1:(\d+)", m.group(1))]
        udpin = re.search(r"udpin:127\.0\.0\.1:(\d+)", m.group(1))
        self.udpin_port = int(udpin.group(1)) if udpin else None
        self.boots += 1
        return self

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.p.poll() is None

    def port(self, serial: int) -> int:
        return self._ports[serial]

    def url(self, serial: int) -> str:
        return f"tcp:127.0.0.1:{self.port(serial)}"

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.stop(timeout=10)
            self.proc = None
