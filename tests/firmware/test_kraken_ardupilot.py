"""``pmon demo --df kraken`` on ArduPilot's own ArduCopter SITL (issue 32): the simulated KrakenSDR
stamps its frames with the firmware's UTC (SYSTEM_TIME) and draws them at its heading
(GLOBAL_POSITION_INT.hdg); the app maps them back through the same messages. The mock's version:
tests/sim/test_kraken_sitl.py (skipped where this runs in the same session: ``mock_of``).

Every run's app.log ends with "KrakenSDR unreachable: ... Connection reset by peer" and status.json
refused: the feed closes its server once its last frame was read, before the app is stopped (not
a failure). "Frames written but not read" is one: the feed, descheduled, once wrote two frames
back to back, and the app lost the first (sim/stack/kraken.py ``MIN_SHOWN_S`` now holds the second;
tests/sim/test_kraken_feed_behind.py)."""
from __future__ import annotations

import json
import re

import pytest

from sim.firmware.ardupilot import skip_reason

pytestmark = [pytest.mark.ardupilot, pytest.mark.sitl,
              pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")]


@pytest.mark.timeout(420)
def test_pmon_demo_df_kraken_on_ardupilots_own_sitl(tmp_path):
    """Every frame the simulated KrakenSDR wrote is one the app used, none refused, and the
    mission is scored."""
    import subprocess
    import sys
    from pathlib import Path

    out = tmp_path / "d"
    p = subprocess.run([sys.executable, "-m", "onboard.cli", "demo", "--df", "kraken", "--autopilot", "ardupilot",
                        "--speedup", "3", "--duration", "20", "--out", str(out)],
                       cwd=Path(__file__).resolve().parents[2], capture_output=True, text=True, timeout=400)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-2000:]
    rep = json.loads((out / "report.json").read_text())
    assert rep["scored_ticks"] >= 19 and len(rep["rmse_m"]) == 4, rep
    feed_log, app_log = (out / "feed.log").read_text(), (out / "app.log").read_text()
    written = re.search(r"feed: KrakenSDR: (\d+) frames written, (\d+) scans without", feed_log)
    assert written and int(written.group(1)) == 20 and int(written.group(2)) == 0, feed_log[-1500:]
    used = re.search(r"pmon run: KrakenSDR: \d+ lines, (\d+) frames \((\d+) missed\), (\d+) scans, (\d+) rejected \{\}",
                     app_log)
    assert used and (int(used.group(1)), int(used.group(2)), int(used.group(3))) == (20, 0, 80), app_log[-1500:]
    # KrakenSDR's status.json is there from its start (the app may find it gone once the feed ended)
    assert "HTTP 404" not in app_log, app_log[-1500:]
    assert (out / "kraken" / "DOA_value.html").exists()
