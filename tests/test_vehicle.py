"""Calibration of sim.vehicle against a stock ArduCopter SITL (GUIDED, position targets).

Measured on the real SITL with stock parameters:
- a 20 m horizontal step from hover is reached (within 1 m) after about 5.6 s;
- a 5 m step after about 2.6 s;
- a setpoint advanced 5 m every second is followed at 5 m/s about 14 m behind
  (distance from the newly sent setpoint to the vehicle when it is sent).
The model must match each within 15 %.
"""

import math

import numpy as np
import pytest

from sim.vehicle import (
    Setpoint,
    VehicleLimits,
    VehicleState,
    attitude,
    fall,
    sqrt_controller,
    step,
    stopping_point,
)

DT = 0.02  # 50 Hz, as the mock autopilot steps the model
HOVER = VehicleState(pos=(0.0, 0.0, -10.0))


def time_to_reach(distance: float, rng=None, limits=VehicleLimits()) -> float:
    """Seconds until a hovering vehicle is within 1 m of a target `distance` m north."""
    target = (distance, 0.0, -10.0)
    state, t = HOVER, 0.0
    while t < 60.0:
        state = step(state, Setpoint(pos=target), DT, limits, rng)
        t += DT
        if math.dist(state.pos, target) < 1.0:
            return t
    raise AssertionError("target never reached")


def ramp_lag(speed_step: float = 5.0, seconds: float = 40.0):
    """Lag behind a setpoint advanced speed_step m every second; (lags, speeds) in steady state."""
    state, lags, speeds = HOVER, [], []
    per_s = round(1.0 / DT)
    target = HOVER.pos
    for i in range(round(seconds / DT)):
        t = i * DT
        if i % per_s == 0:
            target = (target[0] + speed_step, 0.0, -10.0)
            if t >= 15.0:
                lags.append(target[0] - state.pos[0])
        state = step(state, Setpoint(pos=target), DT)
        if t >= 15.0:
            speeds.append(math.hypot(state.vel[0], state.vel[1]))
    return np.array(lags), np.array(speeds)


@pytest.mark.timeout(20)
def test_20m_step_takes_about_5_6_s():
    t = time_to_reach(20.0)
    assert t == pytest.approx(5.6, rel=0.15), t


@pytest.mark.timeout(20)
def test_5m_step_takes_about_2_6_s():
    t = time_to_reach(5.0)
    assert t == pytest.approx(2.6, rel=0.15), t


@pytest.mark.timeout(20)
def test_noise_does_not_change_the_calibration():
    rng = np.random.default_rng(7)
    assert time_to_reach(20.0, rng) == pytest.approx(5.6, rel=0.15)
    assert time_to_reach(5.0, rng) == pytest.approx(2.6, rel=0.15)


@pytest.mark.timeout(20)
def test_ramp_followed_at_5_m_s_about_14_m_behind():
    lags, speeds = ramp_lag()
    assert lags.mean() == pytest.approx(14.0, rel=0.15), lags
    assert lags.std() < 0.5
    assert speeds.mean() == pytest.approx(5.0, rel=0.05)


@pytest.mark.timeout(20)
@pytest.mark.parametrize("speed", [10.0, 5.0, 2.0])
def test_speed_limits_never_exceeded(speed):
    limits = VehicleLimits(speed_xy=speed)
    rng = np.random.default_rng(1)
    state = VehicleState()
    targets = [(300.0, 0.0, -40.0), (-200.0, 150.0, -5.0), (0.0, 0.0, 0.0)]
    for target in targets:
        for _ in range(round(60.0 / DT)):
            state = step(state, Setpoint(pos=target), DT, limits, rng)
            assert math.hypot(state.vel[0], state.vel[1]) <= speed + 1e-9
            assert -limits.speed_up - 1e-9 <= state.vel[2] <= limits.speed_down + 1e-9
            assert math.hypot(state.acc[0], state.acc[1]) <= limits.accel_xy + 1e-9
    # a velocity command above the limit is clipped too
    for _ in range(round(20.0 / DT)):
        state = step(state, Setpoint(vel=(50.0, 50.0, -9.0)), DT, limits)
    assert math.hypot(state.vel[0], state.vel[1]) == pytest.approx(speed)
    assert state.vel[2] == pytest.approx(-limits.speed_up)


@pytest.mark.timeout(20)
def test_speed_override_and_vertical_limits():
    state = VehicleState()
    for _ in range(round(30.0 / DT)):
        state = step(state, Setpoint(pos=(500.0, 0.0, -50.0), speed_xy=3.0), DT)
        assert math.hypot(*state.vel[:2]) <= 3.0 + 1e-9
        assert state.vel[2] >= -2.5 - 1e-9  # WPNAV_SPEED_UP
    for _ in range(round(10.0 / DT)):
        state = step(state, Setpoint(pos=(state.pos[0], 0.0, 0.0)), DT)
        assert state.vel[2] <= 1.5 + 1e-9  # WPNAV_SPEED_DN


@pytest.mark.timeout(20)
def test_velocity_and_brake_commands():
    state = HOVER
    for _ in range(round(10.0 / DT)):
        state = step(state, Setpoint(vel=(0.0, 4.0, 0.0)), DT)
    assert state.vel[1] == pytest.approx(4.0, abs=1e-3)
    stop = stopping_point(state)
    for _ in range(round(10.0 / DT)):
        state = step(state, Setpoint(), DT)  # nothing commanded: brake
    assert math.hypot(*state.vel) < 0.05
    assert state.pos[1] == pytest.approx(stop[1], abs=2.0)


@pytest.mark.timeout(20)
def test_yaw_turns_at_limited_rate_and_attitude_follows_acceleration():
    state = HOVER
    state = step(state, Setpoint(yaw=math.pi / 2, pos=HOVER.pos), 1.0)
    assert state.yaw == pytest.approx(math.radians(90.0) * 1.0, abs=1e-6)
    state = VehicleState(pos=(0, 0, -10), acc=(2.0, 0.0, 0.0), yaw=0.0)
    roll, pitch, _ = attitude(state)
    assert pitch < 0 and roll == pytest.approx(0.0)  # nose down to accelerate north


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
