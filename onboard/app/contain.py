"""Handlers that cannot stop the loop that runs them.

The io thread runs one handler per MAVLink message, per DF datagram and per periodic job
(heartbeat, link watchdog, tick schedule, setpoint stream, ...). An exception in one of them is
caught here, counted under its kind (``where: ExceptionType``), logged with its traceback the
first time that kind is seen (a peer repeating a bad packet must not fill the log), and the
loop goes on to the next handler: a message nobody foresaw can cost its own handling, never
the schedule. Used by one thread; others may read the counts.
"""
from __future__ import annotations

import logging
from typing import Callable


class Contained:
    def __init__(self, log: logging.Logger, on_first: Callable[[str, BaseException], None] | None = None):
        self.log = log
        self.on_first = on_first  # called once per new kind (the app says it to the ground)
        self.counts: dict[str, int] = {}
        self.total = 0

    def run(self, where: str, fn: Callable, *args) -> bool:
        """``fn(*args)``; False if it raised (counted, first of its kind logged)."""
        try:
            fn(*args)
            return True
        except Exception as exc:
            self.caught(where, exc)
            return False

    def caught(self, where: str, exc: BaseException) -> None:
        kind = f"{where}: {type(exc).__name__}"
        n = self.counts.get(kind, 0) + 1
        self.counts[kind] = n
        self.total += 1
        if n == 1:
            self.log.error("error in %s (counted; this kind is logged once)", where, exc_info=exc)
            if self.on_first is not None:
                try:
                    self.on_first(kind, exc)
                except Exception:  # reporting must not raise into the loop either
                    pass
