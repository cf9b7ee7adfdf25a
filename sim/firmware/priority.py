"""The simulated flight's scheduling: the product's own (docs/DEPLOY.md), so a busy machine (a
second pytest worker, a build, a browser) takes no CPU from a flight.

On a vehicle the autopilot, the DF receiver and the companion are separate computers, and the app
on the companion runs at ``pmon run --rt-priority N``. In simulation they share one machine, so
with ``PMON_SIM_RT_PRIORITY=N`` (N in 1..97) the rig starts the app at ``--rt-priority N`` (its io
thread FIFO N, its worker N - 1) and every process standing in for the vehicle's other computers
(the firmware's SITL, the mock autopilot, the DF feed) at SCHED_FIFO N + 1. Unset or 0: normal
scheduling, as a user's ``pmon demo`` runs. tests/conftest.py sets 40 where SCHED_FIFO is
permitted (root, CAP_SYS_NICE or RLIMIT_RTPRIO), so every flight the suite flies is scheduled as
the docs tell an integrator to schedule the app.

The kernel's real-time throttling (sched_rt_runtime_us, 95 % of each second by default) keeps a
runaway FIFO process from taking a whole core.
"""
from __future__ import annotations

import os
import shutil
import subprocess
from typing import Sequence

ENV = "PMON_SIM_RT_PRIORITY"
MAX_APP_PRIORITY = 97  # the vehicle one above it, below the kernel's own 99


def app_priority() -> int:
    """The app's real-time priority from ``PMON_SIM_RT_PRIORITY`` (0: normal scheduling).
    ValueError naming the variable when it is not an integer in 0..97."""
    text = os.environ.get(ENV, "").strip()
    if not text:
        return 0
    if not (text.isascii() and text.isdigit()) or int(text) > MAX_APP_PRIORITY:
        raise ValueError(f"{ENV}={text!r}: expected an integer 0..{MAX_APP_PRIORITY}")
    return int(text)


def vehicle_priority() -> int:
    """SCHED_FIFO priority of the processes standing in for the vehicle's other computers (0: normal)."""
    n = app_priority()
    return n + 1 if n else 0


def fifo_argv(argv: Sequence[str], priority: int) -> list[str]:
    """``argv`` started at SCHED_FIFO ``priority`` by ``chrt`` (its threads inherit it); as it is
    for 0 or where there is no chrt."""
    chrt = shutil.which("chrt")
    return [chrt, "-f", str(priority), *argv] if priority > 0 and chrt else list(argv)


def fifo_permitted(priority: int) -> bool:
    """Whether this process may start a program at SCHED_FIFO ``priority`` (tried with ``chrt``)."""
    chrt = shutil.which("chrt")
    if chrt is None:
        return False
    try:
        return subprocess.run([chrt, "-f", str(priority), "true"], capture_output=True, timeout=10).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


def vehicle_threads(*threads) -> None:
    """Started threads of this process that stand in for the vehicle's other computers (the
    in-process mock autopilot's simulation, a scripted DF) at SCHED_FIFO ``vehicle_priority()``,
    as their processes would be; nothing at 0. A refusal leaves a thread at normal scheduling."""
    priority = vehicle_priority()
    if not priority:
        return
    for th in threads:
        if th is not None and th.native_id is not None:
            try:
                os.sched_setscheduler(th.native_id, os.SCHED_FIFO, os.sched_param(priority))
            except OSError:
                pass


def app_config_priority() -> dict:
    """The AppConfig field an in-process app takes to run as ``pmon run --rt-priority`` would."""
    return {"rt_priority": app_priority()}
