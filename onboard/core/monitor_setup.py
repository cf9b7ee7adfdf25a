"""What is static about a mission (``MonitorSetup``), built once from a scenario: what the tick
(onboard/core/monitor.py), the choice of planner (onboard/core/planner_choice.py) and the particle
steering (onboard/core/tracking/steering.py, through ``SteeringSetup``) read."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from onboard.core.tracking import intent as intent_mod
from onboard.core.tracking import filter as tracking
from onboard.core.dynamics import MotionModel
from onboard.core.guidance.predictor import FreeLaw, GuidanceParams, free_law
from onboard.core.obstacles import Obstacles
from onboard.core.planning.inputs import CandidateGrid, LookaheadParams, UavMotion
from onboard.core.tracking.steering_setup import PlanSteering


@dataclass(frozen=True, eq=False)
class MonitorSetup:
    """Everything static about a mission, built once from a scenario (``from_scenario``: every
    value from it; onboard/settings/sections.py declares the defaults, so none here)."""

    model: MotionModel
    sensor: tracking.SensorModel
    guidance: GuidanceParams
    obstacles: Obstacles  # as built; the guidance inflates by its own margin
    uav_obstacles: Obstacles  # inflated by the UAV's clearance margin
    goals: np.ndarray  # (M, 3) goal centroid per target
    initial_means: np.ndarray  # (M, 6)
    initial_cov: np.ndarray  # (6, 6)
    grid: CandidateGrid
    area_min: np.ndarray
    area_max: np.ndarray
    n_particles: int
    resample_fraction: float
    objective: str
    control_mix: float  # fraction of particles predicted with a random control
    regularise_bandwidth: float  # h of the regularised resampling (tracking.resample_if_needed)
    free_steering: FreeLaw | None  # particles whose own plan is the free optimum steer by it
    plan_steering: PlanSteering | None  # the others, while the plan is constrained, by reference plans
    recovery: tracking.Recovery | None  # a lost target found again along the bearings (tracking.recover)
    # per target, its candidate goals and mode prior (onboard/core/tracking/intent.py), and how modes move;
    # None: the paper's filter, every particle heading for ``goals``
    intents: tuple[intent_mod.Intent, ...] | None
    intent: intent_mod.IntentParams | None
    ground_obstacles: Obstacles  # the obstacles a ground target meets (``Obstacles.extruded`` at 0 m)
    planner: str  # greedy | lookahead
    lookahead_steps: int
    motion: UavMotion
    lookahead: LookaheadParams
    # the planner and the particle steering the configuration chooses, built once per setup by
    # onboard/core/monitor.py (``uav_planner``, ``particle_steering``): derived, not settings
    parts: dict = field(default_factory=dict, init=False, repr=False)

    @classmethod
    def from_scenario(cls, sc) -> "MonitorSetup":
        """From a scenario; to change a setting, change the scenario (``onboard.config.override``)."""
        obstacles = Obstacles.from_boxes(sc.obstacles)
        d = sc.dynamics
        model = MotionModel.create(d.dt_s, d.friction, d.mass_kg, d.process_noise_diag)
        return cls(
            model=model,
            sensor=tracking.SensorModel.from_config(sc.sensor),
            guidance=GuidanceParams.from_config(sc.guidance),
            obstacles=obstacles,
            uav_obstacles=obstacles.inflate(sc.uav.obstacle_margin_m),
            goals=np.array([sc.goal_point(t) for t in sc.targets], dtype=float),
            initial_means=np.array([t.mean for t in sc.targets]),
            initial_cov=sc.initial_cov,
            grid=CandidateGrid.from_config(sc.uav),
            area_min=np.array(sc.area.min_m), area_max=np.array(sc.area.max_m),
            n_particles=sc.tracking.particles,
            resample_fraction=sc.tracking.resample_ess_fraction,
            control_mix=sc.tracking.control_mix,
            regularise_bandwidth=sc.tracking.regularise_bandwidth,
            free_steering=free_law(model, GuidanceParams.from_config(sc.guidance)),
            plan_steering=PlanSteering.from_config(sc.tracking),
            recovery=tracking.Recovery.from_config(sc.tracking),
            intents=target_intents(sc) if sc.tracking.intent else None,
            intent=intent_params(sc) if sc.tracking.intent else None,
            ground_obstacles=obstacles.extruded(0.0),
            objective=sc.planning.objective,
            planner=sc.planning.planner,
            lookahead_steps=sc.planning.lookahead_steps,
            motion=UavMotion.from_config(sc.planning),
            lookahead=LookaheadParams.from_config(sc.planning.lookahead),
        )

    @property
    def n_targets(self) -> int:
        return len(self.goals)


STATIONARY_DECLARED = 0.8  # the stationary prior of a target the scenario says stands still
UNKNOWN_STATIONARY = 0.5  # ... of a target whose goal is not known: standing or moving, even odds


def target_intents(sc) -> tuple[intent_mod.Intent, ...]:
    """Per target, what the scenario says it may do (``Target.goal``, ``goals``, ``stationary``)
    as candidate goals and a mode prior: a declared stationary target 0.8 stationary; with
    candidate goals, ``intent_stationary_prior`` and ``intent_free_prior`` (shared by FREE and
    AIMED), the rest shared evenly by the goals; with none, stationary or moving at even odds."""
    tr = sc.tracking
    out = []
    for t in sc.targets:
        names = t.candidates
        goals = np.array([sc.goal_named(n).center_m for n in names], dtype=float).reshape(-1, 3)
        if names:
            p_stat = STATIONARY_DECLARED if t.stationary else tr.intent_stationary_prior
            p_free = min(tr.intent_free_prior, 1.0 - p_stat)
        else:
            p_stat = STATIONARY_DECLARED if t.stationary else UNKNOWN_STATIONARY
            p_free = 1.0 - p_stat
        rest = max(0.0, 1.0 - p_stat - p_free)
        # moving without a named goal: wandering (FREE) or heading somewhere (AIMED), even odds
        prior = np.r_[np.full(len(names), rest / len(names)) if names else [], p_stat, p_free / 2, p_free / 2]
        out.append(intent_mod.Intent(goals, names, prior / prior.sum()))
    return tuple(out)


def intent_params(sc) -> intent_mod.IntentParams:
    tr = sc.tracking
    return intent_mod.IntentParams(tr.intent_switch_prob, tr.intent_free_accel_mps2, sc.guidance.speed_max_mps,
                                   intent_mod.STATIONARY_SIGMA_M, tr.intent_recovery_prior, tr.intent_recovery_sigma_m,
                                   tr.intent_start_speed_mps, tr.intent_goal_switch_share)
