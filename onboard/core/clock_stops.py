"""Where the clock stops the guidance, as counts (a run replayed to the same decisions).

A guidance solve (``guidance.plan_guidance``) with a time limit (``max_solve_time_s``) has one
``Deadline``; its searches ask it, between QP solves, whether the time is up. A deadline reads
the clock at most once per count of QP solves (the first time it is asked at that count) and,
once passed, stays passed: so where the clock stopped a solve is fully said by one count, the QP
solves it had spent then. ``SearchClock`` is the tick's timer that keeps those counts: live, it
records them (``stops``: per deadline of the tick, in the order they were made, the count, for
the deadlines that passed); given the counts of a recorded tick (``replay``), it never reads
the clock for a decision and stops each solve at its recorded count, so the same inputs give
the same plans whatever the machine's speed (onboard/app/replay.py).
"""
from __future__ import annotations

import time
from typing import Callable, Sequence


class Deadline:
    """One guidance solve's time limit. ``passed(solves)``: whether it stops the solve that has
    spent ``solves`` QP solves (the solves of all its searches, in order)."""

    __slots__ = ("_timer", "_end", "_asked", "_stopped", "_on_stop")

    def __init__(self, timer: Callable[[], float], limit_s: float, stopped: int | None = None,
                 on_stop: Callable[[int], None] | None = None, replay: bool = False):
        self._timer = timer
        self._end = None if replay else timer() + limit_s
        self._asked = -1  # the count the clock was last read at
        self._stopped = stopped  # the count the clock stopped the solve at (None: not yet)
        self._on_stop = on_stop

    def passed(self, solves: int) -> bool:
        if self._stopped is not None:
            return solves >= self._stopped
        if self._end is None or solves == self._asked:
            return False
        self._asked = solves
        if self._timer() < self._end:
            return False
        self._stopped = solves
        if self._on_stop is not None:
            self._on_stop(solves)
        return True


class SearchClock:
    """The timer of one tick (``timer``: the clock read for the timings), making its guidance
    deadlines. ``replay``: the tick's recorded ``stops`` ([deadline index, solves] pairs): the
    deadlines pass at those counts and never by the clock."""

    def __init__(self, timer: Callable[[], float] = time.perf_counter,
                 replay: Sequence[Sequence[int]] | None = None):
        self.timer = timer
        self._replay = None if replay is None else {int(k): int(n) for k, n in replay}
        self.deadlines = 0  # made this tick
        self.stops: list[list[int]] = []  # [deadline index, QP solves] where the clock stopped a solve

    def __call__(self) -> float:
        return self.timer()

    def deadline(self, limit_s: float) -> Deadline:
        k = self.deadlines
        self.deadlines += 1
        if self._replay is not None:
            return Deadline(self.timer, limit_s, self._replay.get(k), replay=True)
        return Deadline(self.timer, limit_s, on_stop=lambda n: self.stops.append([k, n]))


def deadline_of(timer: Callable[[], float], limit_s: float | None) -> Deadline | None:
    """The deadline of a guidance solve limited to ``limit_s`` (None: no limit) on ``timer``
    (a ``SearchClock`` keeps its count)."""
    if limit_s is None:
        return None
    if isinstance(timer, SearchClock):
        return timer.deadline(limit_s)
    return Deadline(timer, limit_s)
