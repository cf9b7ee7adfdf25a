"""The tick schedule's shared pieces: what the io thread hands the worker, and its timings
(autopilot s)."""
from __future__ import annotations

from dataclasses import dataclass

COAST_AFTER_S = 2.0  # autopilot s past a scan's wait without any DF datagram -> coast tick
PLAN_RESERVE_S = 0.25  # autopilot s of a tick's budget kept for tracking, planning and sending


@dataclass
class TickRecord:
    """What the io thread hands the worker."""

    t: float  # scan time (autopilot s)
    scans: dict  # ch -> Datagram
    skipped: int
    started_local: float = 0.0
    run_local: float | None = None  # when the worker began it (the watchdog reads this)
    due_t: float | None = None  # autopilot time when it was handed to the worker
    arrived_t: float | None = None  # autopilot time its newest datagram arrived
