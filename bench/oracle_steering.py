"""What the filter would reach if it knew how the true target steers: an oracle experiment.

    python -m bench.oracle_steering [--methods lookahead,greedy_l1,orbit] [--trials 16]

Runs ``bench/consistency.py``'s figures on the same trials as ``pmon eval``, with one change in
the filter's prediction: every particle of target j at tick k is moved with the TRUE target's
guidance linearised at the TRUE state, u_true + K_true (x_i - x_true) (clipped to the input box),
K_true the closed-loop gain the PCRB uses (``sim.truth.world.closed_loop_gain``). No filter can do
this (it uses the truth); it measures how much of the gap between the filter and the posterior
Cramer-Rao bound is the filter not knowing the targets' policy (docs/TRACKING.md, plan steering).
The trial loop and the filter are the evaluation's own; the oracle is patched in here only.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from onboard.core.tracking import steering as _steering
from sim.evaluation import trials as _ev
from sim.truth import world as _truth

_NOW = {"tick": 0, "target": 0}  # which prediction the filter is making (ticks run in order)
_TRUE: dict[str, np.ndarray] = {}  # the current trial's true states, controls and gains

_truth_step = _truth.TruthWorld.step
_tick = _ev.tick
_controls = _steering.particle_controls


def _step_recording(self):
    before = self.states
    out = _truth_step(self)
    self.__dict__.setdefault("oracle_log", []).append(
        (before, np.array([p.next_control for p in self.plans])))
    return out


def _simulate_truth(sc, n_steps, rng, kind="nominal", kind_rng=None, with_gains=False):
    """The nominal truth (the oracle knows only the scenario's model), its states and gains recorded."""
    world = _truth.TruthWorld.from_scenario(sc, rng)
    world.record_gains = True
    states = [world.states]
    for _ in range(n_steps):
        states.append(world.step())
    _TRUE["x"] = np.array([s for s, _ in world.oracle_log])
    _TRUE["u"] = np.array([u for _, u in world.oracle_log])
    _TRUE["K"] = np.array(world.gains)
    return np.array(states), np.array(world.gains)


def _tick_counting(setup, state, *args, **kwargs):
    _NOW["tick"], _NOW["target"] = state.step, 0
    return _tick(setup, state, *args, **kwargs)


def _oracle_controls(plan, particles, goal, setup, rng, *args, **kwargs):
    k, j = _NOW["tick"], _NOW["target"]
    _NOW["target"] += 1
    if k >= len(_TRUE["u"]):  # the last tick's prediction is never scored: no truth beyond it
        return _controls(plan, particles, goal, setup, rng, *args, **kwargs)
    u = _TRUE["u"][k, j] + (particles - _TRUE["x"][k, j]) @ _TRUE["K"][k, j].T
    u[:, :2] = np.clip(u[:, :2], -setup.guidance.u_max_n, setup.guidance.u_max_n)
    return u


# patched at import, so the evaluation's worker processes (spawned: they import this module) have it
_truth.TruthWorld.step = _step_recording
_ev.simulate_kind = _simulate_truth
_ev.tick = _tick_counting
_steering.particle_controls = _oracle_controls


def main() -> int:
    from bench.consistency import consistency, report
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--methods", default="lookahead,greedy_l1,orbit")
    ap.add_argument("--trials", type=int, default=16)
    ap.add_argument("--workers", type=int, default=None)
    args = ap.parse_args()
    res = consistency("paper", args.methods.split(","), args.trials, workers=args.workers)
    report(res, label="oracle ")
    return 0


if __name__ == "__main__":
    sys.exit(main())
