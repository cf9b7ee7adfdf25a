"""Advisory (issue 48) against ArduPilot's own firmware: ArduCopter SITL flies a waypoint mission
in AUTO, uploaded as a ground station does, while ``pmon run --advise`` tracks, plans from
where the copter is and publishes the next waypoint. What the app sends its autopilot is counted
on the link, by a relay between the two (sim/stack/link_count.py, its kinds): not one command reaches
the firmware while advising. ``pmon gcs watch --json`` and the live view show the advised
waypoint; one ``pmon gcs start`` hands over: GUIDED entered, the app's setpoints flow.
The mock's version, with the refusals: tests/app/test_advisory.py."""
from __future__ import annotations

import io
import json
import math
import threading
import urllib.request

import numpy as np
import pytest

from onboard.app.contract import APP_COMPID
from onboard.app.mavlink_connection import mavlink
from sim.firmware.ardupilot import skip_reason
from sim.stack.link_count import LinkCounter
from sim.stack.mission_upload import upload
from sim.stack.procedure import BOOT_FAST_UNTIL_S, RECOMMENDED_PARAMS, Mission, MissionConfig

pytestmark = [pytest.mark.ardupilot, pytest.mark.sitl, pytest.mark.timeout(900),
              pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")]

ADVISE_S = 60.0  # autopilot s of the mission flown in AUTO while the app advises
# the mission: a square around the targets' side of the area, mission ENU m (the scenario's frame)
SQUARE_ENU = ((150.0, 450.0), (550.0, 450.0), (550.0, 650.0), (150.0, 650.0))
GUIDED = 4


def _view_state(url: str, scenario: str, seconds: float) -> list[dict]:
    """The live view (groundstation/view.py) of the flight on ``url``: its /state.json, once a
    second for ``seconds`` wall s."""
    from rich.console import Console

    from groundstation.gcs_link import GcsLink
    from groundstation.view import serve
    from onboard.config import load_scenario

    ready, stop, server, states = threading.Event(), threading.Event(), [], []
    gl = GcsLink(url, 10.0)

    def run():
        try:
            gl.connect()
            serve(gl, load_scenario(scenario), 0, None, False, Console(file=io.StringIO()),
                  on_ready=lambda srv: (server.append(srv), ready.set()), stop=stop)
        finally:
            ready.set()
    th = threading.Thread(target=run, name="pmon-view", daemon=True)
    th.start()
    try:
        assert ready.wait(20) and server, "the view did not start"
        for _ in range(int(seconds)):
            stop.wait(1.0)
            with urllib.request.urlopen(server[0].url + "state.json", timeout=5) as r:
                states.append(json.loads(r.read()))
        return states
    finally:
        stop.set()
        th.join(timeout=10)
        gl.close()


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    out = tmp_path_factory.mktemp("ardupilot_advisory")
    rec: dict = {"out": out}
    counter = LinkCounter(compid=APP_COMPID)
    # DISARM_DELAY 0: the take-off's pmon gcs, started at nice 19 on a loaded machine, came 13
    # autopilot s after the arm at speedup 3, past the 10 s ArduCopter disarms an idle copter after
    # speedup 2: at 3 a loaded machine's overruns skipped scans (counted; the test allows them)
    cfg = MissionConfig(speedup=2.0, params={**RECOMMENDED_PARAMS, "DISARM_DELAY": 0}, feed_duration_s=600,
                        seed=5, link_proxy=True, app_args=("--advise",))
    with Mission(cfg, out, link_tap=counter.feed) as m:
        rec["m"] = m
        m.fast_boot()
        # armed only at the flight's speedup: DISARM_DELAY (10 s) passes in 1 wall s at the boot's
        m.wait(lambda o: (o.t or 0.0) >= BOOT_FAST_UNTIL_S + 1.0, 120, "the boot's speedup over")
        # the pilot's ground station (the operator's pmon gcs, sysid 255) takes off ...
        rec["arm"] = m.gcs("arm", "--wait", timeout=120)
        rec["takeoff"] = m.gcs("takeoff", "40", "--wait")
        # ... uploads a mission and sets AUTO: the firmware flies it by itself
        wps = [m.frame.geodetic_from_enu((e, n, 0.0))[:2] + (40.0,) for e, n in SQUARE_ENU]
        rec["upload"] = upload(m.spare_url, wps)
        rec["auto"] = m.gcs("mode", "AUTO")
        rec["t_auto"] = m.observer.t
        m.sim_sleep(ADVISE_S / 2)
        rec["watch"] = m.gcs("watch", "--json", "--count", "3", timeout=10)
        rec["view"] = _view_state(m.spare_url, cfg.scenario, 5)
        m.sim_sleep(ADVISE_S / 2)
        rec["t_start"] = m.observer.t
        rec["advisory_counts"] = counter.snapshot()
        rec["bad"] = counter.bad
        rec["positions"] = [p for p in m.observer.positions if p[0] is not None and p[0] >= rec["t_auto"]]
        rec["modes_advisory"] = [md for md in m.observer.modes if md[0] is not None and md[0] >= rec["t_auto"]]
        # one command hands over
        rec["start"] = m.gcs("start")
        rec["monitoring"] = m.wait(lambda o: o.app_state == "monitoring" and o.modes and o.modes[-1][1] == GUIDED,
                                   30, "monitoring in GUIDED")
        m.sim_sleep(10.0)
        rec["after_start"] = counter.commands()
        rec["status"] = m.gcs("status")
    with open(out / "run.jsonl") as f:
        rec["ticks"] = [json.loads(line) for line in f]
    yield rec


def _ok(call, *want):
    assert call.rc == 0, f"pmon gcs {' '.join(call.args)}: exit {call.rc}: {call.stderr.strip()}"
    for w in want:
        assert w in call.stdout, f"pmon gcs {' '.join(call.args)}: {w!r} not in {call.stdout!r}"
    return call


def test_the_mission_flies_in_auto_and_no_command_of_the_app_reaches_the_firmware(flight):
    _ok(flight["arm"], "armed")
    _ok(flight["takeoff"], "at 40 m after")
    assert flight["upload"] == "MAV_MISSION_ACCEPTED"
    _ok(flight["auto"])
    assert [md[1] for md in flight["modes_advisory"]] in ([3], []), flight["modes_advisory"]  # AUTO throughout
    lat_lon = np.array([p[1:3] for p in flight["positions"]])
    span = np.hypot(*(lat_lon.max(0) - lat_lon.min(0)) * (111_320.0, 111_320.0 * math.cos(math.radians(lat_lon[0, 0]))))
    assert span > 150.0, span  # it flew the mission
    kinds, types = flight["advisory_counts"]
    print(f"advisory, from the app's start to the hand-over ({flight['t_start'] - flight['t_auto']:.0f} autopilot s "
          f"of them in AUTO, the copter over {span:.0f} m): what reached the firmware from the app: {kinds}; "
          f"by type {types}; unreadable frames {flight['bad']}")
    assert kinds.get("command", 0) == 0, types
    assert flight["bad"] == 0  # every byte the app sent was read: nothing passed uncounted
    assert kinds.get("telemetry", 0) > 100


def test_estimates_and_a_plan_from_the_vehicle_every_tick_while_advising(flight):
    ticks = [t for t in flight["ticks"] if flight["t_auto"] + 2.0 <= t["t"] <= flight["t_start"] - 1.0]
    assert len(ticks) >= ADVISE_S * 0.9, len(ticks)
    assert all(t["state"] == 5 for t in ticks)
    # a tick (estimates, PMON_TGT, a plan) every scan, or the scan counted skipped by an overrun
    # (the app's way under load, any state: docs/MAVLINK.md "The 1 Hz loop"): none lost unsaid
    gaps = np.diff([t["t"] for t in ticks])
    skipped = [t["skipped_before"] for t in ticks[1:]]
    assert np.allclose(gaps, 1.0 + np.array(skipped)), list(zip(gaps, skipped))
    print(f"advisory: {len(ticks)} ticks in AUTO, {sum(skipped)} scans skipped by overruns, each tick planned "
          f"from the vehicle")
    assert all(t["next"] is not None and t["plan_from"] == t["uav_enu"] and not t["sent"] for t in ticks)


def test_watch_and_the_view_show_the_advised_waypoint(flight):
    lines = [json.loads(s) for s in _ok(flight["watch"]).stdout.splitlines() if s.startswith("{")]
    assert len(lines) == 3
    for u in lines:
        assert u["app_state"] == "advisory" and u["next_enu_m"] is None, u
        assert u["advice_enu_m"] is not None and abs(u["advice_enu_m"][2] - 40.0) < 0.5, u
        assert len(u["targets"]) == 4
    views = [s for s in flight["view"] if s["app"] and s["app"]["state"] == "advisory"]
    assert len(views) >= 3 and all(s["advice"] is not None and s["setpoint"] is None for s in views), flight["view"]


def test_one_start_hands_over_guided_entered_and_setpoints_flow(flight):
    _ok(flight["start"], "app monitoring")
    assert flight["monitoring"]
    sent = flight["after_start"]
    print("after the start, the app's commands:", sent)
    assert sent.get("SET_POSITION_TARGET_LOCAL_NED", 0) >= 50
    assert sent.get(f"COMMAND_LONG:{mavlink.MAV_CMD_DO_SET_MODE}", 0) >= 1
    _ok(flight["status"], "onboard app: monitoring")
