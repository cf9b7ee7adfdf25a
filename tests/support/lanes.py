"""The suite's two lanes (tests/README.md, "Two lanes"): the whole suite run as ``python -m pytest``
(no paths given) is split between this process, the flights lane (every test that flies or
times anything, one at a time at normal priority), and a second pytest process started here with
the same arguments, the compute lane (the pure tests tests/conftest.py lists), which lowers itself
to nice 19 (and SCHED_IDLE) so that it only takes CPU the flights lane leaves idle. Given paths,
``--collect-only``, ``--lf``/``--ff``/``--sw``, or ``PMON_TEST_LANES=0``, the run stays in one
process."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time

import pytest

LANE_ENV = "PMON_TEST_LANE"  # "compute" in the compute lane's process (set by the flights lane)
OFF_ENV = "PMON_TEST_LANES"  # "0": no split
COMPUTE_NICE = 19
# the compute lane's per-test timeout (pytest-timeout's, wall clock): at nice 19 beside busy
# processes it gets a sliver of a core, and a pure test must not fail for being slow there
COMPUTE_TIMEOUT_S = 7200
# markers only the flights lane may run: a compute-listed module that carries one is misfiled
FLIGHT_MARKERS = ("sitl", "firmware", "ardupilot", "px4", "load")


def module_of(item) -> str:
    """The test's file relative to the repository, with '/' (as tests/conftest.py lists them)."""
    return os.path.relpath(str(item.path), str(item.config.rootpath)).replace(os.sep, "/")


def is_compute(item, modules: frozenset, flights: frozenset) -> bool:
    """In the compute lane: its module is listed and the test (by name without parameters) is not
    one of that module's flights."""
    name = item.nodeid.split("[", 1)[0]
    return module_of(item) in modules and name not in flights


def split_wanted(config) -> bool:
    """The whole suite by ``python -m pytest`` in a process that is not already a lane."""
    o = config.option
    return (os.environ.get(OFF_ENV, "1") != "0" and LANE_ENV not in os.environ
            and "PYTEST_XDIST_WORKER" not in os.environ
            and config.args_source == pytest.Config.ArgsSource.TESTPATHS
            and not (o.collectonly or o.help or o.version or getattr(o, "lf", False)
                     or getattr(o, "failedfirst", False) or getattr(o, "stepwise", False)
                     or getattr(o, "numprocesses", None)))


def become_compute() -> None:
    """The compute lane lowers its own priority (and its children's: they inherit it). It stays in
    the flights lane's session: where the kernel schedules by session (autogroup), nice orders
    the tasks inside one, so the lane yields to every process of the flights lane's session (the
    tests, the app, the mock, the clients), while a firmware SITL (a session of its own) keeps
    its session's share; a lane in a session of its own at nice 19 would yield to every other
    session on the machine too, and wait out other work's load."""
    os.nice(COMPUTE_NICE - os.nice(0))
    # and SCHED_IDLE where the kernel has it (no privilege needed): a waking flight preempts it at
    # once, also when the flights lane itself runs niced (nice 10 beside nice 19 is not enough)
    if hasattr(os, "SCHED_IDLE"):
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        except OSError:
            pass


def _die_with_parent() -> None:  # the compute lane ends when the flights lane's process does
    try:
        import ctypes
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class ComputeLane:
    """The compute lane's process: started with the flights lane's own arguments (so the same
    ``-m``, ``-k`` and options select from the same suite), its output in a log file."""

    def __init__(self, config):
        args = [a for a in config.invocation_params.args if a != "--cache-clear"]
        fd, self.log = tempfile.mkstemp(prefix="pmon-compute-lane-", suffix=".log")
        self.t0 = time.time()  # wall clock: the log file's mtime says when the lane's last line came
        # no cache: the flights lane's process writes the last-failed list (two writers race)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "pytest", *args, "-p", "no:cacheprovider", "-o", f"timeout={COMPUTE_TIMEOUT_S}"],
            cwd=str(config.invocation_params.dir), stdin=subprocess.DEVNULL, stdout=fd,
            stderr=subprocess.STDOUT, env={**os.environ, LANE_ENV: "compute"},
            preexec_fn=_die_with_parent)
        os.close(fd)
        self.rc: int | None = None
        self.wall_s = 0.0

    def wait(self) -> int:
        try:
            self.rc = self.proc.wait()
        except BaseException:
            self.stop()
            raise
        # until its last line (its summary), not until now: the flights lane is often the later
        self.wall_s = max(0.0, os.path.getmtime(self.log) - self.t0)
        return self.rc

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def output(self) -> str:
        with open(self.log, errors="replace") as f:
            return f.read()


def merged_exit(flights: int, compute: int) -> int:
    """The run's exit code: a lane that selected no test (5) does not fail a lane that ran."""
    codes = [int(c) for c in (flights, compute) if int(c) != pytest.ExitCode.NO_TESTS_COLLECTED]
    return max(codes) if codes else int(pytest.ExitCode.NO_TESTS_COLLECTED)
