"""What the route planner would fly if it knew where the targets will be: an oracle experiment.

    python -m bench.oracle_routes --out DIR [--trials 100] [--seed 2024] [--methods flight@stock]
                                  [--workers 2] [--to-the-end] [--set KEY=VALUE ...]

``pmon eval paper`` on the same trials (same truths, starts and DF draws), with one change in the
lookahead planner: each route is scored against the targets' TRUE positions over its horizon,
x_(t+1..t+H) of the trial's truth (the last one held past the trial's end), instead of their
predicted guidance plans mu_(t+1..t+H|t). The beliefs the score starts from, the routes and the
flight are the evaluation's own. No planner can do this; it measures how much of the flown path's
distance to the clairvoyant ceiling (docs/PLANNING.md) is the planner not knowing the targets'
future, and how much is how routes are scored. ``--to-the-end``: also the horizon cut at the
trial's last tick, as the ceiling's window ends there (a mission's end no flying planner knows).
Writes ``pmon eval``'s files to ``--out``.
"""
from __future__ import annotations

import os
import sys
from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from onboard.core.planning import planners as _planners
from sim.evaluation import trials as _ev

_NOW: dict = {"truth": None, "tick": 0}  # the trial's truth (K, M, 6) and the tick being run
TO_THE_END = "PMON_ORACLE_TO_THE_END"  # environment: inherited by the spawned workers
_run_method = _ev.run_method
_tick = _ev.tick
_plan = _planners.LookaheadPlanner.plan


def _run_method_recording(cfg, method, trial, truth, start, gains=None, path=None):
    _NOW["truth"] = truth
    return _run_method(cfg, method, trial, truth, start, gains, path)


def _tick_counting(setup, state, *args, **kwargs):
    _NOW["tick"] = state.step
    return _tick(setup, state, *args, **kwargs)


def _oracle_plan(self, inputs, rng):
    """The planner's own ``plan``, its targets' plans replaced by their true future (M, H, 6)."""
    truth, k = _NOW["truth"], _NOW["tick"]
    idx = np.minimum(np.arange(k + 1, k + 1 + self.steps), len(truth) - 1)
    if os.environ.get(TO_THE_END) == "1":
        idx = np.unique(idx)  # the ticks up to the last, once each
    true_plans = tuple(SimpleNamespace(means=truth[idx, j]) for j in range(truth.shape[1]))
    return _plan(self, replace(inputs, plans=true_plans), rng)


# patched at import, so the evaluation's worker processes (spawned: they import this module) have it
_ev.run_method = _run_method_recording
_ev.tick = _tick_counting
_planners.LookaheadPlanner.plan = _oracle_plan


def main(argv=None) -> int:
    from bench import patched_eval_parser, run_patched_eval
    ap = patched_eval_parser(__doc__, "comma-separated; the lookahead ones get the oracle")
    ap.add_argument("--to-the-end", action="store_true", help="the horizon cut at the trial's last tick")
    a = ap.parse_args(argv)
    os.environ[TO_THE_END] = "1" if a.to_the_end else "0"
    return run_patched_eval(a)


if __name__ == "__main__":
    sys.exit(main())
