"""Scheduling: the app's real-time threads above everything else on the companion computer, and
the product's other programs below it (docs/DEPLOY.md).

A companion computer is never idle (video, a telemetry router, logging); at normal scheduling a
busy neighbour takes CPU from the tick whenever the kernel decides. Linux's answer is the
scheduler: ``pmon run --rt-priority N`` (``app.rt_priority``) puts the io thread (MAVLink reader,
setpoint stream, tick schedule) at SCHED_FIFO N and the tick worker at N - 1, so the short io
work preempts a long tick on a shared core (FIFO does not time-slice equal priorities), and
both preempt every normal process. Where that is not permitted (no CAP_SYS_NICE, RLIMIT_RTPRIO
below N) each refusal is one warning and the thread stays at normal scheduling. Memory is
locked (mlockall) so a tick never waits on a page fault to disk; ``--cpu-affinity`` pins the
process. Ground-station programs started on the companion lower themselves (``lower_priority``).

Linux only (os.sched_*, /proc); elsewhere each step reports that it is not available.
Light module (no numpy): the ground station imports it.
"""
from __future__ import annotations

import ctypes
import os
from dataclasses import dataclass

MAX_PRIORITY = 98  # SCHED_FIFO 99 is the kernel's own (watchdog, migration threads)
MCL_CURRENT, MCL_FUTURE, MCL_ONFAULT = 1, 2, 4  # <sys/mman.h>


@dataclass(frozen=True)
class Outcome:
    """What one step did: ``ok`` it took effect; ``text`` one line for the log either way."""

    ok: bool
    text: str


def parse_cpus(text: str) -> tuple[int, ...]:
    """``0,2-3`` -> (0, 2, 3); ValueError naming what is wrong (ranges ascending, CPUs that exist)."""
    cpus: set[int] = set()
    for part in (p.strip() for p in text.split(",")):
        lo, sep, hi = part.partition("-")
        if not (lo.isascii() and lo.isdigit()) or (sep and not (hi.isascii() and hi.isdigit())):
            raise ValueError(f"CPU list {text!r}: {part!r} is not N or N-M")
        a, b = int(lo), int(hi) if sep else int(lo)
        if b < a:
            raise ValueError(f"CPU list {text!r}: range {part!r} runs backwards")
        cpus.update(range(a, b + 1))
    online = os.cpu_count() or 1
    if max(cpus) >= online:
        raise ValueError(f"CPU list {text!r}: this computer has CPUs 0-{online - 1}")
    return tuple(sorted(cpus))


def _tasks() -> list[int]:
    """Thread ids of this process (Linux), else the calling thread's pid."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [0]


def set_affinity(cpus: tuple[int, ...]) -> Outcome:
    """Every thread of the process (and every one it starts later: they inherit) on ``cpus``."""
    try:
        for tid in _tasks():
            os.sched_setaffinity(tid, cpus)
    except (OSError, AttributeError) as exc:
        return Outcome(False, f"CPU affinity {_cpus(cpus)} not set ({_why(exc)})")
    return Outcome(True, f"CPUs {_cpus(cpus)}")


def set_fifo(tid: int, priority: int) -> Outcome:
    """Thread ``tid`` (a native id; 0: the caller) at SCHED_FIFO ``priority``."""
    try:
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        return Outcome(False, f"SCHED_FIFO refused ({_why(exc)}; it needs root, CAP_SYS_NICE or "
                              "RLIMIT_RTPRIO at least the priority: LimitRTPRIO in a unit)")
    return Outcome(True, f"FIFO {priority}")


def lock_memory() -> Outcome:
    """mlockall: the pages mapped now and later stay in RAM. MCL_ONFAULT locks a page when first
    touched, so the threads' reserved stacks are not made resident. MCL_FUTURE only where the
    lock cannot run out (root, or RLIMIT_MEMLOCK unlimited): with a finite limit a later
    allocation past it would fail inside numpy, a crash instead of a page fault."""
    try:
        import resource
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.mlockall
        unlimited = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0] == resource.RLIM_INFINITY
    except (OSError, AttributeError, ImportError) as exc:
        return Outcome(False, f"memory not locked ({_why(exc)})")
    flags = MCL_CURRENT | (MCL_FUTURE if os.geteuid() == 0 or unlimited else 0)
    for extra in (MCL_ONFAULT, 0):  # MCL_ONFAULT: Linux 4.4 on; EINVAL before
        if fn(flags | extra) == 0:
            return Outcome(True, "memory locked" + ("" if flags & MCL_FUTURE else " (current pages only)"))
        err = ctypes.get_errno()
        if err != 22:  # EINVAL
            break
    return Outcome(False, f"memory not locked: mlockall: {os.strerror(err)} (LimitMEMLOCK=infinity or "
                          "CAP_IPC_LOCK needed)")


def name_thread(tid: int, name: str) -> None:
    """The thread's name as ps -L, top and the journal show it (15 bytes; best effort)."""
    try:
        with open(f"/proc/self/task/{tid}/comm", "w") as f:
            f.write(name[:15])
    except OSError:
        pass


def policy_of(tid: int) -> tuple[int, int]:
    """(policy, priority) of a thread of this process: os.SCHED_* and its real-time priority."""
    return os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority


def lower_priority() -> Outcome:
    """This process's threads to nice 19: a ground-station command run on the companion computer
    takes little of the tick's CPU (weight 15 against a normal thread's 1024), and threads started
    afterwards inherit it (a plot). Not SCHED_IDLE: its weight (3) is a fifth of nice 19's, and
    beside busy processes an idle-class command all but stops (docs/DEPLOY.md, section 4). The
    app's own protection is its real-time priority (``pmon run --rt-priority``)."""
    try:
        for tid in _tasks():
            os.setpriority(os.PRIO_PROCESS, tid, 19)  # Linux: per thread
        return Outcome(True, "nice 19")
    except (OSError, AttributeError) as exc:
        return Outcome(False, f"priority not lowered ({_why(exc)})")


def _cpus(cpus: tuple[int, ...]) -> str:
    return ",".join(str(c) for c in cpus)


def _why(exc: BaseException) -> str:
    return getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
