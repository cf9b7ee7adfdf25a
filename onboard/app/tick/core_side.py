"""The core's side of the app: the ``MonitorSetup`` built from the scenario, the PMON_*
parameters and the planner's motion limits (rebuilt when any of them changes), the core state
carried from tick to tick, and the checks on a tick's beliefs. Owned by the worker
(onboard/app/tick/worker.py); ``build_setup`` runs under the app lock."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from onboard.app.params import ParamTable
from onboard.app.autopilot.plan_limits import PlanLimits
from onboard.core.tracking import filter as tracking
from onboard.core.guidance.predictor import GuidanceWorkspace
from onboard.core.monitor import MonitorSetup, initial_state
from onboard.core.planning.inputs import CandidateGrid
from onboard.core.tracking.filter import ParticleSet


class MonitorCore:
    def __init__(self, scenario, params: ParamTable, limits: PlanLimits, rng: np.random.Generator):
        self.base_scenario = scenario
        self.params = params
        self.limits = limits
        self.rng = rng
        self.n_targets = len(scenario.targets)
        self.scenario = scenario  # with the parameters applied (build_setup)
        self.setup: MonitorSetup | None = None
        self.state = None  # onboard.core.monitor.MonitorState
        self.workspace = GuidanceWorkspace()
        self._version: tuple | int = -1
        # the parameters' values and the planner's limits the setup was built from (the run log's
        # replay record: a set arriving during a tick is not what that tick's setup holds)
        self.built_from: tuple[dict[str, float], tuple | None] = ({}, None)
        self._last_good: list[tuple[np.ndarray, np.ndarray] | None] = [None] * self.n_targets
        self.build_setup()

    def build_setup(self) -> MonitorSetup:
        """(Re)build the setup if the parameters or the planner's limits changed since; the
        beliefs carry over (resampled to a new particle count), warm starts only while the
        guidance settings stay."""
        planner = self.limits.planner
        version = (self.params.version, planner)
        if self._version == version:
            return self.setup
        values = {n: self.params[n] for n in self.params.names()}
        sc = self.params.apply(self.base_scenario)
        if sc.planning.motion == "vehicle" and planner is not None:
            speed, accel, jerk = planner
            sc = replace(sc, planning=replace(sc.planning, speed_max_mps=speed, accel_max_mps2=accel,
                                              jerk_max_mps3=jerk))
        old = self.setup
        self.setup = MonitorSetup.from_scenario(sc)
        self.scenario = sc
        if self.state is None:
            self.state = initial_state(self.setup, self.rng)
        else:
            self.state = self._carried_over(old)
        self._version = version
        self.built_from = (values, planner)
        return self.setup

    def _carried_over(self, old: MonitorSetup | None):
        n = self.setup.n_particles
        beliefs = []
        for b in self.state.beliefs:
            if len(b) != n:  # resample the current belief to the new particle count
                idx = self.rng.choice(len(b), size=n, p=b.weights / b.weights.sum())
                b = ParticleSet(b.particles[idx], np.full(n, -np.log(n)))
            beliefs.append(b)
        plans = self.state.plans
        if old is not None and old.guidance != self.setup.guidance:
            plans = (None,) * self.n_targets  # warm starts of another horizon do not fit
            self.workspace = GuidanceWorkspace()
        return type(self.state)(tuple(beliefs), plans, self.state.step)

    @property
    def version(self) -> tuple | int:
        """The version of the setup built last (the parameters' and the planner limits')."""
        return self._version

    def tick_setup(self) -> MonitorSetup:
        """(Under the lock) ``build_setup``, with the candidate grid within reach."""
        setup = self.build_setup()
        grid = self.grid_within_reach()
        return setup if grid.n_radial == setup.grid.n_radial else replace(setup, grid=grid)

    def grid_within_reach(self) -> CandidateGrid:
        """The candidate grid without the rings the vehicle cannot fly in one tick (PMON_REACH)."""
        g = self.setup.grid
        n_r = min(g.n_radial, int(math.floor(self.params.settings.app.reach_m / g.step_m + 1e-9)))
        return CandidateGrid(g.step_m, n_r, g.n_heading, g.altitude_m)

    def reseed_collapsed(self, setup: MonitorSetup, res) -> list[int]:
        """Particle collapse: a target whose update left no finite weight (``degenerate``) or
        whose belief holds a NaN/inf is re-seeded from its last good estimate, covariance
        inflated (x4 plus the initial covariance: it was lost, so be generous). Only that
        target's belief is replaced; the others are untouched. Returns the targets re-seeded.
        Worker thread."""
        out = []
        beliefs = list(self.state.beliefs)
        for j, b in enumerate(beliefs):
            bad = bool(res.degenerate[j]) or not (np.all(np.isfinite(b.particles))
                                                  and np.all(np.isfinite(b.log_weights))
                                                  and np.all(np.isfinite(res.means[j])))
            if not bad:
                self._last_good[j] = (res.means[j].copy(), res.covs[j].copy())
                continue
            mean, cov = self._last_good[j] or (setup.initial_means[j], setup.initial_cov)
            cov = 4.0 * cov + setup.initial_cov
            try:
                beliefs[j] = tracking.initialise(mean, cov, len(b.particles), self.rng)
            except np.linalg.LinAlgError:
                beliefs[j] = tracking.initialise(mean, setup.initial_cov, len(b.particles), self.rng)
            out.append(j)
        if out:
            self.state = type(self.state)(tuple(beliefs), self.state.plans, self.state.step)
        return out
