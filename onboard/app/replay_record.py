"""What the run log holds for a replay (``pmon replay``, onboard/app/replay.py): per tick, the
core's inputs and the budgets its guidance spent, and its outputs to the last bit.

Every tick's record gets a ``replay`` field:

- ``run`` (the first tick only): the run's scenario (every setting: ``config.scenario_tree``)
  and the seed of the core's random generator;
- ``setup`` (the first tick, and each tick the core's setup was rebuilt for: a PMON parameter
  set, the autopilot's limits read): the parameters' values and the planner's limits;
- ``rng``: the core generator's state as the tick began;
- ``scans``: the scans the tick used (sensor position, bearings per channel, clutter rates);
  ``plan_from``: the UAV state it planned from (position, velocity, acceleration), or null;
  ``n_radial``: the candidate rings within reach; ``guidance_s``: each solve's time limit;
- ``deadlines``: the guidance solves with a time limit the tick made; ``stops``: where the clock
  stopped one, [deadline index, QP solves spent] (onboard/core/clock_stops.py);
- ``out``: the estimates (means, covariances), each target's guidance status, QP solves and
  lateral margin (0: the search without it ran, ``Plan.margin_m``), the next UAV position and its planned velocity, exactly (JSON floats read back to the same bits).
"""
from __future__ import annotations

import numpy as np

from onboard.config import scenario_tree

VERSION = 1  # of the ``replay`` field


class ReplayRecorder:
    """The ``replay`` fields of one app's ticks (the worker's, worker thread)."""

    def __init__(self, core, seed: int):
        self.core = core
        self.seed = seed
        self._version: object = None  # the core setup's version last recorded

    def fields(self, setup, scans, plan_from, rng_state: dict, clock, res) -> dict:
        core = self.core
        out: dict = {}
        if self._version is None:
            out["run"] = {"version": VERSION, "seed": self.seed, "scenario": scenario_tree(core.base_scenario)}
        if core.version != self._version:
            self._version = core.version
            values, planner = core.built_from
            out["setup"] = {"params": dict(values), "planner": None if planner is None else list(planner)}
        out.update(rng=rng_state, scans=[scan_fields(s) for s in scans],
                   plan_from=None if plan_from is None else {
                       "p": _floats(plan_from.position), "v": _floats(plan_from.velocity),
                       "a": None if plan_from.acceleration is None else _floats(plan_from.acceleration)},
                   n_radial=setup.grid.n_radial, guidance_s=setup.guidance.max_solve_time_s,
                   deadlines=clock.deadlines, stops=clock.stops, out=outputs(res))
        return out


def scan_fields(scan) -> dict:
    return {"p": _floats(scan.sensor_position), "b": [_floats(b) for b in scan.bearings],
            "c": None if scan.clutter_rates is None else [None if c is None else float(c) for c in scan.clutter_rates]}


def outputs(res) -> dict:
    """A tick's decisions, exactly: what a replay compares."""
    p = res.planning
    v_next = None
    if p is not None and p.index is not None and p.velocities is not None:
        v_next = _floats(p.velocities[p.index])
    return {"means": np.asarray(res.means, float).tolist(), "covs": np.asarray(res.covs, float).tolist(),
            "plans": [pl.status for pl in res.plans], "qp_solves": [int(pl.qp_solves) for pl in res.plans],
            "margins": [pl.margin_m for pl in res.plans],
            "next": None if res.next_position is None else _floats(res.next_position), "v_next": v_next}


def _floats(x) -> list[float]:
    return [float(v) for v in np.asarray(x, float).ravel()]
