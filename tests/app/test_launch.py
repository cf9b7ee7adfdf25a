"""The launch sequence (onboard/app/autopilot/launch.py) on plain values: what it asks the autopilot for,
when, and what it says, through a boot like ArduCopter's (tests/firmware/test_ardupilot.py flies it on the
real firmware)."""
from __future__ import annotations

from dataclasses import replace

from onboard.app.autopilot import launch as L

ALTITUDE_M = 40.0
GROUND = L.VehicleView(position=True, in_launch_mode=False, armed=False, up_m=0.1, home_up_m=0.0, prearm_ok=True)


def actions(acts):
    return [a[0] if isinstance(a, tuple) else f"say:{a.text}" for a in acts]


def run(seq, view, t):
    seq, acts = L.step(seq, view, t)
    return seq, actions(acts), acts


def test_waits_for_the_position_and_the_prearm_checks_saying_so_once():
    seq = L.Launch(ALTITUDE_M)
    seq, a, raw = run(seq, replace(GROUND, position=False), 0.0)
    assert a == ["say:launch: waiting for the autopilot's position"] and raw[0].once
    v = replace(GROUND, prearm_ok=False, prearm_text="PreArm: Need Position Estimate")
    seq, a, raw = run(seq, v, 1.0)
    assert a == ["say:launch: waiting for the autopilot's pre-arm checks (PreArm: Need Position Estimate)"]
    assert seq.phase == "ready"  # nothing sent to an autopilot that is not ready
    seq, a, _ = run(seq, replace(GROUND, prearm_ok=True), 2.0)
    assert a == ["mode"] and seq.phase == "mode"


def test_arming_is_retried_while_refused_and_the_reason_said_once_per_reason():
    seq = L.Launch(ALTITUDE_M, phase="arm", mode_seen=True)
    g = replace(GROUND, in_launch_mode=True)
    seq, a, _ = run(seq, g, 10.0)
    assert a == ["arm"]
    seq, a, _ = run(seq, replace(g, prearm_text="Arm: Need Position Estimate"), 11.0)
    assert a == []  # not before ARM_RETRY_S
    seq, a, raw = run(seq, replace(g, prearm_text="Arm: Need Position Estimate"), 12.0)
    assert a == ["say:launch: arming refused: Arm: Need Position Estimate", "arm"] and raw[0].once
    # ArduCopter's pre-arm bit can pass for a second and fail again (its 4.4 SITL, at ~24 s):
    # then no ARM until it passes again
    seq, a, _ = run(seq, replace(g, prearm_ok=False), 12.5)
    assert a == [] and seq.phase == "arm"
    seq, a, _ = run(seq, replace(g, armed=True), 13.0)  # at once, not at the next retry
    assert a == ["say:launch: armed", "takeoff"] and seq.phase == "takeoff"


def test_take_off_above_home_then_climb_then_start_when_the_app_can():
    seq = L.Launch(ALTITUDE_M, phase="takeoff", mode_seen=True)
    v = replace(GROUND, in_launch_mode=True, armed=True, home_up_m=2.0, up_m=2.1)
    seq, _, raw = run(seq, v, 20.0)
    assert raw == [("takeoff", ALTITUDE_M - 2.0)]  # the altitude above home that puts it at h
    seq, a, _ = run(seq, replace(v, climbing=True), 21.0)  # the autopilot reports TAKEOFF
    assert seq.phase == "climb" and a == [f"say:launch: climbing to {ALTITUDE_M:g} m"]
    seq, a, _ = run(seq, replace(v, up_m=20.0), 25.0)
    assert seq.phase == "climb" and a == []
    at = replace(v, up_m=ALTITUDE_M - 0.5, start_blocker="no DF data in the last 3 s")
    seq, a, _ = run(seq, at, 30.0)
    assert seq.phase == "start" and a == ["say:launch: at altitude, waiting: no DF data in the last 3 s"]
    seq, a, _ = run(seq, replace(at, can_start=True, start_blocker=None), 31.0)
    assert seq is None and a == ["start"]


def test_a_pilot_or_a_disarm_aborts_it_and_a_take_off_never_taken_gives_up():
    g = replace(GROUND, in_launch_mode=True, armed=True)
    seq, a, _ = run(L.Launch(ALTITUDE_M, phase="climb", mode_seen=True),
                    replace(g, in_launch_mode=False, mode_name="LOITER"), 5.0)
    assert seq is None and a == ["say:launch aborted: the vehicle left GUIDED (now LOITER)"]
    seq, a, _ = run(L.Launch(ALTITUDE_M, phase="takeoff", mode_seen=True), replace(g, armed=False), 5.0)
    assert seq is None and a == ["say:launch aborted: the vehicle disarmed"]
    seq = L.Launch(ALTITUDE_M, phase="takeoff", mode_seen=True)
    for k in range(L.TAKEOFF_TRIES):
        t = 10.0 + k * L.TAKEOFF_RETRY_S
        seq, a, _ = run(seq, replace(g, home_up_m=0.0, up_m=0.0), t)
        assert a == ["takeoff"]
        seq, a, _ = run(seq, replace(g, home_up_m=0.0, up_m=0.0), t + 3.3)  # spooling: no repeat
        assert a == []
    seq, a, _ = run(seq, replace(g, home_up_m=0.0, up_m=0.0), 10.0 + L.TAKEOFF_TRIES * L.TAKEOFF_RETRY_S)
    assert seq is None and a[0].startswith("say:launch failed")
    # before the sequence took the vehicle to GUIDED, another mode is not a pilot
    seq, a, _ = run(L.Launch(ALTITUDE_M), replace(GROUND, in_launch_mode=False), 0.0)
    assert seq is not None


def test_px4s_take_off_is_its_own_mode_and_the_start_waits_for_its_switch_back_to_hold():
    """PX4 (v1.16 SITL): armed in Hold, the take-off flown in AUTO.TAKEOFF (the autopilot's own
    mode, not a pilot's), which PX4 ends by switching to Hold: only then is OFFBOARD asked for."""
    hold = replace(GROUND, in_launch_mode=True, armed=True, home_up_m=0.0, up_m=0.1, mode_name="AUTO.LOITER")
    taking_off = replace(hold, in_launch_mode=False, in_own_mode=True, mode_name="AUTO.TAKEOFF", climbing=True)
    seq = L.Launch(ALTITUDE_M, phase="takeoff", mode_seen=True, launch_mode="AUTO.LOITER")
    seq, a, _ = run(seq, hold, 10.0)
    assert a == ["takeoff"]
    seq, a, _ = run(seq, replace(taking_off, up_m=5.0), 11.0)
    assert seq.phase == "climb" and a == [f"say:launch: climbing to {ALTITUDE_M:g} m"]
    at = replace(taking_off, up_m=ALTITUDE_M - 0.6, can_start=True)
    seq, a, _ = run(seq, at, 35.0)
    assert seq.phase == "start" and a == ["say:launch: at altitude, waiting for the autopilot to end its "
                                          "take-off (AUTO.TAKEOFF)"]
    seq, a, _ = run(seq, replace(hold, up_m=ALTITUDE_M - 0.6, can_start=True), 36.0)
    assert seq is None and a == ["start"]
    # a pilot's mode that is neither the launch's nor the autopilot's own take-off aborts it
    seq, a, _ = run(L.Launch(ALTITUDE_M, phase="climb", mode_seen=True, launch_mode="AUTO.LOITER"),
                    replace(taking_off, in_own_mode=False, mode_name="POSCTL"), 20.0)
    assert seq is None and a == ["say:launch aborted: the vehicle left AUTO.LOITER (now POSCTL)"]
