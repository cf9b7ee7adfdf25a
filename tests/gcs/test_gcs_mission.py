"""The ground-station CLI alone flies a whole mission against the SITL stack (mock ArduCopter,
onboard app, DF feed on loopback TCP; 2x: the three share one GIL here), as an operator would: every step through
``groundstation.cli.main(argv)`` and its exit code, output and --json."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from sim.stack.sitl_stack import SitlStack

from groundstation.cli import main
from tests.support.mavlink_gcs import QUICK_BOOT_S

pytestmark = [pytest.mark.sitl, pytest.mark.slow]


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    out = tmp_path_factory.mktemp("mission")
    st = SitlStack(speedup=2.0, ready_s=QUICK_BOOT_S, runlog_path=str(out / "run.jsonl"), truth_path=str(out / "truth.jsonl"))
    st.start()
    assert st.wait_ready()
    st.out = out
    try:
        yield st
    finally:
        st.stop()


def gcs(stack, capsys, *argv):
    """Run one CLI command; (exit code, stdout, stderr)."""
    capsys.readouterr()
    rc = main(["--connect", stack.gcs_url, "--timeout", "5", *argv])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def gcs_json(stack, capsys, *argv):
    rc, out, err = gcs(stack, capsys, "--json", *argv)
    return rc, [json.loads(line) for line in out.splitlines() if line.strip()], err


@pytest.mark.timeout(90)
def test_the_cli_flies_a_whole_mission(stack, capsys):
    ap, app = stack.ap, stack.app
    # before anything: idle app, disarmed vehicle; start is refused with the reason
    rc, [s], _ = gcs_json(stack, capsys, "status")
    assert rc == 0 and s["vehicle"]["armed"] is False and s["app"]["state"] == "idle"
    assert s["vehicle"]["battery_pct"] == 100 and abs(s["vehicle"]["lat_deg"] - 35.1468) < 1e-3  # home: the UAV start
    assert s["app"]["params"]["PMON_ALT"] == 40
    rc, out, err = gcs(stack, capsys, "start")
    assert rc == 1 and err.strip() == "pmon gcs: start refused by the onboard app (DENIED): vehicle not armed"
    assert out == ""

    rc, out, _ = gcs(stack, capsys, "arm")
    assert rc == 0 and "GUIDED, armed" in out and ap.state().armed and ap.state().mode_name == "GUIDED"
    # the app hears the arming on its own link, up to a heartbeat period after the GCS does
    assert ap.wait_until(lambda s: app.vehicle.armed, 2)
    rc, _, err = gcs(stack, capsys, "start")
    assert rc == 1 and "vehicle not flying" in err

    rc, out, _ = gcs(stack, capsys, "takeoff", "40", "--wait", "--timeout", "40")
    assert rc == 0 and "at 40 m" in out and ap.state().alt_rel > 38.5
    # flying, but no DF data yet: refused, try later
    rc, _, err = gcs(stack, capsys, "start")
    assert rc == 1 and "TEMPORARILY_REJECTED" in err and "no DF data" in err

    stack.start_feed()
    assert ap.wait_until(lambda s: app.scans.accepted >= 4, 15)
    rc, [r], _ = gcs_json(stack, capsys, "start")
    assert rc == 0 and r["result"] == "ACCEPTED" and r["app_state"] == "monitoring"
    assert app.state == 1

    # a few watch updates, every target shown each time
    rc, updates, _ = gcs_json(stack, capsys, "watch", "--count", "3")
    assert rc == 0 and len(updates) == 3
    for u in updates:
        assert [t["name"] for t in u["targets"]] == ["T1", "T2", "T3", "T4"]
        assert u["app_state"] == "monitoring" and u["uav_enu_m"] is not None
    assert updates[-1]["next_enu_m"] is not None
    rc, out, _ = gcs(stack, capsys, "watch", "--count", "1")  # the human table
    assert rc == 0 and all(f"T{j}" in out for j in range(1, 5)) and "next waypoint" in out

    # a parameter change reaches the running app and shows in status; h moves the setpoints
    rc, out, _ = gcs(stack, capsys, "params", "set", "pmon_alt", "45")
    assert rc == 0 and out.startswith("PMON_ALT = 45") and app.params["PMON_ALT"] == 45
    n = app.counters.get("ticks", 0)
    assert ap.wait_until(lambda s: app.counters.get("ticks", 0) >= n + 2, 10)
    rc, [s], _ = gcs_json(stack, capsys, "status")
    assert rc == 0 and s["app"]["params"]["PMON_ALT"] == 45
    assert s["app"]["next_enu_m"][2] == pytest.approx(45.0)
    rc, out, _ = gcs(stack, capsys, "status")
    assert "ALT=45" in out and "onboard app: monitoring" in out

    # pause, resume, stop: the app's state follows, each once
    for cmd, state in (("pause", 2), ("resume", 1), ("stop", 0)):
        rc, [r], _ = gcs_json(stack, capsys, cmd)
        assert rc == 0 and r["result"] == "ACCEPTED" and app.state == state, (cmd, r)
    # record a little telemetry, hold, then RTL
    tlog = stack.out / "gcs.tlog"
    rc, [r], _ = gcs_json(stack, capsys, "record", str(tlog), "--duration", "3")  # 1.5 s got 17-18 at load 10
    assert rc == 0 and r["messages"] > 20 and tlog.stat().st_size > 1000
    rc, out, _ = gcs(stack, capsys, "hold")
    assert rc == 0 and ap.state().mode_name == "BRAKE"
    rc, out, _ = gcs(stack, capsys, "rtl")
    assert rc == 0 and "mode RTL" in out and ap.state().mode_name == "RTL"
    assert sum("paused: setpoints stopped" in text for _, text in app.events) == 1

    # the flight afterwards: from the app's run log (with truth) and from the GCS's own tlog
    rc, [p], _ = gcs_json(stack, capsys, "plot", str(stack.out / "run.jsonl"), "--scenario", "paper")
    assert rc == 0 and p["tracks"] == 4 and p["truth"] is True and p["uav_points"] > 5
    assert (stack.out / "run.png").stat().st_size > 20_000
    rc, [p], _ = gcs_json(stack, capsys, "plot", str(tlog), "--out", str(stack.out / "tlog.png"))
    assert rc == 0 and p["tracks"] == 4 and p["uav_points"] >= 1
    # and for map tools: GeoJSON and KML from both logs
    from tests.support.geojson_check import assert_geojson_in_area
    for log in (stack.out / "run.jsonl", tlog):
        rc, [p], _ = gcs_json(stack, capsys, "export", str(log))
        assert rc == 0 and p["tracks"] == 4 and [Path(f).suffix for f in p["files"]] == [".geojson", ".kml"]
        assert_geojson_in_area(p["files"][0], stack.sc)
