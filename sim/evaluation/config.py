"""The evaluation's configuration (sim.evaluation.trials): which scenario, trials, seed and methods, the
ticks and the convergence window, validated (``make_config``); a method by name, with the autopilot
parameters it flies (``method_named``); and each method's monitor, DF and vehicle limits."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np

from onboard.config import ConfigError, override
from onboard.core.monitor import MonitorSetup
from onboard.policy import vehicle_motion
from sim.evaluation.baselines import ORBIT_RADIUS_M, orbit_centre
from sim.evaluation.methods import AUTOPILOTS, DEFAULT_METHODS, METHODS, Method, method_scenario
from sim.mock.multicopter import VehicleLimits, limits_from_params
from sim.truth.sensors import DirectionFinder
from sim.truth.kinds import check_kind, filter_scenario

DEFAULT_WINDOW_S = 10.0  # convergence window: metrics are time-averaged from this time on


@dataclass(frozen=True, eq=False)
class EvalConfig:
    scenario: Any  # onboard.config.Scenario
    n_trials: int
    seed: int
    methods: tuple[Method, ...]
    n_ticks: int
    window_start: int  # first tick of the convergence window
    truth_kind: str = "nominal"  # how the true targets move (sim/truth/kinds.py)
    told: bool = False  # the filter is told each trial what its targets really do (truth_kinds.filter_scenario)

    @property
    def method_names(self) -> tuple[str, ...]:
        return tuple(m.name for m in self.methods)

    @property
    def orbit_radius_m(self) -> float:
        """The orbit baseline's radius (``sim.evaluation.baselines.OrbitPlanner``), m."""
        return ORBIT_RADIUS_M

    @property
    def orbit_center(self) -> np.ndarray:
        """The orbit baseline's centre, the targets' initial centroid (ENU m, planar)."""
        return orbit_centre(MonitorSetup.from_scenario(self.scenario))

    @property
    def dt_s(self) -> float:
        return self.scenario.dynamics.dt_s


def make_config(sc, n_trials: int, seed: int, methods: Sequence[str] = DEFAULT_METHODS,
                duration_s: float | None = None, particles: int | None = None,
                window_s: float = DEFAULT_WINDOW_S, truth: str = "nominal", told: bool = False) -> EvalConfig:
    """Validated configuration. Raises ValueError with a one-line reason."""
    check_kind(sc, truth)
    if told and truth not in ("candidate_goal", "stationary"):
        raise ValueError(f"--told applies to --truth candidate_goal or stationary, not {truth}")
    sc = filter_scenario(sc, truth)
    if n_trials < 1:
        raise ValueError(f"--trials must be >= 1, got {n_trials}")
    if seed < 0:
        raise ValueError(f"--seed must be >= 0, got {seed}")
    names = list(methods)
    if not names:
        raise ValueError("--methods is empty")
    unknown = [m for m in names if m.partition("@")[0] not in METHODS]
    if unknown:
        raise ValueError(f"unknown method {unknown[0]!r} (known: {', '.join(METHODS)}; a vehicle method "
                         f"takes @{'|@'.join(AUTOPILOTS)})")
    if len(set(names)) != len(names):
        raise ValueError("--methods names a method twice")
    chosen = tuple(method_named(m, sc) for m in names)
    for option, key, value in (("--duration", "mission.duration_s", duration_s),
                               ("--particles", "tracking.particles", particles)):
        if value is not None:  # a setting of every method's scenario, checked as a file is
            try:
                sc = override(sc, {key: value})
            except ConfigError as exc:
                raise ValueError(f"{option} {value}: {exc}") from None
    for m in chosen:
        try:
            method_scenario(sc, m)
        except ConfigError as exc:
            raise ValueError(f"method {m.name}: {exc}") from None
    dt = sc.dynamics.dt_s
    duration = sc.mission.duration_s
    if not duration >= 2 * dt:
        raise ValueError(f"--duration must be at least 2 time steps ({2 * dt:g} s), got {duration_s}")
    n_ticks = int(round(duration / dt))
    # the window starts at window_s, or halfway when the mission is too short for that
    window_start = min(int(round(window_s / dt)), n_ticks // 2)
    return EvalConfig(sc, int(n_trials), int(seed), chosen, n_ticks, window_start, truth, told)


def method_named(name: str, sc=None) -> Method:
    """A registered method by name; ``NAME@LABEL`` is that method flown with the autopilot
    parameters ``AUTOPILOTS[LABEL]`` (a method of its own name, seeds and all). ValueError for
    a label on a method that flies no vehicle (under the scenario ``sc``, when given)."""
    base, at, label = name.partition("@")
    m = METHODS[base]
    if not at:
        return m
    if label not in AUTOPILOTS:
        raise ValueError(f"method {name!r}: unknown autopilot parameters {label!r} (one of {', '.join(AUTOPILOTS)})")
    try:  # its motion under its policy (a paper method's: the paper's jump)
        motion = m.motion or (None if sc is None else method_scenario(sc, m).planning.motion)
    except ConfigError as exc:
        raise ValueError(f"method {base}: {exc}") from None
    if m.sensing != "uav" or motion == "jump":
        raise ValueError(f"method {name!r}: {base} flies no vehicle (only vehicle-motion methods take @{label})")
    return replace(m, name=name, autopilot=label, description=f"{m.description}; autopilot: {label}")


def _setup_for(cfg: EvalConfig, method: Method) -> tuple[MonitorSetup, DirectionFinder | None, VehicleLimits | None]:
    """The method's monitor, its DF (None: fixed sensors) and, for a flown method, the vehicle's
    limits from its autopilot's parameters."""
    sc = method_scenario(cfg.scenario, method)
    flown = method.sensing != "fixed" and sc.planning.motion == "vehicle"  # the ceiling: its vehicle's limits
    limits = limits_from_params(AUTOPILOTS[method.autopilot or "stock"]) if flown else None
    if limits is not None and method.autopilot_limits:
        # PX4's OFFBOARD shapes no jerk (onboard/app/autopilot/profiles.py Px4): the scenario's stays
        jerk = limits.jerk_xy_max() if limits.shaping else math.inf
        m = vehicle_motion(sc.planning, limits.speed_xy, limits.accel_xy, jerk)
        sc = override(sc, {"planning.speed_max_mps": m.speed_max_mps, "planning.accel_max_mps2": m.accel_max_mps2,
                           "planning.jerk_max_mps3": m.jerk_max_mps3})
    df = None if method.sensing != "uav" else DirectionFinder.from_config(sc.sensor)
    setup = MonitorSetup.from_scenario(sc)
    if method.planner is not None and method.planner != setup.planner:
        # a baseline or a bench's planner, registered in PLANNERS (not one the flight app may be configured with)
        setup = replace(setup, planner=method.planner)
    return setup, df, limits
