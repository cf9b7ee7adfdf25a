"""The tick schedule: which DF scan the worker ticks next, and when (io thread, under the app
lock; autopilot seconds throughout).

A scan is due when all its channels have arrived or ``PMON_SCAN_WAIT`` after its time. Scans
still within their budget (``PMON_BUDGET`` after their time) are ticked in order; past it, only
the newest due scan is ticked and the older ones are counted as skipped: an overrun is skipped,
never queued. A scan that becomes due while the worker is busy waits for it. Without DF data
the filters coast on the 1 s grid, so they stay in step with time.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from onboard.app.context import AppContext
from onboard.app.df.datagram import ScanBuffer
from onboard.app.mavlink_connection import mavlink
from onboard.app.part import Job, Part

COAST_AFTER_S = 2.0  # autopilot s past a scan's wait without any DF datagram -> coast tick
PLAN_RESERVE_S = 0.25  # autopilot s of a tick's budget kept for tracking, planning and sending


@dataclass
class TickJob:
    """What the schedule hands the worker."""

    t: float  # scan time (autopilot s)
    scans: dict  # ch -> Datagram
    skipped: int
    started_local: float = 0.0
    run_local: float | None = None  # when the worker began it (the watchdog reads this)
    due_t: float | None = None  # autopilot time when it was handed to the worker
    arrived_t: float | None = None  # autopilot time its newest datagram arrived


class TickSchedule(Part):
    """``worker``: has ``busy`` and ``submit(job)``; ``ctx``: the app's parameters, clocks,
    counters and voice."""

    def __init__(self, ctx: AppContext, scans: ScanBuffer, worker):
        self.scans = scans
        self.params = ctx.params
        self.clock = ctx.clock
        self.mono = ctx.mono
        self.worker = worker
        self.counters = ctx.counters
        self.say = ctx.say
        self.ran_local = self.mono()  # local s the job last ran to its end (the watchdog reads it)
        self.last_tick_t: float | None = None  # scan time of the newest tick handed over
        self.submitted_t: float | None = None  # autopilot time the newest tick was handed over
        self._silent = False  # DF silence episode (coasting) in progress

    def jobs(self) -> tuple[Job, ...]:
        return (Job("tick schedule", self.periodic),)

    def periodic(self, local: float, now: float | None) -> None:
        """``run`` once the autopilot's clock has a sample (before it there is nothing to
        schedule, and the job counts as run)."""
        if now is not None:
            self.run(now)
        self.ran_local = self.mono()

    def run(self, now: float) -> None:
        """The periodic job: hand the worker the next tick, if one is due and it is free."""
        if self.worker.busy:
            return
        wait = self.params.settings.app.scan_wait_s
        due = [k for k in self.scans.pending if self.scans.complete(k) or now >= k + wait]
        if due:
            self._tick_scans(now, due)
        elif self.last_tick_t is not None and now >= self.last_tick_t + 1.0 + wait + COAST_AFTER_S:
            # late enough that a DF delivering a few seconds late is not overtaken: a coast tick
            # takes that scan time, and a scan arriving after it is rejected as stale_time
            self._coast()

    def _coast(self) -> None:
        if not self._silent:  # once per silence episode
            self._silent = True
            self.counters.add("df_silences")
            self.say("no DF data: predicting only", mavlink.MAV_SEVERITY_WARNING)
        self.counters.add("ticks_coasted")
        key = self.last_tick_t + 1.0
        self.scans.consumed_until = max(self.scans.consumed_until, key)
        self._submit(TickJob(key, {}, 0))

    def _tick_scans(self, now: float, due: list[float]) -> None:
        live = [k for k in due if now <= k + self.params.settings.app.tick_budget_s]
        key = min(live) if live else max(due)
        taken = self.scans.take_until(key)
        if self._silent:
            self._silent = False
            self.say("DF data back: updating again")
        skipped = len(taken) - 1
        if skipped:
            self.counters.add("ticks_skipped", skipped)
        if self.last_tick_t is not None and key > self.last_tick_t + 1.5:
            missed = int(round(key - self.last_tick_t)) - 1 - skipped
            if missed > 0:
                self.counters.add("ticks_coasted_missing", missed)
        self._submit(TickJob(key, taken[-1][1], skipped, arrived_t=self.scans.last_arrival))

    def _submit(self, job: TickJob) -> None:
        job.started_local = self.mono()
        job.due_t = self.clock.now()
        self.submitted_t = job.due_t
        self.last_tick_t = job.t
        self.worker.submit(job)

    def on_clock_jump(self, jump_s: float, now: float | None) -> bool:
        """A jump the clock followed: the watchdog's tick gap starts again; a jump ahead restarts
        the schedule on the new timeline (no burst of coast ticks, no scan of the old timeline
        ticked on the new one). True when it restarted."""
        self.submitted_t = now
        if not (jump_s > 0 and now is not None):
            return False
        self.scans.drop_pending()  # stamped on the old timeline
        start = math.floor(now) - 1.0
        self.scans.consumed_until = max(self.scans.consumed_until, start)
        if self.last_tick_t is not None:
            self.last_tick_t = max(self.last_tick_t, start)
        return True

    def on_reboot(self) -> None:
        """The autopilot's clock, which stamps the scans, started over: so does the schedule
        (else every new scan would be 'stale'); the filters keep their state."""
        self.scans.start_over()
        self.last_tick_t = None
