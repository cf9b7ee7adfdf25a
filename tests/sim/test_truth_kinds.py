"""The truths the model did not write (sim/truth/kinds.py): each kind does what its name says,
starts where the nominal truth starts (paired trial by trial), and is refused where it cannot be."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from onboard.config import load_scenario
from onboard.core.obstacles import Obstacles
from sim.truth.kinds import TRUTH_KINDS, check_kind, draw_kind, filter_scenario, simulate_kind, truth_world

STEPS = 60


@pytest.fixture(scope="module")
def paper():
    return load_scenario("paper")


def _truth(sc, kind, seed=11):
    return simulate_kind(sc, STEPS, np.random.default_rng(seed), kind, np.random.default_rng(seed + 1))


@pytest.fixture(scope="module")
def nominal(paper):
    return _truth(paper, "nominal")


def test_every_kind_starts_where_the_nominal_truth_starts(paper, nominal):
    for kind in TRUTH_KINDS[1:]:
        tr = _truth(paper, kind)
        np.testing.assert_array_equal(tr[0, :, :3], nominal[0, :, :3], err_msg=kind)


def test_stationary_targets_never_move(paper, nominal):
    tr = _truth(paper, "stationary")
    assert np.all(tr == tr[0]) and np.all(tr[:, :, 3:] == 0.0)


def test_candidate_goal_targets_head_for_one_of_the_scenarios_goals(paper):
    rng = np.random.default_rng(4)
    names = {draw_kind(paper, "candidate_goal", rng, STEPS).goal_names for _ in range(30)}
    flat = {n for ns in names for n in ns}
    assert flat == {"G", "W", "E"}  # every candidate is drawn
    d = draw_kind(paper, "candidate_goal", np.random.default_rng(12), STEPS)
    tr = _truth(paper, "candidate_goal")
    for j, name in enumerate(d.goal_names):
        goal = np.array(paper.goal_named(name).center_m[:2])
        assert np.linalg.norm(tr[-1, j, :2] - goal) < np.linalg.norm(tr[0, j, :2] - goal) - 100.0, name


def test_unknown_goals_are_points_nobody_named_away_from_the_start(paper):
    obstacles = Obstacles.from_boxes(paper.obstacles)
    for seed in range(20):
        d = draw_kind(paper, "unknown_goal", np.random.default_rng(seed), STEPS)
        for t, g in zip(paper.targets, d.goals):
            p = np.array(g)
            assert all(np.linalg.norm(p[:2] - np.array(b.center_m[:2])) >= 200.0 for b in paper.goals)
            assert np.linalg.norm(p[:2] - np.array(t.position_m[:2])) >= 300.0
            assert not obstacles.extruded(0.0).contains(p[None]).any()
        assert d.goal_names == (None,) * 4


def test_stop_turn_targets_stop_for_twenty_seconds_or_turn_back(paper):
    d = draw_kind(paper, "stop_turn", np.random.default_rng(12), STEPS)
    tr = _truth(paper, "stop_turn")
    kinds = {}
    for m in d.mismatch:
        kinds.setdefault(m.target, []).append((m.kind, m.at_step))
    assert set(kinds) == {0, 1, 2, 3}
    for j, ev in kinds.items():
        if ev[0][0] == "stop":
            (_, at), (resume, back) = ev
            assert resume == "resume" and back - at == 20
            # held near where it stopped (its guidance brakes and holds; noise Q moves it)
            held = tr[at + 8:back, j, :2]
            assert np.linalg.norm(held.mean(axis=0) - tr[at, j, :2]) < 60.0
        else:
            assert ev == [("turn_back", STEPS // 2)]


def test_wandering_targets_stay_in_the_area_out_of_obstacles_and_slow(paper):
    tr = _truth(paper, "wander")
    assert (tr[:, :, :2] >= 0).all() and (tr[:, :, :2] <= 1000).all()
    speed = np.linalg.norm(tr[:, :, 3:5], axis=-1)
    assert speed.max() <= 6.0 + 1e-9 and speed.mean() > 1.0
    ground = Obstacles.from_boxes(paper.obstacles).extruded(0.0)
    assert not ground.contains(tr.reshape(-1, 6)[:, :3]).any()


def test_a_kind_the_scenario_cannot_host_is_refused_in_one_line(paper):
    with pytest.raises(ValueError, match="--truth must be one of"):
        check_kind(paper, "teleport")
    one_goal = replace(paper, goals=paper.goals[:1])
    with pytest.raises(ValueError, match="at least 3 goal regions"):
        check_kind(one_goal, "candidate_goal")
    with pytest.raises(ValueError, match="--told applies"):
        filter_scenario(paper, "wander", draw_kind(paper, "wander", None, STEPS), told=True)


def test_the_filter_knows_the_candidates_and_told_knows_the_truth(paper):
    untold = filter_scenario(paper, "candidate_goal")
    assert all(t.goal is None and t.candidates == ("G", "W", "E") for t in untold.targets)
    d = draw_kind(paper, "candidate_goal", np.random.default_rng(3), STEPS)
    told = filter_scenario(untold, "candidate_goal", d, told=True)
    assert tuple(t.goal for t in told.targets) == d.goal_names
    stat = filter_scenario(paper, "stationary", draw_kind(paper, "stationary", None, STEPS), told=True)
    assert all(t.stationary and t.candidates == () for t in stat.targets)


def test_the_world_is_reproducible_from_its_seeds(paper):
    a = truth_world(paper, np.random.default_rng(5), "unknown_goal", np.random.default_rng(6), STEPS)
    b = truth_world(paper, np.random.default_rng(5), "unknown_goal", np.random.default_rng(6), STEPS)
    np.testing.assert_array_equal(a.goals, b.goals)
