"""onboard.core.setpoint: the position + velocity + acceleration target that flies the plan."""
import math
from dataclasses import replace

import numpy as np
import pytest

from onboard.core.planning.next_position import choose_lookahead, choose_next_position
from onboard.core.planning.inputs import UavState
from onboard.core.setpoint import plan_setpoint
from sim.mock.guided import enu, fly_plan
from sim.mock.multicopter import VehicleState, advance_input
from tests.support.planning_cases import SCORING, VEHICLE, moves, still_targets as _still_targets


@pytest.mark.parametrize("offset", [0.0, 0.13, 0.5, 1.0])
def test_the_firmware_carries_the_setpoint_to_the_planned_next_state(rng, offset):
    """Sent ``offset`` s after the tick, the target ArduCopter moves on by itself (advance_input,
    as the firmware does between messages) is at the planner's next position with its next
    velocity when the next tick comes, for both planners on the vehicle motion."""
    particles, logw, plans = _still_targets(rng, [[0.0, 500.0], [300.0, 200.0]])
    p0, v0 = np.array([10.0, -20.0]), np.array([6.0, -4.0])
    uav = UavState(p0, v0)
    for res in (choose_next_position(particles, logw, uav, moves(VEHICLE), math.radians(1.0), "position_trace", 1.0),
                choose_lookahead(particles, logw, plans, uav, moves(VEHICLE), SCORING)):
        v1 = res.velocities[res.index]
        assert np.linalg.norm(v1 - v0) > 0.5  # the plan accelerates: the test sees the acceleration term
        pos, vel, acc = plan_setpoint(p0, v0, v1, 1.0, offset)
        p, v = advance_input((*pos, 0.0), (*vel, 0.0), (*acc, 0.0), 1.0 - offset)
        np.testing.assert_allclose(p[:2], res.position[:2], atol=1e-9)
        np.testing.assert_allclose(v[:2], v1, atol=1e-9)


def test_the_setpoint_is_the_plans_state_at_the_offset():
    p0, v0, v1 = np.array([1.0, 2.0, 40.0]), np.array([4.0, 0.0, 0.0]), np.array([4.0, 3.0, 0.0])
    pos, vel, acc = plan_setpoint(p0, v0, v1, 1.0)
    np.testing.assert_array_equal(pos, p0)
    np.testing.assert_array_equal(vel, v0)
    np.testing.assert_array_equal(acc, [0.0, 3.0, 0.0])
    pos, vel, acc = plan_setpoint(p0, v0, v1, 2.0, 1.0)  # a 2 s tick, half-way
    np.testing.assert_allclose(acc, [0.0, 1.5, 0.0])
    np.testing.assert_allclose(vel, [4.0, 1.5, 0.0])
    np.testing.assert_allclose(pos, [5.0, 2.75, 40.0])


@pytest.mark.parametrize("args, match", [
    (([0.0, np.nan], [0.0, 0.0], [1.0, 0.0], 1.0, 0.0), "not finite"),
    (([0.0, 0.0], [0.0, np.inf], [1.0, 0.0], 1.0, 0.0), "not finite"),
    (([0.0, 0.0], [0.0, 0.0], [1.0, 0.0, 0.0], 1.0, 0.0), "shapes differ"),
    (([0.0, 0.0], [0.0, 0.0], [1.0, 0.0], 0.0, 0.0), "tick_s"),
    (([0.0, 0.0], [0.0, 0.0], [1.0, 0.0], 1.0, 1.5), "offset_s"),
    (([0.0, 0.0], [0.0, 0.0], [1.0, 0.0], 1.0, -0.1), "offset_s"),
    (([0.0, 0.0], [0.0, 0.0], [1.0, 0.0], 1.0, 0.0, [np.nan, 0.0]), "not finite"),
    (([0.0, 0.0], [0.0, 0.0], [1.0, 0.0], 1.0, 0.0, [1.0, 0.0, 0.0]), "shapes differ"),
])
def test_bad_input_is_refused_not_sent(args, match):
    with pytest.raises(ValueError, match=match):
        plan_setpoint(*args)


# --------------------------------------------------------------------------- continuous acceleration
RAMPS = replace(VEHICLE, jerk_max_mps3=5.0)  # the flight policy's: ArduCopter's PSC_JERK_XY


@pytest.mark.parametrize("offset", [0.0, 0.13, 0.5])
def test_a_continuous_acceleration_starts_where_the_last_plan_left_it_and_ends_on_the_plan(rng, offset):
    """Both planners plan from the acceleration the last tick's plan ended with: the setpoint's
    acceleration at the tick is that one (no step for ArduCopter's jerk-limited shaper), it
    changes by at most jerk_max_mps3 over the tick, and the target the firmware moves on between
    the app's re-sends (10 Hz, each message's acceleration carried on as constant) is at the
    planned next position with the planned velocity at the next tick."""
    particles, logw, plans = _still_targets(rng, [[0.0, 500.0], [300.0, 200.0]])
    p0, v0, a0 = np.array([10.0, -20.0]), np.array([6.0, -4.0]), np.array([-2.0, 1.5])
    uav = UavState(p0, v0, a0)
    for res in (choose_next_position(particles, logw, uav, moves(RAMPS), math.radians(1.0), "position_trace", 1.0),
                choose_lookahead(particles, logw, plans, uav, moves(RAMPS), SCORING)):
        v1 = res.velocities[res.index]
        _, _, acc = plan_setpoint(p0, v0, v1, 1.0, 0.0, a0)
        np.testing.assert_allclose(acc, a0, atol=1e-12)
        pos, vel, a1 = plan_setpoint(p0, v0, v1, 1.0, 1.0, a0)
        np.testing.assert_allclose(pos, res.position[:2], atol=1e-9)
        np.testing.assert_allclose(vel, v1, atol=1e-12)
        assert np.linalg.norm(a1 - a0) <= 5.0 + 1e-9 and np.linalg.norm(a1) <= 2.5 + 1e-9
        p, v = plan_setpoint(p0, v0, v1, 1.0, offset, a0)[:2]
        for d in np.arange(offset, 1.0 - 1e-9, 0.1):  # the re-sends
            pos, vel, acc = plan_setpoint(p0, v0, v1, 1.0, d, a0)
            p, v = advance_input((*pos, 0.0), (*vel, 0.0), (*acc, 0.0), min(0.1, 1.0 - d))
        assert np.linalg.norm(np.asarray(p[:2]) - res.position[:2]) < 0.01


def test_a_copter_with_a_jerk_limit_flies_plans_that_reverse_their_acceleration():
    """The tail of bench/ardupilot.py's distance from the plan: a plan that turns one way and then
    the other steps its acceleration by up to 2 a_max = 5 m/s^2 at a tick, which ArduCopter's
    shaper (PSC_JERK_XY 5 m/s^3, sim.mock.guided's model of it) takes a second to follow: 1.7-1.8 m
    off the planned point at the next tick. With the acceleration ramped (jerk_max_mps3) the
    same copter is within 0.4 m once the first tick is flown."""
    def misses(motion):
        st = VehicleState(pos=(0.0, 0.0, -40.0), vel=(0.0, 8.0, 0.0))  # NED: 8 m/s east, in GUIDED
        a, out = np.zeros(2), []
        for k in range(12):
            p0, v0 = enu(st.pos)[:2], enu(st.vel)[:2]
            ask = np.array([[0.0, 2.5 if (k // 2) % 2 == 0 else -2.5]])  # north, reversed every 2 ticks
            if motion.jerk_max_mps3 > 0.0:
                p1, v1, a1 = (x[0] for x in motion.step(p0[None], v0[None], a[None], ask, 1.0))
            else:
                v1 = v0 + ask[0]
                p1, a1 = p0 + 0.5 * (v0 + v1), None
            st = fly_plan(st, v1, 40.0, 1.0, first=k == 0, a_k=None if a1 is None else a)
            a = a1
            out.append(float(np.linalg.norm(enu(st.pos)[:2] - p1)))
        return np.array(out[1:])

    assert misses(VEHICLE).max() > 1.5
    assert misses(RAMPS).max() < 0.4
