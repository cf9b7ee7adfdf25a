"""The evaluation's baseline planners (sim/evaluation/baselines.py): registered by name beside the
flight planners, built from a setup naming them, and drawing from their own stream."""
from dataclasses import replace

import numpy as np

from onboard.core.guidance.predictor import GuidanceWorkspace
from onboard.core.monitor import MonitorSetup, Scan, initial_state, tick, uav_planner
from onboard.core.planning.inputs import UavState
from sim.evaluation.baselines import HoverPlanner, OrbitPlanner, RandomPlanner, register_baselines

register_baselines()  # (sim.evaluation.methods does so too; this test needs no method)


def test_a_setup_naming_a_baseline_flies_it(paper):
    setup = MonitorSetup.from_scenario(paper)
    for name, kind in (("hover", HoverPlanner), ("orbit", OrbitPlanner), ("random", RandomPlanner)):
        assert isinstance(uav_planner(replace(setup, planner=name)), kind)


def test_a_planners_draws_never_shift_the_filters(paper):
    """The random baseline draws from ``planner_rng``: with the same scans, the filter's beliefs
    after each tick are those of the hover baseline from the same streams, and its moves are
    admissible candidates of S_(t+1); drawing from the filter's own stream instead changes them."""
    def run(planner, separate):
        setup = replace(MonitorSetup.from_scenario(paper), planner=planner)
        rng, prng = np.random.default_rng(5), np.random.default_rng(6)
        state, ws = initial_state(setup, rng), GuidanceWorkspace()
        uav, out = np.array([300.0, 300.0, setup.grid.altitude_m]), []
        for _ in range(3):
            bearings = tuple(np.array([0.5 + 0.1 * j]) for j in range(setup.n_targets))
            state, res = tick(setup, state, [Scan(uav, bearings)], rng, plan_from=UavState(uav), workspace=ws,
                              planner_rng=prng if separate else None)
            out.append((np.stack([b.particles for b in state.beliefs]), res.planning))  # scans stay put
        return out

    hover, rand, shared = run("hover", True), run("random", True), run("random", False)
    moved = 0
    for (b_h, p_h), (b_r, p_r) in zip(hover, rand):
        np.testing.assert_array_equal(b_h, b_r)
        assert p_h.index == 0 and np.array_equal(p_h.position, p_h.candidates[0])
        assert p_r.admissible[p_r.index] and len(p_r.candidates) == 4 * 15 + 1
        moved += p_r.index != 0
    assert moved >= 2
    assert not np.array_equal(shared[-1][0], rand[-1][0])
