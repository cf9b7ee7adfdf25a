"""sim.mock.multicopter and sim.mock.guided against ArduPilot's own SITL (ArduCopter 4.4.0-dev, the shared binary).

The reference is tests/data/sitl_response.json.gz: what ``python -m bench.sitl_response --save
tests/data/sitl_response.json.gz`` recorded on the real SITL, at ArduCopter's stock limits and
the demo's: a velocity command far above the airframe's top speed, 20 m and 100 m position
steps, a 10 Hz position + velocity ramp, and planner-like routes at 90 % and 70 % of the top speed
sent one setpoint a second four ways (position only; position + the velocity at that point;
a ramp reaching the next point; the plan's position, velocity and acceleration). The model is
given the same setpoints at the same firmware times (sim.firmware.response_model.replay, 400 Hz) and
must fly what the SITL flew.

The demo's 90 % routes are left out of the bounds: they ask for 3 m/s^2 of turn at 9 m/s, which
the SITL airframe's lean (30 deg) cannot give on top of its drag; the SITL then falls behind by up
to 19 m, unevenly from run to run, and the model by less (see test_beyond_the_envelope...).
"""
import math
from pathlib import Path

import numpy as np
import pytest

from sim.firmware.response_cases import TICK_S, distance_at_ticks, planner_route, route_setpoint
from sim.firmware.response_flight import MASK_POS, MASK_PVA
from sim.firmware.response_model import in_envelope, limits_for, load, replay, rms_error
from sim.mock.copter import Copter, GuidedTarget, Mode
from sim.mock.control_math import sqrt_controller
from sim.mock.copter_params import Params
from sim.mock.guided import GuidedSetpoint, fly, fly_timeline
from sim.mock.multicopter import (
    Setpoint,
    VehicleLimits,
    VehicleState,
    attitude,
    fall,
    step,
    stopping_point,
)

DATA = Path(__file__).parents[1] / "data" / "sitl_response.json.gz"
DT = 0.02  # 50 Hz, as the mock autopilot steps the model
HOVER = VehicleState(pos=(0.0, 0.0, -10.0))
# RMS position error allowed over a whole recorded trace (m). The model's, at the fitted
# airframe (python -m bench.sitl_response --replay tests/data/sitl_response.json.gz): 0.14-0.61 m,
# and 1.47-1.52 m on the routes sent as the next point with its velocity (the form the SITL flies
# least repeatably: its p95 next-tick distance on the stock 90 % route was 29, 9 and 9 m in three
# runs of the bench). The kinematic model this one replaced: 3.3 m on the stock top-speed trace,
# 15 m (100 m step) and 92 m (top speed) at the demo's limits, where it flew 20 m/s.
RMS_MAX_M = 1.0
RMS_MAX_POSVEL_NEXT_M = 2.0


@pytest.fixture(scope="module")
def sitl():
    return load(DATA)


def _traces(sitl, inside=True):
    return [(lab, tr) for lab in sitl for tr in sitl[lab]["traces"]
            if in_envelope(lab, tr["name"]) == inside]


def _ids():
    data = load(DATA)
    return [f"{lab}:{tr['name']}" for lab in data for tr in data[lab]["traces"] if in_envelope(lab, tr["name"])]


@pytest.mark.timeout(60)
@pytest.mark.parametrize("case", _ids())
def test_model_flies_each_recorded_sitl_trace(sitl, case):
    lab, name = case.split(":")
    tr = next(t for t in sitl[lab]["traces"] if t["name"] == name)
    bound = RMS_MAX_POSVEL_NEXT_M if name.endswith("posvel_next") else RMS_MAX_M
    assert rms_error(tr, limits_for(sitl[lab]["params"])) < bound


@pytest.mark.timeout(60)
def test_distance_at_the_next_tick_as_the_sitl(sitl):
    """The figure the app is judged by: how far from the plan's point the copter is when the next
    1-s setpoint is due. Position-only setpoints leave it 9-27 m short (median: it brakes to each
    point); the plan's position, velocity and acceleration keep it 0.5-0.7 m away (p95 <= 1.7 m)."""
    for lab, tr in _traces(sitl):
        if not tr["name"].startswith("route"):
            continue
        real = distance_at_ticks(tr)
        model = distance_at_ticks({**tr, "pos": replay(tr, limits_for(sitl[lab]["params"])).tolist()})
        assert abs(np.median(model) - np.median(real)) < 0.4 + 0.05 * np.median(real), (lab, tr["name"])
        # p95 within 1 m: the SITL's own spread (stock 90 % route, plan's state: p95 0.89 m in one
        # run, 1.73 m in the next, a 2.4 m transient in one turn)
        assert abs(np.percentile(model, 95) - np.percentile(real, 95)) < 1.0 + 0.1 * np.percentile(real, 95)
        if tr["name"].endswith("_pos"):
            assert np.median(real) > 8.0
        if tr["name"].endswith("_pva"):
            assert np.median(real) < 1.0 and np.percentile(real, 95) < 2.0


@pytest.mark.timeout(60)
def test_top_speed_is_the_airframes_not_wpnav_speed(sitl):
    """At the demo's WPNAV_SPEED 20 m/s the SITL copter still flies at most 10.1 m/s: its drag at
    the 30 deg lean limit. The model's plateau is the same."""
    for lab in sitl:
        tr = next(t for t in sitl[lab]["traces"] if t["name"] == "top")
        t = np.asarray(tr["t"])
        model = replay(tr, limits_for(sitl[lab]["params"]))
        t_stop = tr["sends"][-1][0]
        hold = (t > t_stop - 3.0) & (t <= t_stop)
        real_v = np.median(np.linalg.norm(np.asarray(tr["vel"])[hold], axis=1))
        model_v = np.median(np.linalg.norm(np.diff(model, axis=0)[hold[1:]] / np.diff(t)[hold[1:], None], axis=1))
        assert real_v == pytest.approx(10.08, abs=0.1)
        assert model_v == pytest.approx(real_v, abs=0.15)


@pytest.mark.timeout(60)
def test_beyond_the_envelope_the_model_falls_behind_too_but_less(sitl):
    """The demo's 90 % route, sent as the plan's state: both fall behind in the turns; the model
    by less (median 1.9 against 3.5 m, p95 6.8 against 16.0 m): an evaluation of plans beyond
    the airframe's envelope flatters them."""
    lab = "demo"
    tr = next(t for t in sitl[lab]["traces"] if t["name"] == "route90_pva")
    real = distance_at_ticks(tr)
    model = distance_at_ticks({**tr, "pos": replay(tr, limits_for(sitl[lab]["params"])).tolist()})
    assert np.percentile(real, 95) > 5.0 and np.percentile(model, 95) > 3.0
    assert np.percentile(model, 95) < np.percentile(real, 95)


@pytest.mark.timeout(60)
def test_the_mock_flies_the_recorded_setpoints_as_the_sitl(sitl):
    """The mock autopilot's GUIDED (sim.mock.autopilot.Copter at its 50 Hz) given the recorded routes'
    setpoints: the position + velocity target moves on between messages, a new sub-mode restarts
    the controller."""
    for lab, name in (("stock", "route70_pva"), ("stock", "route70_pos"), ("demo", "route70_ramp")):
        tr = next(t for t in sitl[lab]["traces"] if t["name"] == name)
        p = sitl[lab]["params"]
        c = Copter((35.0, 33.0, 100.0), Params(overrides={k: p[k] for k in (
            "WPNAV_SPEED", "WPNAV_ACCEL", "WPNAV_SPEED_UP", "PSC_JERK_XY")}), None, pos_noise=0.0)
        c.armed, c.land_complete = True, False
        c.state = VehicleState(pos=(0.0, 0.0, -20.0))
        assert c.set_mode(Mode.GUIDED)
        t = np.asarray(tr["t"]) - tr["t"][0]
        sends = [(s[0] - tr["t"][0], s) for s in tr["sends"]]
        out, i, now = [], 0, 0.0
        for ts in t:
            while now < ts - 1e-9:
                while i < len(sends) and sends[i][0] <= now + 1e-9:
                    _, (_, mask, pos, vel, acc) = sends[i]
                    pos = (pos[0], pos[1], -20.0)
                    c.set_guided(GuidedTarget("pos", pos=pos) if mask == MASK_POS else
                                 GuidedTarget("posvel", pos=pos, vel=tuple(vel), acc=tuple(acc or (0, 0, 0))))
                    i += 1
                c.tick(DT)
                now += DT
            out.append(c.state.pos[:2])
        rms = math.sqrt(np.mean(np.sum((np.array(out) - np.asarray(tr["pos"])) ** 2, axis=1)))
        assert rms < RMS_MAX_M, (lab, name, rms)


@pytest.mark.timeout(60)
def test_fly_one_tick_and_its_rate(sitl):
    """sim.mock.guided.fly, the evaluation's step: one tick from a setpoint is fly_timeline's; the
    firmware's 400 Hz and the mock's 50 Hz differ by under 0.15 m over a whole recorded route."""
    lab = "stock"
    tr = next(t for t in sitl[lab]["traces"] if t["name"] == "route70_pva")
    limits = limits_for(sitl[lab]["params"])
    fast, slow = replay(tr, limits, 400.0), replay(tr, limits, 50.0)
    assert np.max(np.linalg.norm(fast - slow, axis=1)) < 0.15

    P, V = planner_route(7.0, 2.5)
    state, first = VehicleState(pos=(0.0, 0.0, -20.0)), True
    for k in range(len(P) - 1):
        _, pos, vel, acc = route_setpoint("pva", P, V, k)
        sp = GuidedSetpoint(pos=(pos[0], pos[1], -20.0), vel=vel, acc=acc)
        nxt = fly(state, sp, TICK_S, limits, new_submode=first)
        again = fly_timeline(state if not first else VehicleState(pos=state.pos, vel=state.vel, acc=state.acc),
                             [(0.0, sp)], [TICK_S], limits, submode=None if first else "posvelaccel")[-1]
        assert nxt.pos == again.pos
        state, first = nxt, False
        assert math.dist(state.pos[:2], P[k + 1]) < 1.5  # on the plan at every tick


def test_fly_stops_after_guid_timeout_and_brakes_to_a_position_only_setpoint():
    limits = VehicleLimits()
    moving = fly(VehicleState(pos=(0.0, 0.0, -20.0)), GuidedSetpoint(pos=(0.0, 0.0, -20.0), vel=(5.0, 0.0, 0.0)),
                 2.0, limits, new_submode=True)
    assert moving.vel[0] > 3.0
    # no message for 10 s: 3 s on (GUID_TIMEOUT), then it stops at the target it had reached
    later = fly(moving, GuidedSetpoint(pos=moving.pos, vel=(5.0, 0.0, 0.0)), 12.0, limits)
    assert math.hypot(*later.vel[:2]) < 0.1
    assert later.pos[0] == pytest.approx(moving.pos[0] + 15.0, abs=1.0)
    # position only: it arrives with no speed left (the brake the issue measured)
    there = fly(VehicleState(pos=(0.0, 0.0, -20.0)), GuidedSetpoint(pos=(20.0, 0.0, -20.0)), 8.0, limits,
                new_submode=True)
    assert there.pos[0] == pytest.approx(20.0, abs=0.7) and math.hypot(*there.vel[:2]) < 0.5
    with pytest.raises(ValueError, match="rejects"):
        GuidedSetpoint(pos=(0.0, 0.0, -20.0), acc=(1.0, 0.0, 0.0))


@pytest.mark.timeout(20)
@pytest.mark.parametrize("speed", [10.0, 5.0, 2.0])
def test_speed_limits_on_position_targets(speed):
    """Towards a position-only setpoint the shaped path never asks for more than the speed limit;
    the vehicle following it overshoots by a little (the SITL: 4.08 and 4.12 m/s in two runs at
    WPNAV_SPEED 400, the model 4.11) and never flies past the airframe's top speed. The lean stays
    within its limit."""
    limits = VehicleLimits(speed_xy=speed)
    rng = np.random.default_rng(1)
    state = VehicleState()
    a_lean = 9.80665 * math.tan(limits.angle_max)
    for target in [(300.0, 0.0, -40.0), (-200.0, 150.0, -5.0), (0.0, 0.0, 0.0)]:
        for _ in range(round(60.0 / DT)):
            state = step(state, Setpoint(pos=target), DT, limits, rng)
            assert math.hypot(*state.xy.vel) <= speed + 1e-9
            assert math.hypot(state.vel[0], state.vel[1]) <= min(speed + 0.3, 10.1)
            assert -limits.speed_up - 1e-9 <= state.vel[2] <= limits.speed_down + 1e-9
            assert math.hypot(*state.xy.lean_acc) <= a_lean + 1e-9


@pytest.mark.timeout(20)
def test_velocity_commands_are_not_capped_at_wpnav_speed():
    """As ArduCopter (the SITL flew 10.08 m/s for a 12 m/s command at WPNAV_SPEED 400: python -m
    bench.sitl_response --limits stock --param WPNAV_SPEED=400 --cases top): a velocity command
    is flown up to the airframe's top speed; the climb rate is capped."""
    limits = VehicleLimits(speed_xy=4.0)
    state = HOVER
    for _ in range(round(20.0 / DT)):
        state = step(state, Setpoint(vel=(10.0, 0.0, -9.0)), DT, limits)
    assert state.vel[0] == pytest.approx(10.0, abs=0.05)
    assert state.vel[2] == pytest.approx(-limits.speed_up)


@pytest.mark.timeout(20)
def test_speed_override_and_vertical_limits():
    state = VehicleState()
    for _ in range(round(30.0 / DT)):
        state = step(state, Setpoint(pos=(500.0, 0.0, -50.0), speed_xy=3.0), DT)
        assert math.hypot(*state.xy.vel) <= 3.0 + 1e-9 and math.hypot(*state.vel[:2]) <= 3.3
        assert state.vel[2] >= -2.5 - 1e-9  # WPNAV_SPEED_UP
    for _ in range(round(10.0 / DT)):
        state = step(state, Setpoint(pos=(state.pos[0], 0.0, 0.0)), DT)
        assert state.vel[2] <= 1.5 + 1e-9  # WPNAV_SPEED_DN


@pytest.mark.timeout(20)
def test_velocity_and_brake_commands():
    state = HOVER
    for _ in range(round(10.0 / DT)):
        state = step(state, Setpoint(vel=(0.0, 4.0, 0.0)), DT)
    assert state.vel[1] == pytest.approx(4.0, abs=0.02)
    stop = stopping_point(state)
    for _ in range(round(10.0 / DT)):
        state = step(state, Setpoint(), DT)  # nothing commanded: brake
    assert math.hypot(*state.vel) < 0.05
    assert state.pos[1] == pytest.approx(stop[1], abs=1.0)


@pytest.mark.timeout(20)
def test_yaw_turns_at_limited_rate_and_attitude_follows_the_lean():
    state = HOVER
    state = step(state, Setpoint(yaw=math.pi / 2, pos=HOVER.pos), 1.0)
    assert state.yaw == pytest.approx(math.radians(90.0) * 1.0, abs=1e-6)
    state = HOVER
    for _ in range(round(1.0 / DT)):
        state = step(state, Setpoint(vel=(5.0, 0.0, 0.0)), DT)
    roll, pitch, _ = attitude(state)
    assert pitch < 0 and roll == pytest.approx(0.0, abs=1e-6)  # nose down to accelerate north


@pytest.mark.timeout(20)
def test_fall_stops_on_the_ground():
    state = VehicleState(pos=(0.0, 0.0, -20.0))
    for _ in range(500):
        state = fall(state, DT)
    assert state.pos[2] == 0.0 and state.vel == (0.0, 0.0, 0.0)


def test_sqrt_controller_shape():
    assert sqrt_controller(0.1, 1.0, 1.25, 0.0) == pytest.approx(0.1)
    big = sqrt_controller(100.0, 1.0, 1.25, 0.0)
    assert big == pytest.approx(math.sqrt(2 * 1.25 * (100.0 - 1.25 / 2)))
    assert sqrt_controller(-100.0, 1.0, 1.25, 0.0) == pytest.approx(-big)
    assert sqrt_controller(0.01, 1.0, 1.25, 0.02) <= 0.01 / 0.02


# --------------------------------------------------------------------------- the real SITL, live

@pytest.mark.ardupilot
@pytest.mark.timeout(120)
def test_live_sitl_flies_a_short_route_as_the_model():
    """Boots the ArduCopter SITL, takes off, and flies the first 12 s of the stock 70 % route sent
    as the plan's state (position, velocity, acceleration) each second; the model, given the
    same setpoints at the same firmware times, flies within RMS_MAX_M of it, and the copter is
    within 1.5 m of the plan's point when each next setpoint is due."""
    from sim.firmware.response_cases import fly_route
    from sim.firmware.response_flight import HOME, SitlFlight
    from sim.firmware.ardupilot import ArduPilotSitl, find_binary, skip_reason

    reason = skip_reason()
    if reason is not None:
        pytest.skip(reason)
    P, V = planner_route(7.0, 2.5)
    sitl = ArduPilotSitl(find_binary(), HOME, speedup=5.0).start()
    try:
        f = SitlFlight(sitl.url(0), 5.0)
        try:
            f.take_off()
            params = f.read_params(("WPNAV_SPEED", "WPNAV_ACCEL", "WPNAV_SPEED_UP", "PSC_JERK_XY",
                                    "PSC_POSXY_P", "PSC_VELXY_P", "PSC_VELXY_I", "PSC_VELXY_D",
                                    "ATC_ACCEL_R_MAX", "ANGLE_MAX"))
            tr = fly_route(f, "pva", P[:13], V[:13]).as_dict()
        finally:
            f.conn.close()
    finally:
        sitl.stop()
    assert all(s[1] == MASK_PVA for s in tr["sends"])
    assert rms_error(tr, limits_for(params)) < RMS_MAX_M
    assert np.max(distance_at_ticks(tr)) < 1.5


# --------------------------------------------------------------------------- PX4 (issue 30)
DATA_PX4 = Path(__file__).parents[1] / "data" / "sitl_response_px4.json.gz"
# RMS position error over each recorded PX4 trace, and the next-tick distance, model against SITL
# (python -m bench.sitl_response --replay tests/data/sitl_response_px4.json.gz)
RMS_MAX_PX4_M = 1.0


@pytest.fixture(scope="module")
def px4():
    return load(DATA_PX4)["px4"]


@pytest.mark.timeout(120)
def test_model_flies_each_recorded_px4_trace(px4):
    """sim.mock.multicopter with PX4's parameters (limits_from_params on its MPC_* names: its position
    controller, no kinematic shaping, SIH's linear drag) given the setpoints PX4 SITL was sent, each
    held until the next as PX4 does. ArduCopter's controller on the same setpoints misses by
    metres: the test fails on a model that is not PX4's."""
    lim = limits_for(px4["params"])
    assert not lim.shaping and lim.speed_xy == 12.0 and lim.accel_xy == 3.0
    for tr in px4["traces"]:
        if not in_envelope("px4", tr["name"]):
            continue
        assert rms_error(tr, lim, 250.0) < RMS_MAX_PX4_M, tr["name"]
    route = next(t for t in px4["traces"] if t["name"] == "route90_pva")
    assert rms_error(route, VehicleLimits(), 250.0) > 2 * rms_error(route, lim, 250.0)


@pytest.mark.timeout(120)
def test_distance_at_the_next_tick_as_px4_sitl(px4):
    """PX4 lags the plan more than ArduCopter (SIH's linear drag is not in the feed-forward): at
    the 90 % route's 8.6 m/s a median 2.4-2.7 m with the plan's state, 8.4 m with the point alone;
    the model says the same within 0.5 m (median) and 1 m (p95)."""
    lim = limits_for(px4["params"])
    for tr in px4["traces"]:
        if not tr["name"].startswith("route"):
            continue
        real = distance_at_ticks(tr)
        model = distance_at_ticks({**tr, "pos": replay(tr, lim, 250.0).tolist()})
        assert abs(np.median(model) - np.median(real)) < 0.5 + 0.1 * np.median(real), tr["name"]
        assert abs(np.percentile(model, 95) - np.percentile(real, 95)) < 1.0 + 0.1 * np.percentile(real, 95)
        if tr["name"].endswith("_pos"):
            assert np.median(real) > 5.0
        else:
            assert np.median(real) < 3.0


def test_the_evaluations_flight_at_px4_flies_px4s_model():
    """``pmon eval --methods flight@px4``: the flown method's vehicle is PX4's (its parameters,
    controller and SIH airframe), planned at its MPC_XY_VEL_MAX / MPC_ACC_HOR capped as the app caps."""
    from sim.evaluation.trials import AUTOPILOTS, method_named
    from sim.mock.multicopter import PX4_SIH_AIRFRAME, limits_from_params

    lim = limits_from_params(AUTOPILOTS["px4"])
    assert not lim.shaping and lim.drag_lin == PX4_SIH_AIRFRAME["drag_lin"] and lim.speed_xy == 12.0
    assert method_named("flight@px4").autopilot == "px4"
