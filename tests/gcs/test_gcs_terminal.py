"""Once as an operator would: ``pmon-gcs watch`` in a real terminal (a tmux pane), the live
screen read back while it updates, Ctrl-C to leave (exit 0)."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from onboard.app.mavlink2 import mavlink
from sim.stack.sitl_stack import SitlStack

from tests.support.mavlink_gcs import QUICK_BOOT_S, Gcs

from groundstation.cli import main

pytestmark = [pytest.mark.sitl,
              pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux not installed")]


def _gcs_argv() -> list[str]:
    exe = Path(sys.executable).parent
    script = exe / "pmon-gcs"
    return [str(script)] if script.exists() else [str(exe / "pmon"), "gcs"]


@pytest.mark.timeout(60)
def test_watch_in_a_real_terminal(capsys):
    sock = f"pmon-gcs-test-{uuid.uuid4().hex[:8]}"  # our own tmux server, killed at the end
    tmux = ["tmux", "-L", sock]
    with SitlStack(speedup=4.0, ready_s=QUICK_BOOT_S) as st:
        assert st.wait_ready()
        st.start_feed()
        # The feed's scans start when it sees the vehicle armed, after its truth world's first
        # steps (seconds on a slow machine), and an idle armed copter disarms itself after
        # DISARM_DELAY (10 s, 2.5 s of wall time here): a GCS turns that off first.
        gcs = Gcs(st.ap.port("tcpin", 2))  # the stack's GCS link (st.gcs_url)
        try:
            ack = gcs.param_set("DISARM_DELAY", 0, timeout=10, comp=1, ptype=mavlink.MAV_PARAM_TYPE_INT8)
            assert ack is not None and ack.param_value == 0
        finally:
            gcs.close()
        assert main(["--connect", st.gcs_url, "arm"]) == 0  # the feed's scans start at arming
        cmd = " ".join(_gcs_argv() + ["--connect", st.gcs_url, "watch", "--duration", "40"])
        try:
            subprocess.run(tmux + ["new-session", "-d", "-s", "w", "-x", "110", "-y", "30",
                                   f"{cmd}; echo EXIT=$?; sleep 30"], check=True,
                           env=dict(os.environ, TERM="xterm-256color"))

            def screen() -> str:
                return subprocess.run(tmux + ["capture-pane", "-p", "-t", "w"], capture_output=True,
                                      text=True).stdout

            def tick_on_screen(text):
                m = re.search(r"tick t=([\d.]+) s", text)
                return float(m.group(1)) if m else None

            deadline = time.monotonic() + 25
            first = None
            while time.monotonic() < deadline:
                s = screen()
                if all(re.search(rf"│\s+T{j} │", s) for j in range(1, 5)) and tick_on_screen(s):
                    first = s
                    break
                time.sleep(0.3)
            assert first is not None, screen()
            assert "pmon watch: app idle" in first and "vehicle GUIDED" in first
            # the same screen (no scrolling output) shows a later tick a moment later
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and tick_on_screen(screen()) == tick_on_screen(first):
                time.sleep(0.2)
            later = screen()
            assert tick_on_screen(later) > tick_on_screen(first), later
            assert later.count("pmon watch:") == 1
            subprocess.run(tmux + ["send-keys", "-t", "w", "C-c"], check=True)
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and "EXIT=" not in screen():
                time.sleep(0.2)
            assert "EXIT=0" in screen()
        finally:
            subprocess.run(tmux + ["kill-server"], capture_output=True)
