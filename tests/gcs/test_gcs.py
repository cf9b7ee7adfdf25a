"""The ground-station CLI's error paths (message and exit code each), retries on a lossy link
that never execute a command twice, the real console script, and the wire contract it shares
with the onboard app."""
from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from sim.stack.sitl_stack import SitlStack

from groundstation import protocol as P
from groundstation.cli import main
from tests.support.ack_dropper import AckDropper
from tests.support.mavlink_gcs import QUICK_BOOT_S

REPO = Path(__file__).resolve().parents[2]


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(capsys, *argv):
    capsys.readouterr()
    rc = main(list(argv))
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


# ----------------------------------------------------------------------------- no vehicle
@pytest.mark.timeout(20)
def test_unreachable_vehicle_times_out_with_exit_3(capsys):
    port = free_udp_port()
    rc, out, err = run(capsys, "--connect", f"udpin:127.0.0.1:{port}", "--timeout", "1", "status")
    assert rc == 3 and out == ""
    assert one_line(err) == f"pmon gcs: no vehicle heard on udpin:127.0.0.1:{port} within 1 s (no MAVLink at all)"
    rc, out, err = run(capsys, "--connect", f"udpin:127.0.0.1:{port}", "--timeout", "1", "--json", "arm")
    assert rc == 3 and json.loads(out) == {"ok": False, "error": one_line(err)[10:], "exit_code": 3}
    with socket.socket() as s:  # a TCP port nobody listens on
        s.bind(("127.0.0.1", 0))
        tcp = s.getsockname()[1]
    rc, out, err = run(capsys, "--connect", f"tcp:127.0.0.1:{tcp}", "--timeout", "1", "status")
    assert rc == 3 and out == "" and "cannot open" in one_line(err) and "refused" in err


def test_usage_errors_exit_2(capsys):
    for argv, why in ((["takeoff", "-5"], "ALT must be in (0, 1000]"),
                      (["params", "set", "PMON_PD", "abc"], "is not a number"),
                      (["--timeout", "0", "status"], "--timeout must be > 0"),
                      (["watch", "--count", "0"], "--count must be >= 1")):
        rc, out, err = run(capsys, "--connect", "udpin:127.0.0.1:1", *argv)
        assert rc == 2 and why in one_line(err), (argv, err)
    rc, _, err = run(capsys, "fly-to-the-moon")
    assert rc == 2 and "invalid choice" in err


def test_plot_of_a_missing_or_foreign_file_exits_1(capsys, tmp_path):
    rc, _, err = run(capsys, "plot", str(tmp_path / "nope.tlog"))
    assert rc == 1 and "no such file" in one_line(err)
    bad = tmp_path / "x.jsonl"
    bad.write_text('{"hello": 1}\n')
    rc, _, err = run(capsys, "plot", str(bad))
    assert rc == 1 and "not a pmon run log" in one_line(err)


def test_the_ground_station_reads_the_apps_own_contract_without_loading_the_app():
    """One contract: the ground station imports onboard/app/contract.py (no copy to drift), and
    that import does not pull in the app or the core (a GCS command stays quick to start)."""
    code = ("import sys, groundstation.protocol; "
            "print(sorted(m for m in sys.modules if m.startswith(('onboard.core', 'onboard.app.app', 'scipy', 'sim'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    assert out.stdout.strip() == "[]", out.stdout
    from onboard.app.contract import REASON_TEXT, Action, State

    assert P.ACTIONS["launch"] == Action.LAUNCH and P.APP_STATES[State.PILOT_OVERRIDE] == "pilot override"
    assert P.REASONS[5] == REASON_TEXT[5] == "no autopilot heartbeat"
    assert (P.GUIDED, P.LOITER, P.RTL, P.LAND, P.BRAKE) == (4, 5, 6, 9, 17)  # ArduCopter's numbers


def test_what_the_app_publishes_is_what_the_ground_station_decodes():
    """PMON_STAT and PMON_TGT encoded by the app's publisher and decoded by the ground station:
    every field lands where the contract's field list says (a field moved on one side only
    fails here)."""
    import math

    from onboard.app.contract import STAT_FIELDS, TGT_FIELDS, State
    from onboard.app.mavlink_connection import mavlink
    from onboard.app.gcs.publisher import Publisher
    from onboard.app.autopilot.vehicle import Vehicle

    class Wire:  # a link that keeps what it sends
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)

        def __init__(self):
            self.sent = []

        def send(self, msg):
            self.sent.append(self.mav.decode(bytearray(msg.pack(self.mav))))
            return True

    class Clock:
        def now(self):
            return 12.0

    stat = {name: float(i + 1) for i, name in enumerate(STAT_FIELDS)}
    stat.update(state=float(State.PAUSED), warnings=3.0, launch_phase=2.0, next_u_m=math.nan)
    wire = Wire()
    pub = Publisher(wire, Clock(), Vehicle(sysid=1), lambda: State.PAUSED, lambda: stat)
    pub.publish_stat()
    tgt = {name: float(10 + i) for i, name in enumerate(TGT_FIELDS)}
    tgt.update(since_scan_s=-1.0, degenerate=1.0)
    pub.publish_target(2, tgt, 12.0)
    s = P.AppStatus.from_msg(wire.sent[0])
    assert (s.state, s.tick_rate_hz, s.last_tick_time_s, s.tick_ms) == ("paused", 2.0, 3.0, 4.0)
    assert s.next_enu is None  # one coordinate not finite: no setpoint
    assert (s.datagrams_accepted, s.datagrams_rejected, s.ticks, s.ticks_skipped, s.latency_ms) == (8, 9, 10, 11, 12.0)
    assert s.uav_enu == (15.0, 16.0, 17.0) and (s.ticks_late, s.setpoints_refused) == (19, 20)
    assert s.launch_phase == "arming" and len(s.warnings) == 2
    assert s.limits == "planned at 23 m/s, 25 m/s^2, 31 m/s^3 (autopilot 22 m/s, 24 m/s^2, 30 m/s^3)"
    t = P.TargetEstimate.from_msg(wire.sent[1])
    assert (t.index, t.x, t.y, t.vx, t.vy, t.sigma_x, t.sigma_y, t.cov_xy) == (2, 10, 11, 13, 14, 16, 17, 19)
    assert t.since_detection_s is None and t.degenerate and t.tick_time_s == 23
    # what the target most likely does: a code, its probability, its goal region's index
    tgt.update(mode=1.0, mode_p=0.93, goal_index=1.0)
    pub.publish_target(0, tgt, 12.0)
    t = P.TargetEstimate.from_msg(wire.sent[2])
    assert (t.mode, t.goal_index) == ("goal", 1) and abs(t.mode_p - 0.93) < 1e-6
    assert t.mode_text(("G", "W")) == "heading for W 0.93" and t.mode_text() == "heading for goal 2 0.93"
    tgt.update(mode=2.0, goal_index=-1.0)
    pub.publish_target(0, tgt, 12.0)
    assert P.TargetEstimate.from_msg(wire.sent[3]).mode_text() == "stationary 0.93"
    for hostile in (float("nan"), 99.0, -3.0):  # a mode code no app sends: unknown, no crash
        tgt.update(mode=hostile, goal_index=hostile)
        pub.publish_target(0, tgt, 12.0)
        t = P.TargetEstimate.from_msg(wire.sent[-1])
        assert (t.mode, t.goal_index, t.mode_text()) == ("unknown", -1, "-")


def test_status_says_the_planned_jerk_and_the_autopilots_where_it_has_one():
    """PMON_STAT's jerk fields in words: a plan whose acceleration steps (0) says so; PX4 (no
    jerk shaped: NaN) shows none of its own; an app older than the fields (their 0 padding)
    shows no autopilot jerk."""
    import math

    from onboard.app.contract import STAT_FIELDS
    from onboard.app.mavlink_connection import mavlink

    def limits(**values):
        d = dict.fromkeys(STAT_FIELDS, 0.0)
        d.update(speed_limit_mps=12.0, speed_plan_mps=9.0, accel_limit_mps2=3.0, accel_plan_mps2=2.5, **values)
        data = [d[f] for f in STAT_FIELDS] + [0.0] * (58 - len(STAT_FIELDS))
        return P.AppStatus.from_msg(mavlink.MAVLink_debug_float_array_message(0, b"PMON_STAT", 0, data)).limits

    assert limits(jerk_limit_mps3=math.nan, jerk_plan_mps3=5.0) == "planned at 9 m/s, 2.5 m/s^2, 5 m/s^3 (autopilot 12 m/s, 3 m/s^2)"
    assert limits(jerk_limit_mps3=2.0, jerk_plan_mps3=0.0) == \
        "planned at 9 m/s, 2.5 m/s^2, acceleration steps (autopilot 12 m/s, 3 m/s^2, 2 m/s^3)"
    assert limits(jerk_limit_mps3=0.0, jerk_plan_mps3=math.nan) == "planned at 9 m/s, 2.5 m/s^2 (autopilot 12 m/s, 3 m/s^2)"


def test_the_advised_waypoint_is_read_from_pmon_stat_and_none_when_nan():
    """PMON_STAT 33-35: the advised waypoint; NaN (no plan), or one field not finite: none."""
    import math

    from onboard.app.contract import ADVICE_FIELDS, STAT_FIELDS
    from onboard.app.mavlink_connection import mavlink

    def advice(*values):
        d = dict.fromkeys(STAT_FIELDS, 0.0)
        d.update(zip(ADVICE_FIELDS, values), state=5.0, next_e_m=math.nan, next_n_m=math.nan, next_u_m=math.nan)
        data = [d[f] for f in STAT_FIELDS] + [0.0] * (58 - len(STAT_FIELDS))
        st = P.AppStatus.from_msg(mavlink.MAVLink_debug_float_array_message(0, b"PMON_STAT", 0, data))
        assert st.state == "advisory" and st.next_enu is None
        return st.advice_enu

    assert advice(120.5, -3.0, 40.0) == (120.5, -3.0, 40.0)
    assert advice(math.nan, math.nan, math.nan) is None
    assert advice(120.5, math.inf, 40.0) is None


# ----------------------------------------------------------------------------- against a vehicle
@pytest.fixture(scope="module")
def stack():
    with SitlStack(speedup=4.0, gcs_udpin=True, ready_s=QUICK_BOOT_S) as st:  # no DF feed: start lacks sensor data
        assert st.wait_ready()
        yield st


@pytest.mark.sitl
@pytest.mark.timeout(60)
def test_refusals_and_parameter_errors_say_why(stack, capsys):
    url = ["--connect", stack.gcs_url, "--timeout", "3"]
    rc, out, err = run(capsys, *url, "start")
    assert rc == 1 and one_line(err) == "pmon gcs: start refused by the onboard app (DENIED): vehicle not armed"
    rc, out, err = run(capsys, *url, "--json", "pause")
    assert rc == 1 and "pause refused by the onboard app (DENIED): not possible in this state" in err
    assert json.loads(out)["exit_code"] == 1
    rc, out, err = run(capsys, *url, "takeoff", "30")  # disarmed: the autopilot says no
    assert rc == 1 and one_line(err).startswith("pmon gcs: takeoff to 30 m refused by the autopilot (FAILED)")
    assert "disarmed" in err
    rc, out, err = run(capsys, *url, "params", "get", "PMON_WARP")
    assert rc == 1 and one_line(err) == "pmon gcs: unknown parameter PMON_WARP (params list shows them)"
    rc, out, err = run(capsys, *url, "params", "set", "PMON_WARP", "9")
    assert rc == 1 and "unknown parameter PMON_WARP" in err
    rc, out, err = run(capsys, *url, "params", "set", "PMON_PD", "1.5")
    assert rc == 1 and one_line(err) == "pmon gcs: params set PMON_PD refused: PMON_PD=1.5 out of range [0.01, 1]"
    assert stack.app.params["PMON_PD"] == pytest.approx(0.95)
    rc, out, err = run(capsys, *url, "params", "set", "PMON_NR", "3.4")  # an integer parameter
    assert rc == 0 and "PMON_NR = 3 (rounded from 3.4)" in out and stack.app.params["PMON_NR"] == 3
    rc, out, _ = run(capsys, *url, "params", "list")
    from onboard.app.params import SPECS
    assert rc == 0 and len(out.splitlines()) == len(SPECS) and "PMON_PARTICLES" in out
    rc, out, err = run(capsys, "--connect", stack.gcs_url, "--sysid", "42", "--timeout", "1", "status")
    assert rc == 3 and one_line(err).startswith(f"pmon gcs: vehicle 42 not heard on {stack.gcs_url} within 1 s")


@pytest.mark.sitl
@pytest.mark.timeout(60)
def test_lost_acknowledgements_are_retried_and_nothing_runs_twice(stack, capsys):
    ap = stack.ap
    seen = {"takeoff": 0}
    COMMAND_ACK = 77

    def drop(msgid, comp, payload):  # the first acknowledgement of a take-off
        if msgid == COMMAND_ACK and comp == 1 and int.from_bytes(payload[:2], "little") == 22 \
                and seen["takeoff"] == 0:
            seen["takeoff"] += 1
            return True
        return False
    arm_sent = []

    def drop_up(msgid, payload):  # the first arm command is lost on the way up
        if msgid == 76 and len(payload) >= 30 and int.from_bytes(payload[28:30], "little") == 400:
            arm_sent.append(payload[32] if len(payload) > 32 else 0)  # confirmation (0 is truncated)
            return len(arm_sent) == 1
        return False
    relay = AckDropper(stack.udpin_port, drop, drop_up)
    try:
        url = ["--connect", f"udpout:127.0.0.1:{relay.port}", "--timeout", "5"]
        rc, out, err = run(capsys, "--json", *url, "arm")
        r = json.loads(out)
        assert rc == 0 and r["attempts"] == 2 and r["result"] == "ACCEPTED", (r, err)
        assert arm_sent == [0, 1]  # resent once, confirmation incremented
        rc, out, err = run(capsys, *url, "--json", "takeoff", "20")
        r = json.loads(out)
        # the ACK is lost; ArduCopter spools its motors 3.3 s before it climbs, so the GCS sees
        # no climb yet and sends the take-off again: accepted, and it changes nothing (one
        # take-off to 20 m; measured on ArduCopter 4.4 SITL, and the mock does the same)
        assert rc == 0 and r["result"] in ("ACCEPTED", "OBSERVED") and r["attempts"] <= 3, (r, err)
        assert relay.dropped == ["up", COMMAND_ACK]
        assert ap.wait_until(lambda s: s.alt_rel > 19.0, 20)
        assert ap.state().alt_rel < 21.0 and ap.counters().get("defects", 0) == 0
        # parameters: a set whose answer is lost is simply sent again (setting is idempotent)
        rc, out, err = run(capsys, *url, "params", "set", "PMON_CLUTTER", "2")
        assert rc == 0 and stack.app.params["PMON_CLUTTER"] == 2
        rc, out, err = run(capsys, *url, "land")
        assert rc == 0 and ap.state().mode_name == "LAND"
    finally:
        relay.close()


@pytest.mark.sitl
@pytest.mark.timeout(60)
def test_the_console_scripts_and_the_environment_variable(stack):
    exe = Path(sys.executable).parent
    pmon_gcs = shutil.which("pmon-gcs", path=str(exe)) or shutil.which("pmon-gcs")
    pmon = shutil.which("pmon", path=str(exe)) or shutil.which("pmon")
    assert pmon is not None
    env = dict(os.environ, PMON_GCS_CONNECT=stack.gcs_url)
    argv = [pmon_gcs] if pmon_gcs else [pmon, "gcs"]
    p = subprocess.run(argv + ["--json", "status"], env=env, capture_output=True, text=True, timeout=30, cwd=REPO)
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    assert s["ok"] and s["vehicle"]["sysid"] == 1 and s["app"]["state"] in P.APP_STATES
    p = subprocess.run([pmon, "gcs", "--timeout", "2", "params", "get", "PMON_HORIZON"], env=env,
                       capture_output=True, text=True, timeout=30, cwd=REPO)
    assert p.returncode == 0 and p.stdout.strip() == "PMON_HORIZON = 50", p.stderr
    p = subprocess.run([pmon, "gcs", "--connect", f"udpin:127.0.0.1:{free_udp_port()}", "--timeout", "1",
                        "start"], capture_output=True, text=True, timeout=30, cwd=REPO)
    assert p.returncode == 3 and p.stdout == "" and len(p.stderr.strip().splitlines()) == 1


@pytest.mark.sitl
@pytest.mark.timeout(60)
def test_arm_right_after_boot_is_refused_with_the_reason_and_arm_wait_arms_when_ready(capsys):
    """As on ArduCopter (its SITL: tests/firmware/test_ardupilot.py): the mock boots with no position and
    refuses to arm until its EKF is ready; arm says why, arm --wait waits it out by itself."""
    with SitlStack(speedup=4.0, ready_s=8.0) as st:
        url = ["--connect", st.gcs_url]
        assert st.ap.wait_until(lambda s: st.app.vehicle.sysid is not None, 10)
        rc, _, err = run(capsys, *url, "--timeout", "3", "arm")
        assert rc == 1 and "Arm: Need Position Estimate" in one_line(err), err
        assert st.ap.sim_time < 8.0
        rc, out, err = run(capsys, *url, "--timeout", "20", "arm", "--wait")
        assert rc == 0 and "armed (ready after" in out, (out, err)
        assert st.ap.state().armed and st.ap.sim_time >= 8.0
        assert st.ap.counters().get("defects", 0) == 0
