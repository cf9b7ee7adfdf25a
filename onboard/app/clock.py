"""The autopilot's clock, as seen from a MAVLink client.

Every autopilot message with ``time_boot_ms`` (SYSTEM_TIME, GLOBAL_POSITION_INT, ATTITUDE, ...)
is a sample (autopilot time, local monotonic time). Between samples the clock runs at the rate
measured over the last few seconds, so it follows a SITL run at any speedup, and a real
autopilot at 1x. It never goes backwards; an autopilot reboot (time jumps back by > 5 s)
resets it. Without samples (autopilot link lost) it keeps running at the last measured rate:
the autopilot's clock does not stop when its link does, and the app keeps estimating on the
DF's timestamps through a link loss (``age_local_s`` says how long the clock has been blind).

The app and the feed take time only from an object with ``now() -> float | None`` (autopilot
seconds; None until the first sample), so tests can inject a ``ManualClock``.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Callable, Protocol


class Clock(Protocol):
    def now(self) -> float | None: ...


class AutopilotClock:
    WINDOW_S = 5.0  # local seconds of samples used to measure the rate

    def __init__(self, monotonic: Callable[[], float] = time.monotonic):
        self._mono = monotonic
        self._lock = threading.Lock()
        self._samples: deque[tuple[float, float]] = deque()  # (local s, autopilot s)
        self._rate = 1.0
        self._last_out = None
        self.resets = 0
        self.resyncs = 0  # times the extrapolation had run > 1 s ahead and was pulled back

    def observe(self, time_boot_ms: int | float) -> None:
        ap = float(time_boot_ms) / 1000.0
        local = self._mono()
        with self._lock:
            if self._samples and ap < self._samples[-1][1] - 5.0:
                self._samples.clear()  # autopilot rebooted
                self._last_out = None
                self.resets += 1
            if self._samples and ap <= self._samples[-1][1]:
                return  # out of order or repeated stamp: no new information
            if self._last_out is not None and ap < self._last_out - 1.0:
                # the extrapolation ran ahead (a rate measured over a burst of samples that a
                # starved reader took at once): follow the autopilot, not the guess
                self._last_out = None
                self.resyncs += 1
            self._samples.append((local, ap))
            while len(self._samples) > 2 and local - self._samples[0][0] > self.WINDOW_S:
                self._samples.popleft()
            (l0, a0), (l1, a1) = self._samples[0], self._samples[-1]
            if l1 - l0 >= 1.0:  # a rate over a shorter span is mostly read-out jitter
                self._rate = max((a1 - a0) / (l1 - l0), 1e-3)

    @property
    def rate(self) -> float:
        """Autopilot seconds per local second (the SITL speedup; 1 on a real vehicle)."""
        return self._rate

    def now(self) -> float | None:
        with self._lock:
            if not self._samples:
                return None
            local, ap = self._samples[-1]
            t = ap + (self._mono() - local) * self._rate
            if self._last_out is not None and t < self._last_out:
                t = self._last_out
            self._last_out = t
            return t

    def age_local_s(self) -> float:
        """Local seconds since the last sample (inf before the first): link health."""
        with self._lock:
            return self._mono() - self._samples[-1][0] if self._samples else float("inf")


class ManualClock:
    """A clock tests set by hand."""

    def __init__(self, t: float | None = 0.0):
        self.t = t

    def now(self) -> float | None:
        return self.t

    @property
    def rate(self) -> float:
        return 1.0

    def age_local_s(self) -> float:
        return 0.0
