"""The simulated flight's scheduling (sim/firmware/priority.py): with PMON_SIM_RT_PRIORITY=N the rig's app
runs at --rt-priority N and each process standing in for the vehicle's other computers at FIFO
N + 1; unset, everything at normal scheduling; a bad value is refused naming the variable."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from sim.firmware.priority import ENV, app_priority, fifo_argv, fifo_permitted, vehicle_priority


def _classes(pid: int) -> dict[str, tuple[int, int]]:
    """Thread name -> (policy, priority) of each thread of ``pid``."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as f:
                name = f.read().strip()
            out[name] = (os.sched_getscheduler(int(tid)), os.sched_getparam(int(tid)).sched_priority)
        except OSError:  # the thread ended meanwhile
            continue
    return out


def test_the_variable_is_read_and_checked(monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    assert (app_priority(), vehicle_priority()) == (0, 0)
    monkeypatch.setenv(ENV, "40")
    assert (app_priority(), vehicle_priority()) == (40, 41)
    monkeypatch.setenv(ENV, "0")
    assert (app_priority(), vehicle_priority()) == (0, 0)
    for bad in ("98", "-1", "forty", "4 0", "٤"):
        monkeypatch.setenv(ENV, bad)
        with pytest.raises(ValueError, match=ENV):
            app_priority()
    assert fifo_argv(["x", "y"], 0) == ["x", "y"]


@pytest.mark.skipif(not fifo_permitted(41), reason="SCHED_FIFO is not permitted here")
def test_a_program_started_at_fifo_keeps_it_in_the_threads_it_starts():
    code = "import threading,time; t=threading.Thread(target=time.sleep,args=(5,),name='child'); t.start(); print('up',flush=True); t.join()"
    p = subprocess.Popen(fifo_argv([sys.executable, "-c", code], 41), stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "up"
        classes = _classes(p.pid)
        assert classes and all(c == (os.SCHED_FIFO, 41) for c in classes.values()), classes
    finally:
        p.kill()
        p.wait(10)


@pytest.mark.sitl
@pytest.mark.skipif(not fifo_permitted(41), reason="SCHED_FIFO is not permitted here")
def test_the_rigs_app_and_vehicle_run_at_the_documented_priorities(monkeypatch, tmp_path):
    from sim.stack.rig import Rig, RigConfig

    monkeypatch.setenv(ENV, "40")
    with Rig(RigConfig(feed_start="now", out_dir=str(tmp_path))) as rig:
        deadline = time.monotonic() + 20.0  # the worker thread starts after the DF port is printed
        while "pmon-worker" not in (app := _classes(rig.app.p.pid)) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert app.get("pmon-io") == (os.SCHED_FIFO, 40) and app.get("pmon-worker") == (os.SCHED_FIFO, 39), app
        for proc in (rig.ap.proc.p, rig.feed.p):  # the mock autopilot's process, the DF feed's
            classes = _classes(proc.pid)
            while "chrt" in classes and time.monotonic() < deadline:  # not yet exec'd past chrt
                time.sleep(0.05)
                classes = _classes(proc.pid)
            assert classes and all(c == (os.SCHED_FIFO, 41) for c in classes.values()), (proc.args, classes)
    monkeypatch.setenv(ENV, "0")
    with Rig(RigConfig(feed_start="now", out_dir=str(tmp_path / "normal"))) as rig:
        for proc in (rig.app.p, rig.ap.proc.p, rig.feed.p):
            assert all(c[0] == os.SCHED_OTHER for c in _classes(proc.pid).values()), proc.args
