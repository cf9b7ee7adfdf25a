"""The clairvoyant ceiling (sim/evaluation/ceiling.py, sim/evaluation/ceiling_search.py): its objective is the
evaluation's PCRB, its gradient is right, its paths keep the vehicle's rules, and its search
never returns a path worse than one it was given."""
from __future__ import annotations

import numpy as np
import pytest

from onboard.config import load_scenario
from onboard.core.planning.information import information_reduction_factor
from onboard.core.monitor import MonitorSetup
from sim.evaluation import ceiling as ce
from sim.evaluation import ceiling_search as cs
from sim.evaluation.trials import pcrb_position


@pytest.fixture(scope="module")
def setup():
    return MonitorSetup.from_scenario(load_scenario("paper"))


def _truth(K: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Two targets moving south past the paper's obstacles, and closed-loop gains pulling them
    back (random, small): (K, 2, 6), (K-1, 2, 3, 6)."""
    t = np.arange(K)[:, None]
    truth = np.zeros((K, 2, 6))
    truth[:, 0, :2] = np.column_stack([300 + 2.0 * t[:, 0], 800 - 8.0 * t[:, 0]])
    truth[:, 1, :2] = np.column_stack([750 - 3.0 * t[:, 0], 700 - 7.0 * t[:, 0]])
    truth[:, :, 3:5] = np.array([[2.0, -8.0], [-3.0, -7.0]])
    gains = np.zeros((K - 1, 2, 3, 6))
    gains[:, :, :2, [0, 1, 3, 4]] = -rng.uniform(0, 300, (K - 1, 2, 2, 4))
    return truth, gains


def _problem(setup, K=30, start=(500.0, 900.0), speed=9.0, accel=2.5):
    truth, gains = _truth(K, np.random.default_rng(1))
    return ce.problem_for_trial(setup, truth, gains, np.array([*start, 40.0]), 10, speed, accel), truth, gains


def test_bound_is_the_evaluations_pcrb_on_a_fixed_path(setup):
    pb, truth, gains = _problem(setup)
    rng = np.random.default_rng(2)
    paths = pb.start + np.cumsum(rng.normal(0, 6, (3, pb.K, 2)), axis=1)
    q = information_reduction_factor(setup.sensor.p_detect, 1.0, setup.sensor.sigma_rad)
    mine = ce.bound_m2(pb, paths)
    for b in range(3):
        ref = pcrb_position(setup.model, setup.initial_cov, truth, gains, paths[b][:, None], setup.sensor.sigma_rad, q)
        np.testing.assert_allclose(mine[b], ref, rtol=1e-9)
    # and the objective is the evaluation's average of it for one trial (bench: bound_m)
    np.testing.assert_allclose(ce.window_bound(pb, mine), [ce.aggregate_bound(m[None], 10) for m in mine],
                               rtol=1e-12)


@pytest.mark.parametrize("weighted", [False, True])
def test_gradient_is_the_derivative_of_the_objective(setup, weighted):
    pb, *_ = _problem(setup)
    rng = np.random.default_rng(3)
    paths = pb.start + np.cumsum(rng.normal(0, 6, (2, pb.K, 2)), axis=1)
    w = rng.random((pb.K, 2)) if weighted else None
    f, g = ce.objective_gradient(pb, paths, w)

    def obj(p):
        b = ce.bound_m2(pb, p)
        return np.einsum("km,bkm->b", w, b) if weighted else ce.window_bound(pb, b)
    np.testing.assert_allclose(f, obj(paths), rtol=1e-12)
    eps = 1e-3
    for b, k, c in [(0, 0, 0), (0, 5, 1), (1, 12, 0), (1, 29, 1)]:
        up, dn = paths.copy(), paths.copy()
        up[b, k, c] += eps
        dn[b, k, c] -= eps
        fd = (obj(up)[b] - obj(dn)[b]) / (2 * eps)
        assert g[b, k, c] == pytest.approx(fd, rel=1e-4, abs=1e-9)


def test_flown_paths_keep_the_limits_and_feasible_ones_pass_unchanged(setup):
    pb, *_ = _problem(setup)
    rng = np.random.default_rng(4)
    wild = rng.normal(0, 10.0, (4, pb.K - 1, 2))  # far beyond 2.5 m/s^2
    paths, flown = ce.fly(pb, wild)
    v = ce.kinematics(pb.K, pb.dt).Lv @ flown
    assert np.linalg.norm(flown, axis=2).max() <= pb.accel_max + 1e-9
    assert np.linalg.norm(v, axis=2).max() <= pb.speed_max + 1e-9
    np.testing.assert_allclose(paths, pb.start + ce.kinematics(pb.K, pb.dt).Lp @ flown, atol=1e-9)
    again, flown2 = ce.fly(pb, flown)
    np.testing.assert_allclose(flown2, flown, atol=1e-12)
    np.testing.assert_allclose(again, paths, atol=1e-9)


def test_check_rejects_obstacles_area_and_limits(setup):
    pb, *_ = _problem(setup, start=(400.0, 700.0))  # north of O1 (x 330-470, y 550-650 inflated)
    south = np.tile([0.0, -2.0], (pb.K - 1, 1))[None]  # straight through O1
    east = np.tile([2.0, 0.0], (pb.K - 1, 1))[None]
    p_s, a_s = ce.fly(pb, south)
    p_e, a_e = ce.fly(pb, east)
    assert not ce.check_path(pb, p_s, a_s)[0]
    assert ce.check_path(pb, p_e, a_e)[0]
    fast = a_e.copy()
    fast[0, 0] = [2.6, 0.0]  # one tick over a_max
    assert not ce.check_path(pb, ce.kinematics(pb.K, pb.dt).Lp @ fast + pb.start, fast)[0]
    pb2, *_ = _problem(setup, start=(990.0, 500.0))
    p_out, a_out = ce.fly(pb2, east)  # out of the area to the east
    assert not ce.check_path(pb2, p_out, a_out)[0]


def test_search_never_returns_worse_than_a_given_path_and_keeps_the_rules(setup):
    pb, *_ = _problem(setup, K=25)
    given = ce.fly(pb, np.tile([0.0, -0.5], (pb.K - 1, 1))[None])
    value = ce.window_bound(pb, ce.bound_m2(pb, given[0]))[0]
    c = cs.search(pb, (given[1], ["given"]), only=("centroid+0",), coarse_iter=15, keep=1, fine_iter=15)
    assert c.value <= value + 1e-12
    assert c.value < value  # the SQP does improve on a slow straight path
    assert ce.check_path(pb, c.path[None], c.acc[None])[0]
    np.testing.assert_allclose(c.value, ce.window_bound(pb, ce.bound_m2(pb, c.path[None]))[0], rtol=1e-12)


def test_sqp_improves_its_start_within_the_limits(setup):
    pb, *_ = _problem(setup, K=25)
    start = ce.fly(pb, np.tile([0.0, -1.0], (pb.K - 1, 1))[None])[1]
    before = cs.evaluate(pb, start)
    acc, nit, calls = cs.sqp(pb, start, block=2, maxiter=30)
    after = cs.evaluate(pb, acc)
    assert after.ok[0] and after.value[0] < before.value[0]
    assert np.linalg.norm(after.acc, axis=2).max() <= pb.accel_max + 1e-9
