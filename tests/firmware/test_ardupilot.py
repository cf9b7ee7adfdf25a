"""The documented procedure (docs/SITL.md) against ArduPilot's own firmware: ArduCopter SITL
(4.4.0-dev, ../shared/ardupilot or $PMON_ARDUPILOT_SITL), with the real programs (``pmon run``,
``pmon feed live``, ``pmon gcs``) as processes, accelerated with SITL's --speedup, each flight
on a SITL instance of its own (sim/stack/procedure.py). Nothing here knows the firmware is a SITL.

Two flights, each checked by several tests:

A. stock parameters (WPNAV_SPEED 10 m/s): the operator sends ``pmon gcs launch`` right after the
   autopilot boots; the app waits out the pre-arm checks, arms, takes off and starts; >= 100 s
   of monitoring; parameters and status through ArduPilot's routing (SERIAL2); a pilot takes
   over twice (LOITER, BRAKE) and the operator resumes; ``pmon locate`` reads the firmware's own
   DataFlash log of it.
B. recommended parameters (docs/SITL.md), the app on a link that can be cut: ``pmon gcs arm
   --wait``, ``takeoff 40 --wait``, ``start``; the link drops for 3 s and the app reconnects;
   the autopilot is stopped and restarted (a reboot); the operator launches again.
"""
from __future__ import annotations

import re
import time

import numpy as np
import pytest

from onboard.app.mavlink_connection import mavlink
from sim.firmware.ardupilot import skip_reason
from sim.stack.procedure import RECOMMENDED_PARAMS, Mission, MissionConfig, fly_launch_procedure
from sim.stack.tick_account import TickAccount

from tests.support.plan_checks import assert_plans_start_at_their_scans_and_join

pytestmark = [pytest.mark.ardupilot, pytest.mark.sitl,
              pytest.mark.skipif(skip_reason() is not None, reason=skip_reason() or "")]

# time-averaged position error of every target's estimate over a flight: a bound on loss, not the
# accuracy (that is the evaluation's, docs/RESULTS.md). With the motion modes the flight default has
# heavier tails (a target's estimate runs along the line of sight for a while, then is found again):
# 72.5 m for T1 in one flight (232 m off at t = 95 s, 3-15 m from t = 113 s on); 60 m before them
RMSE_MAX_M = 80.0
MONITOR_S = 100.0  # autopilot s of monitoring in flight A before the pilot takes over
TICK_S = 1.0  # one tick: the longest a takeover may take to stop the setpoints
FOLLOW_MEDIAN_M, FOLLOW_P95_M = 0.5, 1.0  # copter from the planned point at the next tick (issue 29: p95 <= 1.5)


def _ok(call, *want):
    assert call.rc == 0, f"pmon gcs {' '.join(call.args)}: exit {call.rc}: {call.stderr.strip()}"
    for w in want:
        assert w in call.stdout, f"pmon gcs {' '.join(call.args)}: {w!r} not in {call.stdout!r}"
    return call


def _view(m: Mission, out):
    """``pmon gcs view`` in headless Chromium during the flight (tests/support/viewcheck.py), or why not."""
    from tests.support.viewcheck import browser_unavailable, check_live_view
    if (why := browser_unavailable()):
        return why
    try:
        return check_live_view(m.spare_url, m.cfg.scenario, seconds=20 / m.cfg.speedup,
                               screenshot=out / "view.png")
    except AssertionError as exc:
        return exc


def _expected(rec: dict) -> dict:
    """A tick record as sim.stack.tick_account.TickAccount matches the autopilot's targets to it."""
    e, n, u = rec["next"]
    return {"t": rec["t"], "e": e, "n": n, "u": u, "segment": rec.get("segment")}


def _ran_once(m: Mission) -> None:
    """0 operator retries: no command of the procedure was given twice in a row."""
    names = [c.args for c in m.commands if c.args[:1] not in (("status",), ("params",))]
    repeats = [a for a, b in zip(names, names[1:]) if a == b]
    assert not repeats, f"commands repeated: {repeats}"


# --------------------------------------------------------------------------- flight A
@pytest.fixture(scope="module")
def flight_a(tmp_path_factory):
    out = tmp_path_factory.mktemp("ardupilot_a")

    def during(m, rec):  # the operator looks and tunes while it monitors (~20 s of mission)
        rec["status"] = m.gcs("status")
        rec["view"] = _view(m, out)  # the operator's browser, on a port of its own
        rec["param_get"] = m.gcs("params", "get", "PMON_CLUTTER")
        rec["param_set"] = m.gcs("params", "set", "PMON_CLUTTER", "1.5")
        rec["param_bad"] = m.gcs("params", "set", "PMON_PD", "1.5")
        rec["param_after"] = m.gcs("params", "get", "PMON_CLUTTER")
    # 1.5x: the 0.9 s tick budget is 0.6 s of wall time; a lookahead plan on a loaded 2-core
    # machine took 0.52 s once (at 2x it was late)
    with Mission(MissionConfig(speedup=1.5, feed_duration_s=MONITOR_S + 60, seed=1), out) as m:
        rec = fly_launch_procedure(m, MONITOR_S, during, fast_boot=True)  # the boot until 35 s at 10x
        rec["m"] = m
        rec["gcs_saw_estimates"] = sorted({e[1] for e in m.observer.estimates})
    yield rec


def test_launch_from_boot_waits_for_the_autopilot_and_flies_without_a_retry(flight_a):
    m = flight_a["m"]
    _ok(flight_a["launch"], "accepted by the onboard app")
    texts = m.observer.app_texts()
    assert any("waiting for the autopilot" in t for t in texts), texts  # it did have to wait
    assert any("launch: armed" in t for t in texts) and "PMON: monitoring started" in texts, texts
    assert not any("launch failed" in t or "launch aborted" in t for t in texts), texts
    _ran_once(m)
    assert m.autopilot_crashes() == 0
    assert m.sitl.boots == 1


def test_every_scan_is_ticked_and_every_setpoint_reaches_the_autopilot(flight_a):
    m = flight_a["m"]
    acc = m.tick_account()
    assert acc["scans"] >= MONITOR_S, acc
    assert acc["scans_unticked"] == 0 and acc["ticks_skipped"] == 0, acc
    assert acc["monitoring_ticks"] >= MONITOR_S, acc
    assert acc["ticks_late"] == 0, acc  # every monitoring tick's setpoint held by the autopilot in time


def test_the_copter_flies_the_plan_instead_of_braking_to_each_point(flight_a):
    """issue 24: the plan's position + velocity + acceleration, carried on by ArduCopter between
    messages: at the next tick the copter is where the plan said (position-only setpoints, which
    it brakes to, left it a median 15 m short: bench/ardupilot.py --policy paper). Issue 29: within
    FOLLOW_MEDIAN_M / FOLLOW_P95_M: each plan starts at its scan and its acceleration is continuous,
    which the firmware's jerk-limited shaper follows (a plan from the tick's later snapshot with
    an acceleration stepping at each tick: 0.66-0.75 m median, 1.39-1.82 m p95 in three runs of
    bench/ardupilot.py, docs/SITL.md)."""
    d = np.array(flight_a["m"].follow_errors_m())
    assert len(d) >= MONITOR_S * 0.9
    assert np.median(d) <= FOLLOW_MEDIAN_M and np.percentile(d, 95) <= FOLLOW_P95_M, \
        (np.median(d), np.percentile(d, 95))


def test_each_plan_starts_at_its_scan_with_the_last_plans_acceleration(flight_a):
    """What the copter follows (issue 29): each plan from its scan, with the last plan's acceleration
    (the mock's version: tests/app/test_follow_plan.py)."""
    assert_plans_start_at_their_scans_and_join(flight_a["m"].run_log(), MONITOR_S - 5, MONITOR_S - 10)


def test_the_copter_stays_in_the_area_and_out_of_the_obstacles(flight_a):
    c = flight_a["m"].containment()
    assert c["samples"] > 10 * MONITOR_S, c
    assert c["outside_area"] == 0 and c["in_obstacle"] == 0, c


def test_estimates_are_within_the_stated_error(flight_a):
    e = flight_a["m"].estimate_errors()
    assert e["scored_ticks"] >= MONITOR_S
    assert max(e["rmse_m"]) <= RMSE_MAX_M, e["rmse_m"]


def test_ground_station_on_another_port_sees_estimates_params_and_limits(flight_a):
    st = _ok(flight_a["status"], "onboard app: monitoring")
    # the flight policy plans at the autopilot's stock limits, capped at what the airframe flies
    assert "speed     planned at 9 m/s, 2.5 m/s^2, 5 m/s^3 (autopilot 10 m/s, 2.5 m/s^2, 5 m/s^3)" in st.stdout, st.stdout
    assert "WARNING" not in st.stdout, st.stdout
    assert flight_a["gcs_saw_estimates"] == [0, 1, 2, 3]
    _ok(flight_a["param_get"], "PMON_CLUTTER = 1")
    _ok(flight_a["param_set"], "PMON_CLUTTER = 1.5")
    assert flight_a["param_bad"].rc == 1 and "out of range" in flight_a["param_bad"].stderr
    _ok(flight_a["param_after"], "PMON_CLUTTER = 1.5")


def test_live_view_in_a_browser_draws_every_estimate_where_it_is(flight_a):
    """issue 25: the page in a real browser during this flight, through ArduPilot's routing."""
    r = flight_a["view"]
    if isinstance(r, str):
        pytest.skip(r)
    if isinstance(r, AssertionError):
        raise r
    assert r.frames >= 8 and r.max_marker_err_px <= 1.0, r


def test_pilot_takeover_stops_setpoints_within_a_tick_and_resume_flies_again(flight_a):
    m = flight_a["m"]
    for key in ("LOITER", "hold"):
        _ok(flight_a[key], "accepted by the autopilot")
        assert flight_a[f"{key}_app"] == "pilot override"
        _ok(flight_a[f"{key}_resume"], "app monitoring")
    reactions = m.takeover_reactions()
    assert len(reactions) == 2 and max(reactions) <= TICK_S, reactions
    assert flight_a["end_state"] == "monitoring"
    # after each resume the autopilot holds the app's new setpoints again (in the account above)


def test_pmon_locate_finds_both_emitters_from_this_flights_dataflash_log(flight_a, tmp_path, capsys):
    """``pmon locate`` on ArduCopter's own DataFlash log of this flight (tests/support/locate_check.py):
    its poses are the positions the firmware reported, when it reported them, with its GPS's UTC;
    a KrakenSDR recording drawn along them locates two emitters 250-600 m away within 15 m, the
    ellipses consistent (NEES)."""
    from tests.support.locate_check import locate_from_flight
    locate_from_flight(flight_a["m"], "bin", tmp_path, capsys, airborne_s=MONITOR_S)


# --------------------------------------------------------------------------- flight B
@pytest.fixture(scope="module")
def flight_b(tmp_path_factory):
    out = tmp_path_factory.mktemp("ardupilot_b")
    rec: dict = {"out": out}
    cfg = MissionConfig(speedup=3.0, params=RECOMMENDED_PARAMS, feed_duration_s=400, seed=7,
                        link_proxy=True)
    with Mission(cfg, out) as m:
        rec["m"] = m
        m.fast_boot()  # its boot until 35 s at 10x (and the reboot's, below)
        rec["arm"] = m.gcs("arm", "--wait", timeout=120)  # at once: the autopilot is still booting
        rec["takeoff"] = m.gcs("takeoff", "40", "--wait")
        rec["start"] = m.gcs("start")
        rec["status"] = m.gcs("status")
        m.sim_sleep(20.0)
        # the autopilot's jerk tuned down in flight (on the observer's link; ArduPilot tells every
        # link): the app plans at it from then on
        link = m.observer.link
        link.send(link.mav.param_set_encode(1, 1, b"PSC_JERK_XY", 2.0, mavlink.MAV_PARAM_TYPE_REAL32))
        rec["jerk_told"] = m.wait(lambda o: any(t.endswith(", 2 m/s^3") for t in o.app_texts()), 30, "jerk 2")
        rec["jerk_status"] = m.gcs("status")
        # the telemetry link drops for 3 s (wall) and comes back
        rec["cut_t"] = m.observer.t
        m.proxy.cut(3.0)
        rec["back"] = m.wait(lambda o: any("link back" in t for t in o.app_texts()), 30, "link back")
        rec["lost_texts"] = m.observer.app_texts()
        m.wait(lambda o: o.app_state == "fault", 5, "fault")  # its next heartbeat
        rec["state_after_cut"] = m.observer.app_state
        m.sim_sleep(3.0)
        rec["resume_t"] = m.observer.t
        rec["resume"] = m.gcs("resume")
        m.sim_sleep(10.0)
        # the autopilot is stopped and boots again (eeprom kept): a reboot as the companion sees it
        rec["restart_wall"] = time.monotonic()
        m.sitl.restart(down_s=2.0)
        rec["rebooted"] = m.wait(lambda o: o.boots >= 1 and o.t is not None, 60, "reboot")
        m.fast_boot()  # nothing below is timed in wall s before the copter can arm again
        # (the ground station's own link is down during the reboot too: the app's log says it)
        rec["back_after_reboot"] = m.wait(lambda o: m.app_log().count("link back") >= 2, 60,
                                          "link back after reboot")
        m.wait(lambda o: o.app_state == "fault", 5, "fault")
        rec["state_after_reboot"] = m.observer.app_state
        rec["launch"] = m.gcs("launch")
        rec["monitoring_again"] = m.wait(lambda o: o.app_state == "monitoring", 150, "monitoring")
        rec["again_t"] = m.observer.t
        m.sim_sleep(10.0)
        rec["app_alive"] = m.app.p.poll() is None
    yield rec


def test_arm_wait_takeoff_wait_and_start_each_succeed_once(flight_b):
    m = flight_b["m"]
    _ok(flight_b["arm"], "accepted by the autopilot", "armed")
    _ok(flight_b["takeoff"], "at 40 m after")
    _ok(flight_b["start"], "app monitoring")
    st = _ok(flight_b["status"], "onboard app: monitoring")
    # the demo's PSC_JERK_XY 20 is capped by the attitude loop at 15.3 (AC_PosControl), the plan at 5
    assert "WARNING" not in st.stdout and "planned at 9 m/s, 2.5 m/s^2, 5 m/s^3 (autopilot 20 m/s, 5 m/s^2, 15.3" \
        in st.stdout, st.stdout
    _ran_once(m)


def test_the_autopilots_jerk_set_in_flight_is_planned_with(flight_b):
    """PSC_JERK_XY set to 2 m/s^3 on the firmware while monitoring: the app says it plans at 2
    and the ground station's status shows it (the autopilot's and the plan's)."""
    m = flight_b["m"]
    assert flight_b["jerk_told"], m.observer.app_texts()
    assert "PMON: planning at 9 m/s, 2.5 m/s^2, 2 m/s^3" in m.observer.app_texts()
    st = _ok(flight_b["jerk_status"], "onboard app: monitoring")
    assert "planned at 9 m/s, 2.5 m/s^2, 2 m/s^3 (autopilot 20 m/s, 5 m/s^2, 2 m/s^3)" in st.stdout, st.stdout


def test_link_loss_stops_commanding_reconnects_and_waits_for_resume(flight_b):
    m = flight_b["m"]
    # "link lost" reaches no ground station while the link is down: the app's log has it, and
    # the ground station hears how long it lasted when it is back
    assert "autopilot link lost: setpoints stopped" in m.app_log()
    assert flight_b["back"] and any(re.fullmatch(r"PMON: link back \(lost [345] s\): send resume", t)
                                    for t in m.observer.app_texts()), m.observer.app_texts()
    assert flight_b["state_after_cut"] == "fault"
    _ok(flight_b["resume"], "app monitoring")
    assert m.proxy.connections >= 2  # the app's own TCP reconnect, through the relay
    # between the link coming back and the operator's resume, no setpoint was sent
    from onboard.app.mavlink2 import mavutil
    conn = mavutil.mavlink_connection(str(m.out / "app.tlog"), dialect="ardupilotmega")
    sent = []
    while (msg := conn.recv_match(type="SET_POSITION_TARGET_LOCAL_NED")) is not None:
        sent.append(msg.time_boot_ms / 1000.0)
    cut, resume = flight_b["cut_t"], flight_b["resume_t"]
    assert not [t for t in sent if cut + 1.5 < t < resume], "setpoints sent while in fault"
    assert any(t > resume for t in sent)


def test_autopilot_restart_is_survived_and_the_app_flies_again_only_when_told(flight_b):
    m = flight_b["m"]
    assert flight_b["rebooted"] and flight_b["back_after_reboot"], m.observer.app_texts()
    assert flight_b["state_after_reboot"] == "fault"  # resumes only when told
    _ok(flight_b["launch"], "accepted by the onboard app")
    assert flight_b["monitoring_again"], m.observer.app_texts()
    assert flight_b["app_alive"]
    log = (m.out / "app.log").read_text()
    assert "Traceback" not in log and "Exception in thread" not in log, log[-2000:]
    assert "autopilot rebooted: DF scan times start over" in log  # (no GCS link was up to hear it)
    # the autopilot holds the app's setpoints again after the reboot
    again = flight_b["again_t"]
    with m.observer.lock:
        held = [(t, x, y, z) for t, x, y, z in m.observer.targets if t is not None and t > again + 2]
    sent = [r for r in m.run_log() if r["sent"] and r["t"] > again + 2]
    assert sent and held
    got = [(t, *m.mission_ned(x, y, z)) for t, x, y, z in held]
    taken = [r for r in sent if any(TickAccount._matches(g, _expected(r)) for g in got)]
    assert len(taken) >= len(sent) - 1, (len(taken), len(sent))
    assert m.autopilot_crashes() == 0


def test_stop_keeps_the_firmware_log_it_printed(tmp_path):
    """issue 30: stop() deleted the temporary working directory with the arducopter.log that
    ``python -m sim.firmware.ardupilot`` had printed, so a failed flight lost it."""
    from sim.firmware.ardupilot import ArduPilotSitl, find_binary

    sitl = ArduPilotSitl(find_binary(), (35.145, 33.411, 160.0, 0.0), speedup=1).start()
    log = sitl.workdir / "arducopter.log"
    sitl.stop()
    try:
        assert log.is_file() and log.stat().st_size > 0, log
        assert not (sitl.workdir / "eeprom.bin").exists()  # the rest of the scratch directory goes
    finally:
        import shutil
        shutil.rmtree(sitl.workdir, ignore_errors=True)


def _wrapper(tmp_path, body: str):
    w = tmp_path / "arducopter"
    w.write_text("#!/bin/sh\n" + body)
    w.chmod(0o755)
    return w


def test_a_crash_at_boot_is_reported_and_booted_once_more(tmp_path, capfd):
    """A CI run lost flight A to 'arducopter exited with -6 at boot' with nothing to say why: the
    firmware crashed (SIGABRT) before its ports opened. One crash at boot is written to the log,
    said on stderr and booted again; the second boot is the real firmware, which must come up."""
    from sim.firmware.ardupilot import ArduPilotSitl, find_binary

    marker = tmp_path / "crashed-once"
    w = _wrapper(tmp_path, f'if [ ! -e {marker} ]; then touch {marker}; echo "PANIC: test crash"; '
                 f'kill -ABRT $$; fi\nexec {find_binary()} "$@"\n')
    sitl = ArduPilotSitl(w, (35.145, 33.411, 160.0, 0.0), speedup=1, workdir=tmp_path / "w").start()
    try:
        assert sitl.running and sitl.boots == 1 and sitl.boot_crashes == 1
        log = (tmp_path / "w" / "arducopter.log").read_text()
        assert "PANIC: test crash" in log and "crashed at boot (signal 6)" in log
        assert "crashed at boot (signal 6)" in capfd.readouterr().err
    finally:
        sitl.stop()


@pytest.mark.parametrize("script, error, crashes", [
    # a firmware that keeps crashing is booted once more, then raises with its last words
    ('echo "ERROR: Floating point exception - aborting"; kill -ABRT $$\n',
     r"exited with -6 at boot \(ERROR: Floating point exception", 1),
    # an exit with a status (bad arguments, a port taken) is not booted again
    ('echo "bind failed on port 5960 - Address already in use"; exit 1\n',
     r"exited with 1 at boot \(bind failed on port 5960", 0),
], ids=["crashes-twice", "exit-status"])
def test_a_boot_that_fails_raises_with_the_firmwares_last_words(tmp_path, script, error, crashes):
    from sim.firmware.ardupilot import ArduPilotSitl, SitlError

    sitl = ArduPilotSitl(_wrapper(tmp_path, script), (35.145, 33.411, 160.0, 0.0), speedup=1, workdir=tmp_path / "w")
    with pytest.raises(SitlError, match=error):
        sitl.start()
    sitl.stop()
    assert sitl.boot_crashes == crashes and sitl.boots == 0
