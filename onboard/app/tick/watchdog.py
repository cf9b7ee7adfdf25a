"""The watchdog: reports a stuck io loop, a tick running too long and a schedule that stopped
handing out ticks, once per episode, without the app lock (its own thread, started by the app).

The io thread keeps re-sending the last (checked) setpoint while a tick is stuck, so the vehicle
holds a safe point; an overrun's scans are skipped (onboard/app/tick/schedule.py).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from onboard.app.tick.schedule import COAST_AFTER_S, TickJob


@dataclass(frozen=True)
class Health:
    """What the watchdog looks at, read by the app without its lock."""

    local: float  # local s now
    now: float | None  # autopilot s now
    io_beat: float  # local s the io loop last began an iteration
    sched_beat: float  # local s the tick schedule job last ran to its end
    submitted_t: float | None  # autopilot s the last tick was handed to the worker
    last_tick_t: float | None  # scan time of that tick
    running: TickJob | None  # the tick the worker runs now


class Watchdog:
    """``alarm(text)``: the critical report (no lock); ``rate()``: autopilot s per local s;
    ``scan_wait()``: PMON_SCAN_WAIT now."""

    def __init__(self, watchdog_s: float, alarm: Callable[[str], None], rate: Callable[[], float],
                 scan_wait: Callable[[], float]):
        self.watchdog_s = watchdog_s  # autopilot s a tick may run (or the io loop stall) before a report
        self.alarm = alarm
        self.rate = rate
        self.scan_wait = scan_wait
        self.counts: dict[str, int] = {}  # reports by kind (``tick_stuck``, ...)
        self.alarmed: set[str] = set()  # episodes in progress

    def check(self, h: Health) -> None:
        """Reports, once per episode: an io loop not iterating; a tick schedule that does not
        run to its end (its handler failing every time); no tick handed to the worker for
        ``watchdog_s`` past the longest gap the schedule allows (the coast grid), while the
        worker is idle, i.e. a loop that stopped ticking; a tick running past ``watchdog_s`` of
        autopilot time."""
        rate = self.rate() or 1.0
        limit = self.watchdog_s / rate
        self._episode("io", h.local - h.io_beat > max(limit, 0.5),
                      lambda: f"watchdog: io loop stuck {h.local - h.io_beat:.1f} s")
        self._episode("schedule", h.local - h.sched_beat > max(limit, 0.5),
                      lambda: f"watchdog: tick schedule failing {h.local - h.sched_beat:.1f} s")
        gap = self.watchdog_s + 1.0 + self.scan_wait() + COAST_AFTER_S
        self._episode("ticks", h.now is not None and h.submitted_t is not None and h.last_tick_t is not None
                      and h.running is None and h.now - h.submitted_t > gap,
                      lambda: f"watchdog: no tick for {h.now - h.submitted_t:.1f} s")
        job = h.running
        started = job.run_local if job is not None else None
        self._episode("tick", started is not None and h.local - started > limit,
                      lambda: f"watchdog: tick t={job.t:.0f} running {(h.local - started) * rate:.1f} s")

    def _episode(self, key: str, bad: bool, text: Callable[[], str]) -> None:
        if bad and key not in self.alarmed:
            self.alarmed.add(key)
            kind = f"{key}_stuck"
            self.counts[kind] = self.counts.get(kind, 0) + 1
            self.alarm(text())
        elif not bad:
            self.alarmed.discard(key)
