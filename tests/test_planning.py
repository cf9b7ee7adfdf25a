import math
from types import SimpleNamespace as Box

import numpy as np

from onboard.core.obstacles import Obstacles
from onboard.core.planning import CandidateGrid, admissible, candidate_positions, choose_next_position

GRID = CandidateGrid(step_m=5.0, n_radial=4, n_heading=15, altitude_m=40.0)


def test_candidate_set_is_the_papers():
    c = candidate_positions(np.array([150.0, 200.0, 40.0]), GRID)
    assert c.shape == (4 * 15 + 1, 3)
    np.testing.assert_allclose(c[0], [150, 200, 40])
    r = np.linalg.norm(c[1:, :2] - [150, 200], axis=1)
    np.testing.assert_allclose(np.unique(r.round(9)), [5, 10, 15, 20])


def test_admissibility_excludes_outside_and_blocked():
    wall = Obstacles.from_boxes([Box(center_m=(115, 0, 25), size_m=(4, 200, 50), yaw_rad=0.0)])
    c = candidate_positions(np.array([100.0, 995.0]), GRID)
    ok = admissible(c, np.array([100, 995, 40.0]), (0, 0, 0), (1000, 1000, 1000), wall)
    assert not ok[c[:, 1] > 1000].any()
    c2 = candidate_positions(np.array([100.0, 0.0]), GRID)
    ok2 = admissible(c2, np.array([100, 0, 40.0]), (-1e4, -1e4, 0), (1e4, 1e4, 1e3), wall)
    assert not ok2[c2[:, 0] > 113].any() and ok2[c2[:, 0] < 110].all()


def test_chooses_the_move_that_turns_the_line_of_sight(rng):
    """Target straight ahead (north), uncertain in range only: moving sideways is best."""
    n = 4000
    particles = np.zeros((1, n, 6))
    particles[0, :, 0] = rng.normal(0, 2, n)
    particles[0, :, 1] = 200 + rng.normal(0, 60, n)
    logw = np.full((1, n), -math.log(n))
    res = choose_next_position(particles, logw, np.array([0.0, 0.0]), GRID, math.radians(1.0),
                               (-1e3, -1e3, 0), (1e3, 1e3, 1e3), Obstacles.empty(), "position_trace")
    move = res.position[:2]
    assert np.isclose(np.linalg.norm(move), 20.0)
    assert abs(move[0]) > 3 * abs(move[1])
    along = np.abs(res.candidates[:, 0]) < 1e-6  # moves along the line of sight, and staying
    assert res.scores[res.index] < 0.8 * res.scores[along].min()
