"""The true targets: drawn from N(mu_0, Sigma_0), driven to their goal by their own guidance with
process noise Q, never inside an obstacle, and the model mismatches do what they say."""
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from onboard.settings.sections import Box
from onboard.core.obstacles import Obstacles
from sim.truth.world import Mismatch, TruthWorld, blocked, simulate_truth

ALPHA = 1e-4


@pytest.fixture(scope="module")
def short(paper):
    """The paper scenario with a shorter guidance horizon: same physics, faster tests."""
    return replace(paper, guidance=replace(paper.guidance, horizon=25))


def _run(sc, n, seed, mismatch=()):
    world = TruthWorld.from_scenario(sc, np.random.default_rng(seed), mismatch)
    return world, np.array([world.states] + [world.step() for _ in range(n)])


def test_initial_states_follow_the_prior(paper):
    draws = np.array([TruthWorld.from_scenario(paper, np.random.default_rng(s)).states for s in range(300)])
    mu = np.array([t.mean for t in paper.targets])
    sd = np.sqrt(np.array(paper.initial_cov_diag))
    for d in (0, 1, 3, 4):  # x, y, vx, vy
        z = (draws[:, :, d].mean(axis=0) - mu[:, d]) / (sd[d] / np.sqrt(len(draws)))
        assert np.all(np.abs(z) < 3.9)
    assert np.all(np.abs(draws[:, :, 2]) < 1e-3)  # on the ground


def test_stepping_equals_simulate_truth_and_is_seeded(short):
    world, traj = _run(short, 4, seed=7)
    again = simulate_truth(short, 4, np.random.default_rng(7))
    assert traj.shape == (5, 4, 6) and np.array_equal(traj, again)
    assert world.time_s == pytest.approx(4 * short.dynamics.dt_s)
    assert not np.array_equal(traj, simulate_truth(short, 4, np.random.default_rng(8)))


def test_targets_head_for_their_goal_with_noise_q_and_never_enter_an_obstacle(short):
    n = 30
    world, traj = _run(short, n, seed=3)
    goal = np.array(short.goals[0].center_m[:2])
    d0 = np.linalg.norm(traj[0, :, :2] - goal, axis=1)
    d1 = np.linalg.norm(traj[-1, :, :2] - goal, axis=1)
    # 30 s at up to 16 m/s: each target is well on its way (noise alone would not do this)
    assert np.all(d0 - d1 > 150.0)
    obstacles = Obstacles.from_boxes(short.obstacles)
    for k in range(n):
        for j in range(4):
            assert not blocked(obstacles, traj[k, j, :3], traj[k + 1, j, :3])
    # the process noise: with the targets' own controls replayed, x_t - (A x + B u) ~ N(0, Q)
    rng = np.random.default_rng(3)
    w2 = TruthWorld.from_scenario(short, rng)
    resid = []
    for _ in range(n):
        x = w2.states
        new = w2.step()
        u = np.array([p.next_control for p in w2.plans])
        resid.append(new - (x @ w2.model.A.T + u @ w2.model.B.T))
    resid = np.concatenate(resid)
    q = np.diag(w2.model.Q)
    for d in (0, 1, 3, 4):
        stat = np.sum(resid[:, d] ** 2) / q[d]  # mean known (0): chi2 with len(resid) dof
        m = len(resid)
        assert stats.chi2.ppf(ALPHA / 2, m) < stat < stats.chi2.ppf(1 - ALPHA / 2, m), d


def test_blocked_is_a_ground_plane_test():
    box = Obstacles.from_boxes([Box("O", (0.0, 0.0, 10.0), (20.0, 20.0, 20.0))])
    assert blocked(box, np.array([-30.0, 0.0, 0.0]), np.array([30.0, 0.0, 0.0]))  # across
    assert blocked(box, np.array([-30.0, 0.0, 0.0]), np.array([0.0, 0.0, -1e-5]))  # just below the base
    assert not blocked(box, np.array([-30.0, 15.0, 0.0]), np.array([30.0, 15.0, 0.0]))  # beside
    high = Obstacles.from_boxes([Box("B", (0.0, 0.0, 50.0), (20.0, 20.0, 20.0))])  # a bridge deck
    assert not blocked(high, np.array([-30.0, 0.0, 0.0]), np.array([30.0, 0.0, 0.0]))


def test_mismatch_stop_holds_the_target(short):
    at, n = 5, 25
    _, nominal = _run(short, n, seed=11)
    _, stopped = _run(short, n, seed=11, mismatch=[Mismatch(target=2, kind="stop", at_step=at)])
    assert np.array_equal(nominal[:at + 1], stopped[:at + 1])  # same world until the mismatch
    assert np.array_equal(nominal[:, [0, 1, 3], :2], stopped[:, [0, 1, 3], :2])  # others unaffected
    hold = stopped[at, 2, :2]
    # it brakes within its force limit and then stays near: the process noise makes it wander
    # (about 5.5 m per step, pulled back by its guidance) but it no longer travels
    late = np.linalg.norm(stopped[at + 10:, 2, :2] - hold, axis=1)
    assert late.max() < 60.0
    assert np.linalg.norm(nominal[-1, 2, :2] - hold) > 150.0


def test_mismatch_turn_back_returns_toward_the_start(short):
    at, n = 10, 30
    _, nominal = _run(short, n, seed=12)
    world, back = _run(short, n, seed=12, mismatch=[Mismatch(target=0, kind="turn_back", at_step=at)])
    start = back[0, 0, :2]
    assert np.allclose(world.goals[0, :2], start)
    away_at = np.linalg.norm(back[at, 0, :2] - start)
    assert np.linalg.norm(back[-1, 0, :2] - start) < away_at - 50.0
    assert np.linalg.norm(nominal[-1, 0, :2] - start) > away_at + 50.0


def test_mismatch_other_goal(short):
    g2 = Box("G2", (950.0, 950.0, 0.0), (50.0, 50.0, 0.0))
    sc = replace(short, goals=short.goals + (g2,))
    at, n = 0, 20
    _, nominal = _run(sc, n, seed=13)
    _, other = _run(sc, n, seed=13, mismatch=[Mismatch(target=3, kind="other_goal", at_step=at,
                                                       goal=len(short.goals))])
    dist = lambda tr: np.linalg.norm(tr[-1, 3, :2] - np.array(g2.center_m[:2]))  # noqa: E731
    assert dist(other) < dist(nominal) - 150.0


def test_mismatch_validation(paper):
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="kind"):
        Mismatch(0, "teleport", 3)
    with pytest.raises(ValueError, match="at_step"):
        Mismatch(0, "stop", -1)
    with pytest.raises(ValueError, match="goal"):
        Mismatch(0, "other_goal", 3)
    with pytest.raises(ValueError, match="target"):
        TruthWorld.from_scenario(paper, rng, [Mismatch(4, "stop", 3)])
    with pytest.raises(ValueError, match="goal"):
        TruthWorld.from_scenario(paper, rng, [Mismatch(0, "other_goal", 3, goal=len(paper.goals))])  # no such goal


def test_recording_the_closed_loop_gains_changes_no_state(short):
    """The PCRB's gains (the guidance's du_0/dx at each true state) come with the truth, and
    asking for them does not change the truth (no random draw, the same plans)."""
    plain = simulate_truth(short, 6, np.random.default_rng(5))
    states, gains = simulate_truth(short, 6, np.random.default_rng(5), with_gains=True)
    np.testing.assert_array_equal(plain, states)
    assert gains.shape == (6, len(short.targets), 3, 6)
    assert np.all(np.isfinite(gains)) and np.abs(gains).max() > 0.0
    assert np.all(gains[:, :, 2] == 0.0)  # u_z = 0: no vertical feedback


def test_a_wall_stop_is_counted_where_the_truth_holds_a_target(paper):
    """sim.evaluation.truth_plans finds the wall stops of pmon eval's truths (bench/truth_guidance.py: 15 in
    100 trials at seed 2024, docs/LOG.md): trial 86's T2 is the earliest, held at scan 9 at 0 m/s."""
    from sim.evaluation import trials as ev
    from sim.evaluation.truth_plans import trial_statuses

    cfg = ev.make_config(paper, 100, 2024, ["hover"])
    world = TruthWorld.from_scenario(cfg.scenario, ev._rng(2024, 86, 0))
    states = [world.states] + [world.step() for _ in range(10)]
    assert world.stuck_steps.tolist() == [0, 1, 0, 0]
    assert np.all(states[9][1, 3:] == 0.0) and np.any(states[8][1, 3:5] != 0.0)
    assert np.array_equal(states[9][1, :3], states[8][1, :3])  # held where it was
    stops = trial_statuses({"mission.duration_s": 12.0}, 100, 2024, 86)[2]
    assert stops == [(9, 2)]
