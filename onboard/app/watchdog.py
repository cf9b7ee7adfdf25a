"""The watchdog thread: reports a stuck io loop, a tick running too long and a schedule that
stopped handing out ticks, once per episode, without the app lock. A mixin of ``OnboardApp``."""
from __future__ import annotations

import logging
from typing import Callable

from onboard.app.mavlink_connection import mavlink
from onboard.app.schedule import COAST_AFTER_S

log = logging.getLogger("pmon.app")


class Watchdog:
    """Methods of ``OnboardApp``; the attributes they use are set up in ``OnboardApp.__init__``."""

    def _alarm(self, key: str, text: str) -> None:
        """Report from the watchdog: no app lock (the stuck thread may hold it)."""
        self.watchdog[key] = self.watchdog.get(key, 0) + 1
        full = f"PMON: {text}"
        self.events.append((None, full))
        log.error(full)
        if self.vehicle.sysid is not None:
            self.link.send(self.link.mav.statustext_encode(mavlink.MAV_SEVERITY_CRITICAL, full.encode()[:50]))

    def _watchdog_loop(self) -> None:
        """Reports, once per episode: an io loop not iterating; a tick schedule that does not
        run to its end (its handler failing every time); no tick handed to the worker for
        ``watchdog_s`` past the longest gap the schedule allows (the coast grid), while the
        worker is idle, i.e. a loop that stopped ticking; a tick running past ``watchdog_s`` of
        autopilot time. The io thread keeps re-sending the last (checked) setpoint while a tick
        is stuck, so the vehicle holds a safe point; an overrun's scans are skipped."""
        while not self._stop.wait(0.1):
            local = self.mono()
            rate = getattr(self.clock, "rate", 1.0) or 1.0
            limit = self.cfg.watchdog_s / rate
            self._episode("io", local - self._io_beat > max(limit, 0.5),
                          lambda: f"watchdog: io loop stuck {local - self._io_beat:.1f} s")
            self._episode("schedule", local - self._sched_beat > max(limit, 0.5),
                          lambda: f"watchdog: tick schedule failing {local - self._sched_beat:.1f} s")
            now, sub = self.clock.now(), self._submitted_t
            gap = self.cfg.watchdog_s + 1.0 + self.params["PMON_SCAN_WAIT"] + COAST_AFTER_S
            self._episode("ticks", now is not None and sub is not None and self.last_tick_t is not None
                          and self._running is None and now - sub > gap,
                          lambda: f"watchdog: no tick for {now - sub:.1f} s")
            job = self._running
            started = job.run_local if job is not None else None
            self._episode("tick", started is not None and local - started > limit,
                          lambda: f"watchdog: tick t={job.t:.0f} running {(local - started) * rate:.1f} s")

    def _episode(self, key: str, bad: bool, text: Callable[[], str]) -> None:
        if bad and key not in self._alarmed:
            self._alarmed.add(key)
            self._alarm(f"{key}_stuck", text())
        elif not bad:
            self._alarmed.discard(key)
