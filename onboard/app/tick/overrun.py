"""Which stage of a tick overran its budget (PMON_BUDGET after the scan's time).

A tick's local time splits into stages, in order:

  wait        the scan's time to the worker's start (PMON_SCAN_WAIT, a busy worker, a starved thread)
  update      the snapshot, pairing and the filters' measurement update (core step 1-2)
  guidance    the targets' guidance (core step 3)
  prediction  the filters' prediction (core step 4)
  planning    the UAV's planner (core step 5)
  send        checks, the setpoint's send, the record (under the app lock)

The stage named for an overrun is the one running when the deadline passed: the time it took
may be ordinary (a tick started late still overruns in its first stage), so the record keeps
every stage's time too. The core reports ``tracking`` = update + prediction; ``StageTimer``
splits it by keeping the core's first two timer readings, which frame its update
(onboard/core/monitor.py ``tick``: t0, update, t1).
"""
from __future__ import annotations

import time

from onboard.app.contract import OVERRUN_STAGES


class StageTimer:
    """``time.perf_counter`` for the core tick, keeping its first two readings."""

    __slots__ = ("marks",)

    def __init__(self):
        self.marks: list[float] = []

    def __call__(self) -> float:
        t = time.perf_counter()
        if len(self.marks) < 2:
            self.marks.append(t)
        return t


def core_stages(timings_s: dict, marks: list[float]) -> dict[str, float]:
    """The core's stages (s): update, guidance, prediction, planning."""
    tracking = timings_s.get("tracking", 0.0)
    update = marks[1] - marks[0] if len(marks) >= 2 else tracking
    update = min(max(update, 0.0), tracking)
    return {"update": update, "guidance": timings_s.get("guidance", 0.0), "prediction": tracking - update,
            "planning": timings_s.get("planning", 0.0)}


def overrun_stage(left_s: float, stages: dict[str, float]) -> str:
    """The stage running when the deadline passed, ``left_s`` local s after the worker began
    (<= 0: it began late, ``wait``); the last stage if the stages' sum does not reach it (the
    deadline is on the autopilot's clock, whose rate the local time only estimates)."""
    if left_s <= 0.0:
        return "wait"
    t = 0.0
    for name in OVERRUN_STAGES[1:]:
        t += stages.get(name, 0.0)
        if t > left_s:
            return name
    return OVERRUN_STAGES[-1]


def stage_code(name: str | None) -> int:
    """PMON_STAT's ``overrun_stage``: 0 none, then 1 + the index in OVERRUN_STAGES."""
    return 0 if name is None else 1 + OVERRUN_STAGES.index(name)


def describe(t: float, over_s: float, stage: str, stages: dict[str, float]) -> str:
    """The one line said for an overrun."""
    times = ", ".join(f"{k} {stages.get(k, 0.0) * 1e3:.0f}" for k in OVERRUN_STAGES[1:])
    return f"tick t={t:.0f} {over_s:.2f} s over budget in {stage} ({times} ms)"
