"""A tick over its budget says which stage it overran in (onboard/app/tick/overrun.py): in the tick's
record (the run log), in PMON_STAT and in one STATUSTEXT line; a real app (no autopilot: scans are
ticked without a pose), its core's stages slowed one at a time."""
from __future__ import annotations

import json
import socket
import time

import pytest


from tests.support.app_helpers import wait_for

from onboard.app.df import datagram as dg
from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.contract import OVERRUN_STAGES, STAT_FIELDS
from onboard.app.tick.overrun import StageTimer, core_stages, overrun_stage, stage_code
from onboard.config import load_scenario
from onboard.policy import with_policy
from onboard.core import monitor

M = 4  # the paper scenario's targets


class WallClock:
    """Autopilot time that runs with the wall clock, so a slow stage makes a tick late."""

    rate = 1.0

    def __init__(self, t0: float = 1000.0):
        self.t0, self.m0 = t0, time.monotonic()

    def now(self) -> float:
        return self.t0 + time.monotonic() - self.m0


def test_the_stage_running_when_the_deadline_passed():
    stages = {"update": 0.125, "guidance": 0.5, "prediction": 0.25, "planning": 0.25, "send": 0.0625}
    assert overrun_stage(-0.1, stages) == "wait"  # the worker began past the deadline
    assert overrun_stage(0.0, stages) == "wait"
    assert overrun_stage(0.05, stages) == "update"
    assert overrun_stage(0.5, stages) == "guidance"
    assert overrun_stage(0.625, stages) == "prediction"  # at the deadline guidance ended: not past it
    assert overrun_stage(1.0, stages) == "planning"
    assert overrun_stage(1.15, stages) == "send"
    assert overrun_stage(5.0, stages) == "send"  # the stages' sum short of it: the last
    assert [stage_code(s) for s in (None, "wait", "planning")] == [0, 1, 5]


def test_the_core_tracking_time_splits_into_update_and_prediction():
    """StageTimer frames the core's update by its first two readings: the split sums to the
    core's own ``tracking`` time, the update's part being the update's."""
    timer = StageTimer()
    assert timer() <= timer() and len(timer.marks) == 2
    timer()
    assert len(timer.marks) == 2  # later readings (the QP deadline checks) are not kept
    s = core_stages({"tracking": 0.3, "guidance": 0.2, "planning": 0.1}, [1.0, 1.25])
    assert s == pytest.approx({"update": 0.25, "guidance": 0.2, "prediction": 0.05, "planning": 0.1})


def _slowed(monkeypatch, name: str, seconds: float) -> None:
    real = getattr(monitor, name)

    def slow(*a, **k):
        time.sleep(seconds)
        return real(*a, **k)
    monkeypatch.setattr(monitor, name, slow)


@pytest.mark.timeout(120)
def test_an_overrun_names_its_stage_in_the_record_pmon_stat_and_one_line(monkeypatch, tmp_path):
    clock = WallClock()
    runlog = tmp_path / "run.jsonl"
    app = OnboardApp(AppConfig("udpin:127.0.0.1:0", sensor_port=0, runlog_path=str(runlog)), with_policy(load_scenario("paper"), "paper"),
                     clock=clock).start()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def scan(t: float) -> dict:
        n = len(app.ticks)
        for ch in range(M):
            tx.sendto(dg.encode(t, ch, [0.1 * ch]), ("127.0.0.1", app.sensor_port))
        assert wait_for(lambda: len(app.ticks) > n and app.ticks[-1]["t"] == pytest.approx(t), 20), \
            list(app.ticks)[-2:]
        return app.ticks[-1]
    try:
        rec = scan(clock.now())  # a tick in budget: its stages recorded, no overrun
        assert rec["overrun"] is None and set(rec["stage_ms"]) == set(OVERRUN_STAGES[1:])
        assert rec["stage_ms"]["guidance"] == rec["timings_ms"]["guidance"]
        assert app._status()["overrun_stage"] == 0 and app._status()["overruns"] == 0
        for name, stage in (("_guidance", "guidance"), ("_predict", "prediction"),
                            ("_update_and_estimate", "update")):
            monkeypatch.undo()
            _slowed(monkeypatch, name, 1.2)  # past the 0.9 s budget inside this stage
            rec = scan(clock.now())
            assert rec["overrun"] == stage, rec
            assert rec["stage_ms"][stage] >= 1200, rec["stage_ms"]
            assert app._status()["overrun_stage"] == 1 + OVERRUN_STAGES.index(stage)
        monkeypatch.undo()
        rec = scan(clock.now() - 1.0)  # its budget gone before the worker began
        assert rec["overrun"] == "wait", rec
        c = app.counters
        assert [c.get(f"overruns_{s}", 0) for s in ("guidance", "prediction", "update", "wait")] == [1, 1, 1, 1]
        assert app._status()["overruns"] == 4 and STAT_FIELDS.index("overrun_stage") == 32  # docs/MAVLINK.md
        # one line said, the first; the next within OVERRUN_SAY_S are counted, not said
        said = [text for _, text in app.events if "over budget" in text]
        assert len(said) == 1, said
        assert said[0].startswith("PMON: tick t=") and " s over budget in guidance (update " in said[0], said
        assert "guidance 1" in said[0] and said[0].endswith(" ms)"), said
        # the autopilot reboots: its clock starts over, and the next overrun is said at once
        clock.t0 -= 500.0
        app.schedule.on_reboot()
        app.worker.on_reboot()
        _slowed(monkeypatch, "_guidance", 1.2)
        assert scan(clock.now())["overrun"] == "guidance"
        assert len([text for _, text in app.events if "over budget" in text]) == 2
    finally:
        tx.close()
        app.stop()
    logged = [json.loads(line) for line in runlog.read_text().splitlines()]
    assert [r["overrun"] for r in logged if r["overrun"]] == ["guidance", "prediction", "update", "wait", "guidance"]
    assert all(set(r["stage_ms"]) == set(OVERRUN_STAGES[1:]) for r in logged)


def test_the_ground_station_reads_the_overrun_stage_from_pmon_stat():
    from groundstation import protocol as P
    from onboard.app.mavlink_connection import mavlink

    def decoded(**values):
        d = dict.fromkeys(STAT_FIELDS, 0.0)
        d.update(values)
        data = [d[f] for f in STAT_FIELDS] + [0.0] * (58 - len(STAT_FIELDS))
        s = P.AppStatus.from_msg(mavlink.MAVLink_debug_float_array_message(0, b"PMON_STAT", 0, data))
        return s.overruns, s.overrun_stage

    assert decoded(overruns=4.0, overrun_stage=3.0) == (4, "guidance")
    assert decoded() == (0, None)  # none yet, or an app older than the fields (their 0 padding)
    assert decoded(overrun_stage=99.0) == (0, None)  # not a stage: none, never an exception
