"""Where the clock stops the guidance, as counts: a solve stopped by a clock replays, with the
recorded counts and a clock that never runs out, to the same plan bit for bit."""
from __future__ import annotations

import itertools

import numpy as np

from dataclasses import replace

from onboard.config import load_scenario
from onboard.core.clock_stops import Deadline, SearchClock
from onboard.core.guidance.predictor import Solver, plan_guidance
from onboard.core.monitor import MonitorSetup


def _ticking(step: float):
    """A clock that moves ``step`` s on every reading."""
    c = itertools.count()
    return lambda: next(c) * step


def test_a_deadline_reads_the_clock_once_per_count_and_stays_passed():
    reads = []
    t = iter([0.0, 0.5, 2.0, 5.0])

    def timer():
        reads.append(1)
        return next(t)
    d = Deadline(timer, 1.0)  # ends at 1.0 (first reading 0.0)
    assert not d.passed(0)  # reads 0.5
    assert not d.passed(0)  # the same count: no reading
    assert d.passed(1)  # reads 2.0: passed at 1
    assert d.passed(1) and d.passed(7) and not d.passed(0)
    assert len(reads) == 3


def test_plans_stopped_by_the_clock_replay_to_the_same_bits_by_their_counts():
    setup = MonitorSetup.from_scenario(load_scenario("paper"))
    params = replace(setup.guidance, max_solve_time_s=0.02)
    rng = np.random.default_rng(3)
    stopped = 0
    for j in range(setup.n_targets):
        mean = setup.initial_means[j] + np.r_[rng.normal(0, 30, 2), 0, rng.normal(0, 2, 2), 0]
        live = SearchClock(_ticking(0.001))  # 20 clock readings per solve's time
        a = plan_guidance(setup.model, params, setup.obstacles, mean, setup.goals[j], solver=Solver(timer=live))
        stopped += len(live.stops)
        again = SearchClock(lambda: 0.0, replay=live.stops)  # a clock that never runs out
        b = plan_guidance(setup.model, params, setup.obstacles, mean, setup.goals[j], solver=Solver(timer=again))
        assert again.deadlines == live.deadlines
        assert (a.status, a.qp_solves) == (b.status, b.qp_solves)
        assert np.array_equal(a.controls, b.controls) and np.array_equal(a.means, b.means)
        free = plan_guidance(setup.model, replace(params, max_solve_time_s=None), setup.obstacles, mean,
                             setup.goals[j])
        if live.stops:
            assert a.status == "timeout" and free.qp_solves > a.qp_solves
    assert stopped >= 1  # the clock did stop a solve
