"""``pmon gcs view``: the live page in a real browser during a SITL mission (tests/support/viewcheck.py
says what is checked), through the autopilot's routing and on a link that carries only the
companion's messages; the HTTP side and the command's errors."""
from __future__ import annotations

import json
import os
import socket
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest

from sim.stack.sitl_stack import SitlStack

from groundstation import gcs_commands as C
from groundstation.cli import main
from groundstation.gcs_link import GcsLink
from tests.support.viewcheck import browser_unavailable, check_live_view, summary
from tests.support.mavlink_gcs import QUICK_BOOT_S

pytestmark = pytest.mark.sitl


@pytest.fixture(scope="module")
def mission():
    """The SITL stack flying the paper scenario, launched by the app (GUIDED, arm, take off,
    start), the feed on."""
    with SitlStack(speedup=2.0, gcs_udpin=True, ready_s=QUICK_BOOT_S) as st:
        st.start_feed()
        with GcsLink(st.gcs_url, 10.0) as gl:
            gl.connect()
            C.app_action(gl, "launch")
            assert gl.wait_for(lambda: gl.v.app_state == "monitoring", 40), gl.v.app_state
        yield st


@pytest.mark.timeout(150)
def test_the_page_draws_every_target_where_its_estimate_is(mission, tmp_path):
    why = browser_unavailable()
    if why:
        pytest.skip(why)
    shot = os.environ.get("PMON_VIEW_SCREENSHOT") or str(tmp_path / "view.png")
    rep = check_live_view(mission.gcs_url, "paper", seconds=12, screenshot=shot)
    print(summary(rep))
    assert rep.checked_markers >= 4 * 10 and rep.ticks_shown >= 10
    assert os.path.getsize(shot) > 20_000
    assert rep.phone["frames"] >= 1


@pytest.mark.timeout(120)
def test_the_page_on_a_link_to_the_companion_alone(mission, tmp_path):
    """Only component 191's packets reach the view (as on a link to the companion computer):
    no autopilot heartbeat, the vehicle's mode from the app's PMON_STAT."""
    why = browser_unavailable()
    if why:
        pytest.skip(why)
    from tests.support.ack_dropper import AckDropper
    relay = AckDropper(mission.udpin_port, lambda msgid, comp, payload: comp != 191)
    try:
        # connect() waits its whole timeout for an autopilot that never speaks, then goes on
        rep = check_live_view(f"udpout:127.0.0.1:{relay.port}", "paper", seconds=5, phone=False, timeout=3)
        assert rep.checked_markers >= 4 * 4 and relay.dropped
        assert rep.state["vehicle"] == {"mode": "GUIDED", "armed": True, "from": "app"}
    finally:
        relay.close()


# ----------------------------------------------------------------------------- the command
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.timeout(60)
def test_the_command_serves_the_page_and_the_snapshots(mission, capsys):
    port = _free_port()
    got = {}

    def client():
        base = f"http://127.0.0.1:{port}/"
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(base, timeout=2) as r:
                    got["html"] = r.read()
                break
            except OSError:
                time.sleep(0.1)
        with urllib.request.urlopen(base + "scene.json", timeout=2) as r:
            got["scene"] = json.loads(r.read())
        with urllib.request.urlopen(base + "events", timeout=5) as r:  # Server-Sent Events
            events = []
            mission.app.say("view test: a warning", 4)  # MAV_SEVERITY_WARNING
            while len(events) < 3:
                line = r.readline()
                if line.startswith(b"data: "):
                    events.append(json.loads(line[6:]))
            got["events"] = events
        try:
            urllib.request.urlopen(base + "nope", timeout=2)
        except urllib.error.HTTPError as exc:
            got["404"] = exc.code
        try:  # a page of another site whose name was rebound to 127.0.0.1 gets nothing
            urllib.request.urlopen(urllib.request.Request(base + "state.json", headers={"Host": "evil.example:80"}),
                                   timeout=2)
        except urllib.error.HTTPError as exc:
            got["403"] = exc.code
    th = threading.Thread(target=client)
    th.start()
    capsys.readouterr()
    rc = main(["--connect", mission.gcs_url, "--json", "view", "--port", str(port), "--duration", "5"])
    th.join(timeout=10)
    out = capsys.readouterr().out.splitlines()
    assert rc == 0
    assert json.loads(out[0]) == {"url": f"http://127.0.0.1:{port}/", "scenario": "paper"}
    assert json.loads(out[-1])["ok"] is True and json.loads(out[-1])["updates"] >= 3
    assert b"/view.js" in got["html"] and got["404"] == 404 and got["403"] == 403
    sc = got["scene"]
    assert [o["name"] for o in sc["obstacles"]] == ["O1", "O2", "O3", "O4"]
    assert sc["colours"]["targets"][:4] == ["#d62728", "#1f77b4", "#9467bd", "#2ca02c"]
    ev = got["events"][-1]
    assert ev["app"]["state"] == "monitoring" and len(ev["targets"]) == 4
    assert ev["vehicle"] == {"mode": "GUIDED", "armed": True, "from": "autopilot"}
    # O1 (60 m) and O3 (50 m) stand above h = 40 m; O2 (30 m) and O4 (25 m) do not
    assert ev["blocked"] == [True, False, True, False]
    assert any(m["text"] == "PMON: view test: a warning" and m["severity"] == 4 and m["source"] == "app"
               for m in ev["texts"]), ev["texts"]
    ticks = [e["app"]["tick_time_s"] for e in got["events"] if e["app"]]
    assert len(ticks) >= 2 and ticks == sorted(set(ticks))  # the mission clock runs, a snapshot per tick
    # nothing listens any more, and the same port serves again at once
    with socket.socket() as s, pytest.raises(ConnectionRefusedError):
        s.connect(("127.0.0.1", port))
    rc = main(["--connect", mission.gcs_url, "view", "--port", str(port), "--duration", "0.5"])
    assert rc == 0 and capsys.readouterr().out.startswith(f"view: http://127.0.0.1:{port}/")


def test_view_usage_errors_exit_2(capsys):
    for argv, msg in ((["view", "--port", "70000"], "--port must be in 0..65535"),
                      (["view", "--duration", "0"], "--duration must be > 0"),
                      (["view", "--scenario", "nope.yaml"], "--scenario nope.yaml: cannot read")):
        capsys.readouterr()
        rc = main(["--connect", "udpin:127.0.0.1:1", "--timeout", "0.5", *argv])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and len(err.splitlines()) == 1 and msg in err, (argv, err)


@pytest.mark.timeout(30)
def test_a_port_in_use_is_one_line_exit_1(mission, capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        rc = main(["--connect", mission.gcs_url, "view", "--port", str(port), "--duration", "1"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err == f"pmon gcs: view: cannot serve on 127.0.0.1:{port}: Address already in use"


@pytest.mark.timeout(60)
def test_watch_png_draws_the_whole_scene(mission, tmp_path, capsys):
    import matplotlib.image as mpimg

    from groundstation.scene import BLOCKING_COLOUR, GOAL_COLOUR

    png = tmp_path / "live.png"
    rc = main(["--connect", mission.gcs_url, "--json", "watch", "--count", "2", "--png", str(png)])
    assert rc == 0 and png.exists()
    img = (mpimg.imread(png)[:, :, :3] * 255).round()

    def pixels(hex_colour, tol=6):
        rgb = np.array([int(hex_colour[i:i + 2], 16) for i in (1, 3, 5)])
        return int((np.abs(img - rgb).max(axis=2) <= tol).sum())
    assert pixels(BLOCKING_COLOUR) > 2000  # O1 and O3, above h
    goal = np.array([int(GOAL_COLOUR[i:i + 2], 16) for i in (1, 3, 5)]) * 0.25 + 255 * 0.75  # alpha 0.25 on white
    assert int((np.abs(img - goal).max(axis=2) <= 6).sum()) > 1000
