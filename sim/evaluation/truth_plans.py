"""The simulated targets' own guidance over one of ``pmon eval``'s trials: each target's plan
status at each step, whether its plan's cost jumped, and the wall stops (bench/truth_guidance.py
counts them over many trials)."""
from __future__ import annotations

import numpy as np

from onboard.config import load_scenario
from sim.evaluation import trials as ev
from sim.truth.world import TruthWorld

JUMP = 1.3  # a plan costing more than this times the step before's is a jump (docs/GUIDANCE.md)
JUMP_FLOOR = 2e5  # ... and more than this: near the goal a few metres of noise change the cost by more


def trial_statuses(overrides: dict, n_trials: int, seed: int, trial: int
                   ) -> tuple[list[list[str]], list[bool], list[tuple[int, int]]]:
    """Per target, the status of its plan at each step of trial ``trial`` (``margin0``: a plan
    without the margin); per target, whether its plan's P1 cost ever jumped (above ``JUMP``
    times the step before's and above ``JUMP_FLOOR``); and the wall stops, (scan k, target from
    1): the truth held the target where it was with zero velocity at scan k (sim/truth/world.py: every
    noise draw and the noise-free step entered an obstacle)."""
    cfg = ev.make_config(load_scenario("paper", overrides), n_trials, seed)
    world = TruthWorld.from_scenario(cfg.scenario, ev._rng(cfg.seed, trial, 0))
    out = [[] for _ in range(len(cfg.scenario.targets))]
    last = [float("nan")] * len(out)
    jumped = [False] * len(out)
    stops = []
    for k in range(1, cfg.n_ticks):
        held = world.stuck_steps.copy()
        world.step()
        stops += [(k, j + 1) for j in np.flatnonzero(world.stuck_steps > held)]
        for j, plan in enumerate(world.plans):
            margin = getattr(plan, "margin_m", None)  # absent before the field was added
            out[j].append("margin0" if margin == 0.0 else plan.status)
            jumped[j] |= bool(plan.cost > max(JUMP * last[j], JUMP_FLOOR))  # False with a nan (a fallback)
            last[j] = plan.cost
    return out, jumped, stops
