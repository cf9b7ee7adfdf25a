"""onboard.core.setpoint: the position + velocity + acceleration target that flies the plan."""
import math

import numpy as np
import pytest

from onboard.core.obstacles import Obstacles
from onboard.core.planning import choose_lookahead, choose_next_position
from onboard.core.setpoint import plan_setpoint
from sim.multicopter import advance_input
from tests.support.planning_cases import AREA, GRID, LOOKAHEAD, MODEL, VEHICLE, still_targets as _still_targets


@pytest.mark.parametrize("offset", [0.0, 0.13, 0.5, 1.0])
def test_the_firmware_carries_the_setpoint_to_the_planned_next_state(rng, offset):
    """Sent ``offset`` s after the tick, the target ArduCopter moves on by itself (advance_input,
    as the firmware does between messages) is at the planner's next position with its next
    velocity when the next tick comes, for both planners on the vehicle motion."""
    particles, logw, plans = _still_targets(rng, [[0.0, 500.0], [300.0, 200.0]])
    p0, v0 = np.array([10.0, -20.0]), np.array([6.0, -4.0])
    for res in (choose_next_position(particles, logw, p0, GRID, math.radians(1.0), *AREA, Obstacles.empty(),
                                     "position_trace", VEHICLE, v0, 1.0),
                choose_lookahead(particles, logw, plans, p0, v0, GRID, VEHICLE, MODEL, math.radians(1.0), 0.95,
                                 *AREA, Obstacles.empty(), params=LOOKAHEAD)):
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
])
def test_bad_input_is_refused_not_sent(args, match):
    with pytest.raises(ValueError, match=match):
        plan_setpoint(*args)
