"""The autopilot's clock, as seen from a MAVLink client.

Every autopilot message with ``time_boot_ms`` (SYSTEM_TIME, GLOBAL_POSITION_INT, ATTITUDE, ...)
is a sample (autopilot time, local monotonic time). Between samples the clock runs at the rate
measured over the last few seconds, so it follows a SITL run at any speedup, and a real
autopilot at 1x. It never goes backwards, except to follow a confirmed
jump (an autopilot reboot: time back by > 5 s). Without samples (autopilot link lost) it keeps running at the last measured rate:
the autopilot's clock does not stop when its link does, and the app keeps estimating on the
DF's timestamps through a link loss (``age_local_s`` says how long the clock has been blind).

Jumps. ``time_boot_ms`` only runs forward at the autopilot's rate, so a sample far from where
the clock's extrapolation puts it is either a reboot (far behind), a stretch of blindness at a
wrong rate (far ahead, after a link loss), or a forged message (on an unsigned link anyone can
send a SYSTEM_TIME "from the autopilot": one an hour ahead used to move the clock an hour, tick
32 coast ticks in a burst and poison the rate the watchdog scales by). Such a sample is a
*candidate*: the clock keeps its timeline and follows the candidate only when the samples after
it confirm it (``CONFIRM_SAMPLES`` of them, continuing from it, over ``CONFIRM_LOCAL_S`` local
seconds, none back on the old timeline; one a little older than the candidate's newest, as
PX4's streams stamp them, is skipped as it is on the timeline). A sample back on the old timeline cancels it
(``jumps_ignored`` +1). A followed jump restarts the sample window (the rate is measured on the
new timeline only) and counts in ``jumps`` (``last_jump_s``: by how much); the app reports both
and restarts its tick schedule on a followed jump. "Far" is ``JUMP_TOL_S`` plus 0.1 local s and a
quarter of the local time since the last sample, at the measured rate: a drift of the free-run
through a link loss is not a jump.

The app and the feed take time only from an object with ``now() -> float | None`` (autopilot
seconds; None until the first sample), so tests can inject a ``ManualClock``.
"""
from __future__ import annotations

import math
import statistics
import threading
import time
from collections import deque
from typing import Callable, Protocol


class Clock(Protocol):
    def now(self) -> float | None: ...


class AutopilotClock:
    WINDOW_S = 5.0  # local seconds of samples used to measure the rate
    JUMP_TOL_S = 2.0  # autopilot s a sample may be ahead of the extrapolation (plus the slack below)
    REBOOT_S = 5.0  # a sample this far behind the newest one: a reboot candidate
    CONFIRM_SAMPLES = 3  # samples continuing from a candidate, over ...
    CONFIRM_LOCAL_S = 1.0  # ... at least this many local seconds, before it is followed
    OUT_OF_ORDER_S = 1.0  # a sample this little behind the candidate's newest neither continues nor resets it
    MAX_RATE = 1000.0

    def __init__(self, monotonic: Callable[[], float] = time.monotonic):
        self._mono = monotonic
        self._lock = threading.Lock()
        self._samples: deque[tuple[float, float]] = deque()  # (local s, autopilot s)
        self._rate = 1.0
        self._last_out = None
        self._candidate: list[tuple[float, float]] = []  # samples of an unconfirmed jump
        self.resets = 0  # followed jumps back (reboots)
        self.resyncs = 0  # times the extrapolation had run > 1 s ahead and was pulled back
        self.jumps = 0  # followed jumps, either way
        self.jumps_ignored = 0  # candidates cancelled by a sample on the old timeline
        self.last_jump_s = 0.0  # the newest followed jump, autopilot s (new - old timeline)

    def _far(self, local: float, ap: float) -> bool:
        """Is ``ap`` (seen at ``local``) off the current timeline: far ahead of the
        extrapolation, or behind the newest sample by more than a reboot's margin."""
        l1, a1 = self._samples[-1]
        if ap < a1 - self.REBOOT_S:
            return True
        gap = max(local - l1, 0.0)
        return ap > a1 + gap * self._rate + self.JUMP_TOL_S + (0.1 + 0.25 * gap) * self._rate

    def observe(self, time_boot_ms: int | float) -> None:
        ap = float(time_boot_ms) / 1000.0
        if ap != ap or ap in (float("inf"), float("-inf")):
            return
        local = self._mono()
        with self._lock:
            if self._samples and self._far(local, ap):
                self._jump_candidate(local, ap)
                return
            if self._candidate:  # back on the old timeline: the candidate was not the autopilot
                self._candidate = []
                self.jumps_ignored += 1
            if self._samples and ap <= self._samples[-1][1]:
                return  # out of order or repeated stamp: no new information
            if self._last_out is not None and ap < self._last_out - 1.0:
                # the extrapolation ran ahead (a rate measured over a burst of samples that a
                # starved reader took at once): follow the autopilot, not the guess
                self._last_out = None
                self.resyncs += 1
            self._add(local, ap)

    def _jump_candidate(self, local: float, ap: float) -> None:
        c = self._candidate
        if c and c[-1][1] - self.OUT_OF_ORDER_S <= ap < c[-1][1]:
            return  # another stream's stamp, a little older (PX4's): no news, as on the timeline
        if c and c[-1][1] <= ap:
            c.append((local, ap))  # continues from the candidate
        else:
            c[:] = [(local, ap)]
        if len(c) >= self.CONFIRM_SAMPLES and c[-1][0] - c[0][0] >= self.CONFIRM_LOCAL_S:
            l1, a1 = self._samples[-1]
            old = a1 + (c[0][0] - l1) * self._rate  # where the old timeline was at the jump
            self.last_jump_s = c[0][1] - old
            self.jumps += 1
            if c[0][1] < a1:
                self.resets += 1
            self._samples.clear()
            self._last_out = None
            for sample in c:
                self._add(*sample)
            self._candidate = []

    def _add(self, local: float, ap: float) -> None:
        self._samples.append((local, ap))
        while len(self._samples) > 2 and local - self._samples[0][0] > self.WINDOW_S:
            self._samples.popleft()
        (l0, a0), (l1, a1) = self._samples[0], self._samples[-1]
        if l1 - l0 >= 1.0:  # a rate over a shorter span is mostly read-out jitter
            self._rate = min(max((a1 - a0) / (l1 - l0), 1e-3), self.MAX_RATE)

    @property
    def reboot_pending(self) -> bool:
        """Samples far behind the timeline are coming, not yet confirmed as a reboot."""
        with self._lock:
            return bool(self._candidate) and bool(self._samples) and self._candidate[0][1] < self._samples[-1][1]

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


# ----- Unix time to autopilot time (a DF that stamps its frames in Unix time: onboard/app/kraken/source.py)


class UtcMap:
    """Unix time to autopilot time from the autopilot's SYSTEM_TIME (UTC from its GPS, and its
    time since boot): the median offset of the last ``WINDOW`` messages with a UTC (0 = none),
    so a stray message moves nothing. After a reboot it follows in WINDOW // 2 + 1 messages."""

    WINDOW = 9

    def __init__(self):
        self._offsets: deque[float] = deque(maxlen=self.WINDOW)

    def observe(self, time_unix_usec: int, time_boot_ms: int) -> None:
        if time_unix_usec <= 0 or not 0 <= time_boot_ms < 2**32:
            return
        off = time_unix_usec / 1e6 - time_boot_ms / 1e3
        if math.isfinite(off):
            self._offsets.append(off)

    def autopilot_time(self, unix_s: float) -> float | None:
        if not self._offsets:
            return None
        return unix_s - statistics.median(self._offsets)

    def unix_time(self, autopilot_s: float) -> float | None:
        """The inverse (a simulated KrakenSDR stamps its frames with it: sim/stack/kraken.py)."""
        if not self._offsets:
            return None
        return autopilot_s + statistics.median(self._offsets)


class HostTime:
    """Unix time to autopilot time through this computer's clock (KrakenSDR on this computer,
    or synchronised with it): the autopilot clock now, less the age of the stamp."""

    def __init__(self, clock, wall: Callable[[], float] = time.time):
        self.clock, self.wall = clock, wall

    def autopilot_time(self, unix_s: float) -> float | None:
        now = self.clock.now()
        return None if now is None else now - (self.wall() - unix_s) * getattr(self.clock, "rate", 1.0)


class ManualClock:
    """A clock tests set by hand."""

    def __init__(self, t: float | None = 0.0):
        self.t = t

    def now(self) -> float | None:
        return self.t

    @property
    def reboot_pending(self) -> bool:
        """Samples far behind the timeline are coming, not yet confirmed as a reboot."""
        with self._lock:
            return bool(self._candidate) and bool(self._samples) and self._candidate[0][1] < self._samples[-1][1]

    @property
    def rate(self) -> float:
        return 1.0

    def age_local_s(self) -> float:
        return 0.0
