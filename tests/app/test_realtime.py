"""Scheduling (onboard/app/realtime.py): ``pmon run --rt-priority N`` puts its io thread and tick
worker at SCHED_FIFO in a real process, says in one line where it may not, pins CPUs; ``pmon
gcs`` started as a program lowers itself to idle priority unless told not to."""
from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time

import pytest

from tests.support.processes import LineReader, stop_process

from onboard.app.realtime import parse_cpus

RUN = [sys.executable, "-m", "onboard.cli", "run", "--mavlink", "udpin:127.0.0.1:0", "--df", "127.0.0.1:0"]
# a process without the privileges real-time scheduling and memory locking need, as root
UNPRIVILEGED = ["setpriv", "--inh-caps=-sys_nice,-ipc_lock", "--bounding-set=-sys_nice,-ipc_lock",
                "prlimit", "--rtprio=0", "--memlock=65536"]


def _threads(pid: int) -> dict[str, tuple[int, int]]:
    """Thread name -> (policy, real-time priority) of each thread of ``pid``."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{tid}/comm") as f:
            name = f.read().strip()
        out[name] = (os.sched_getscheduler(int(tid)), os.sched_getparam(int(tid)).sched_priority)
    return out


def _status(pid: int, key: str) -> str:
    with open(f"/proc/{pid}/status") as f:
        return next(line.split(":", 1)[1].strip() for line in f if line.startswith(key + ":"))


def _start(argv: list[str], ready: str) -> tuple[subprocess.Popen, LineReader]:
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    out = LineReader(proc)
    out.wait_for(r"pmon run: mavlink", 60)
    out.wait_for(ready, 10)
    return proc, out


@pytest.mark.skipif(os.geteuid() != 0, reason="SCHED_FIFO and mlockall need root (or CAP_SYS_NICE, CAP_IPC_LOCK)")
@pytest.mark.timeout(120)
def test_rt_priority_puts_the_io_thread_and_the_worker_at_fifo_and_locks_memory():
    cpus = "1" if (os.cpu_count() or 1) > 1 else "0"
    proc, out = _start(RUN + ["--rt-priority", "10", "--cpu-affinity", cpus], r"pmon run: scheduling:")
    try:
        th = _threads(proc.pid)
        assert th["pmon-io"] == (os.SCHED_FIFO, 10), th
        assert th["pmon-worker"] == (os.SCHED_FIFO, 9), th
        assert th["pmon-watchdog"] == (os.SCHED_OTHER, 0) and th["pmon-df"] == (os.SCHED_OTHER, 0), th
        assert int(_status(proc.pid, "VmLck").split()[0]) > 0
        for tid in os.listdir(f"/proc/{proc.pid}/task"):  # threads started before and after the pinning
            assert os.sched_getaffinity(int(tid)) == {int(cpus)}
        assert not any("warning" in line for line in out.lines), out.lines
    finally:
        stop_process(proc)


@pytest.mark.skipif(shutil.which("setpriv") is None or shutil.which("prlimit") is None or os.geteuid() != 0,
                    reason="needs setpriv and prlimit (util-linux) and root to drop its capabilities")
@pytest.mark.timeout(120)
def test_where_fifo_and_mlock_are_refused_one_warning_and_the_app_runs_at_normal_scheduling():
    proc, out = _start(UNPRIVILEGED + RUN + ["--rt-priority", "10"], r"pmon run: warning:")
    try:
        warning = [line for line in out.lines if "warning" in line]
        assert len(warning) == 1, out.lines
        assert "memory not locked" in warning[0] and "pmon-io, pmon-worker at normal scheduling: SCHED_FIFO " \
            "refused (Operation not permitted" in warning[0], warning
        th = _threads(proc.pid)
        assert th["pmon-io"] == (os.SCHED_OTHER, 0) and th["pmon-worker"] == (os.SCHED_OTHER, 0), th
        assert proc.poll() is None  # it runs on
    finally:
        stop_process(proc)
    assert proc.returncode == 0 or proc.returncode == -15


def test_the_scenario_setting_and_cpu_lists():
    from onboard.config import ConfigError, load_scenario, override
    sc = load_scenario("paper")
    assert sc.app.rt_priority == 0  # normal scheduling unless asked
    assert override(sc, {"app.rt_priority": 20}).app.rt_priority == 20
    with pytest.raises(ConfigError, match="app.rt_priority"):
        override(sc, {"app.rt_priority": 99})  # the kernel's own
    assert parse_cpus("0") == (0,) and parse_cpus("0-1") == (0, 1) and parse_cpus("1,0") == (0, 1)
    for bad, why in (("x", "is not N or N-M"), ("1-0", "runs backwards"), ("999", "this computer has CPUs")):
        with pytest.raises(ValueError, match=why):
            parse_cpus(bad)
    res = subprocess.run(RUN + ["--cpu-affinity", "999"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1 and "this computer has CPUs" in res.stderr


def _gcs_nice(extra: list[str], env: dict | None = None) -> tuple[int, int]:
    """(scheduling policy, nice value) of a ``pmon gcs status`` process waiting for a vehicle that
    is silent."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    argv = [sys.executable, "-m", "onboard.cli", "gcs", *extra, "status", "--connect", f"udpin:127.0.0.1:{port}",
            "--timeout", "20"]
    base = {k: v for k, v in os.environ.items() if k != "PMON_GCS_NO_IDLE"}  # tests/conftest.py sets it
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env={**base, **(env or {})})
    try:
        # lowered, or its link opened (past its start, waiting for a heartbeat) at its priority;
        # an idle program's start beside a loaded machine's work can take tens of seconds
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            assert proc.poll() is None, proc.stderr.read()
            if os.getpriority(os.PRIO_PROCESS, proc.pid) == 19:
                return os.sched_getscheduler(proc.pid), 19
            with open(f"/proc/{proc.pid}/net/udp") as f:
                if any(f":{port:04X}" in line for line in f):
                    return os.sched_getscheduler(proc.pid), os.getpriority(os.PRIO_PROCESS, proc.pid)
            time.sleep(0.05)
        raise AssertionError("pmon gcs neither lowered itself nor opened its link in 90 s")
    finally:
        stop_process(proc)


@pytest.mark.timeout(300)
def test_a_ground_station_program_runs_at_nice_19_unless_told_not_to():
    assert _gcs_nice([]) == (os.SCHED_OTHER, 19)  # not SCHED_IDLE: that all but stops it beside busy processes
    assert _gcs_nice(["--no-idle"]) == (os.SCHED_OTHER, os.getpriority(os.PRIO_PROCESS, 0))
    assert _gcs_nice([], {"PMON_GCS_NO_IDLE": "1"}) == (os.SCHED_OTHER, os.getpriority(os.PRIO_PROCESS, 0))
