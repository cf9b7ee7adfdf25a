"""The app as a systemd service (config/systemd/pmon.service, docs/DEPLOY.md): the unit passes
``systemd-analyze verify``; the app speaks systemd's notify protocol (onboard/app/sd_notify.py),
READY=1 once its loop runs and WATCHDOG=1 pings that stop while a tick hangs."""
from __future__ import annotations

import configparser
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest


from tests.support.app_helpers import FaultyTick, wait_for

from onboard.app.df import datagram as dg
from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.autopilot.clock import ManualClock
from onboard.app.sd_notify import Notifier
from onboard.config import load_scenario
from onboard.policy import with_policy

ROOT = Path(__file__).resolve().parents[2]
UNIT = ROOT / "config" / "systemd" / "pmon.service"


def _unit() -> configparser.ConfigParser:
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # systemd's keys are case-sensitive
    cp.read_string(UNIT.read_text().replace("\\\n", " "))
    return cp


def test_the_unit_restarts_on_failure_with_a_watchdog_real_time_limits_and_the_journal():
    s = _unit()["Service"]
    assert s["Type"] == "notify" and s["Restart"] == "on-failure" and float(s["WatchdogSec"]) > 0
    assert s["LimitMEMLOCK"] == "infinity" and s["CPUAffinity"].split()
    assert s["StandardOutput"] == "journal" and s["StandardError"] == "journal"
    argv = shlex.split(s["ExecStart"])
    assert argv[0].endswith("/pmon") and argv[1] == "run"
    rt = int(argv[argv.index("--rt-priority") + 1])
    assert 0 < rt <= int(s["LimitRTPRIO"])  # else the unit's own limit refuses its priority
    import argparse

    from onboard.app.run import add_arguments
    p = argparse.ArgumentParser()
    add_arguments(p)
    run_options = {o for a in p._actions for o in a.option_strings}
    assert {a for a in argv if a.startswith("--")} <= run_options


@pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                    reason="systemd-analyze not installed (apt-get install systemd)")
def test_the_unit_passes_systemd_analyze_verify(tmp_path):
    """As shipped, but for where pmon is installed (verify checks that ExecStart's program exists):
    no error and no warning (verify exits 0 on an unknown key, and warns)."""
    pmon = shutil.which("pmon") or str(Path(sys.executable).parent / "pmon")
    text = UNIT.read_text()
    assert "/opt/pmon/venv/bin/pmon" in text
    (tmp_path / "pmon.service").write_text(text.replace("/opt/pmon/venv/bin/pmon", pmon))
    res = subprocess.run(["systemd-analyze", "verify", str(tmp_path / "pmon.service")],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and res.stderr.strip() == "", res.stderr
    (tmp_path / "pmon.service").write_text(text.replace("/opt/pmon/venv/bin/pmon", pmon)
                                           .replace("WatchdogSec=", "WatchdogSecs="))
    res = subprocess.run(["systemd-analyze", "verify", str(tmp_path / "pmon.service")],
                         capture_output=True, text=True, timeout=60)
    assert "Unknown key 'WatchdogSecs'" in res.stderr  # what the check above would catch


def test_the_notify_socket_from_the_environment():
    assert Notifier.from_env({}) is None  # not a service: nothing sent
    assert Notifier.from_env({"NOTIFY_SOCKET": "relative"}) is None
    n = Notifier.from_env({"NOTIFY_SOCKET": "@pmon-test", "WATCHDOG_USEC": "10000000"})
    assert n.address == "\0pmon-test" and n.watchdog_s == 10.0 and n.ping_every_s == 5.0
    n.close()
    n = Notifier.from_env({"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "1"})
    assert n.watchdog_s is None  # the watchdog is another process's
    assert not n.send("READY=1") and n.failed == 1  # nobody listens: dropped, never raised
    n.close()


class Notifications:
    """The service manager's end: systemd's notify socket, every datagram with its time."""

    def __init__(self):
        self.dir = tempfile.mkdtemp(prefix="pmon-notify-", dir="/tmp")  # AF_UNIX paths: <= 107 bytes
        self.path = os.path.join(self.dir, "notify")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.settimeout(0.05)
        self.got: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop.is_set():
            try:
                self.got.append((time.monotonic(), self.sock.recv(4096).decode()))
            except socket.timeout:
                pass

    def times(self, text: str, since: float = -1.0) -> list[float]:
        return [t for t, m in list(self.got) if m == text and t >= since]

    def close(self):
        self._stop.set()
        self._thread.join(5)
        self.sock.close()
        shutil.rmtree(self.dir, ignore_errors=True)


@pytest.mark.timeout(60)
def test_watchdog_pings_stop_while_a_tick_hangs_and_resume_after(monkeypatch):
    note = Notifications()
    monkeypatch.setenv("NOTIFY_SOCKET", note.path)
    monkeypatch.setenv("WATCHDOG_USEC", "400000")  # a ping every 0.2 s
    tick, release, entered = FaultyTick(), threading.Event(), threading.Event()

    def hang(*a, real, **k):
        entered.set()
        release.wait(30)
        return real(*a, **k)
    clock = ManualClock(50.0)
    app = OnboardApp(AppConfig("udpin:127.0.0.1:0", sensor_port=0), with_policy(load_scenario("paper"), "paper"), clock=clock,
                     tick=tick).start()
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        assert wait_for(lambda: len(note.times("WATCHDOG=1")) >= 3, 10), note.got
        assert note.got[0][1] == "READY=1"
        gaps = [b - a for a, b in zip(note.times("WATCHDOG=1"), note.times("WATCHDOG=1")[1:])]
        assert max(gaps) < 0.4, gaps  # within the watchdog period
        tick.fault = hang
        clock.t = 51.0
        for ch in range(4):
            tx.sendto(dg.encode(51.0, ch, [0.1]), ("127.0.0.1", app.sensor_port))
        assert entered.wait(10)
        hung_at = time.monotonic()
        time.sleep(1.5)  # 3.75 watchdog periods: systemd would have restarted the app
        assert note.times("WATCHDOG=1", since=hung_at + 0.15) == [], note.got[-5:]
        tick.fault = None
        release.set()
        freed = time.monotonic()
        assert wait_for(lambda: len(note.times("WATCHDOG=1", since=freed)) >= 2, 5), note.got[-5:]
        assert wait_for(lambda: any(tk["t"] == 51.0 for tk in app.ticks), 10)
    finally:
        release.set()
        tx.close()
        app.stop()
        time.sleep(0.1)
        note.close()
    assert note.got[-1][1] == "STOPPING=1"
    assert re.fullmatch(r"(READY|WATCHDOG|STOPPING)=1", note.got[1][1])
