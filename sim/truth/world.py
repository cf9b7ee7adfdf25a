"""The true targets of a simulation (eq. (1)), stepped one dt at a time.

Each target starts from x_0 ~ N(mu_0, Sigma_0) and, every step, runs its *own* guidance (Problem
P1, the same ``plan_guidance`` the UAV's predictor uses, warm-started from its previous plan) from
its TRUE state toward its goal, applies the first control and process noise nu ~ N(0, Q):

    x_t = A x_(t-1) + B u_(t-1) + nu_(t-1).

So the onboard predictor's model is right in expectation, as in the paper; mismatches a user may
want to test are explicit (``Mismatch``).

Obstacles: a target never enters one. P1 keeps the noise-free step outside the obstacles inflated
by the guidance margin, but the process noise (sigma_pos = sqrt(30) m per step in the paper) can
push the true position into an obstacle or across a corner. Such a draw is rejected and the noise
redrawn, up to ``NOISE_REDRAWS`` times; then the noise-free step is taken; and if even that would
enter (a fallback plan), the target stays where it is with zero velocity (it has hit a wall).
Rejection slightly truncates the noise near walls; that is the physics of a wall, not a model
error the filter could be blamed for. Obstacles are tested on the ground plane: each obstacle
whose height range covers the target's altitude is extruded vertically, so noise of 1e-5 m in z
does not let a target slip under a box that stands on the ground.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from onboard.core.dynamics import MotionModel
from onboard.core.guidance.predictor import (Feedback, GuidanceParams, GuidanceWorkspace, Plan, PlanAsk, Solver,
                                             plan_guidance)
from onboard.core.obstacles import Obstacles

MISMATCH_KINDS = ("stop", "turn_back", "other_goal", "resume")
BEHAVIOURS = ("guided", "stationary", "wander")
# a wandering target (``wander``): velocity kept with this factor per step plus white acceleration
# of this sigma per axis, speed capped, pushed back inward within the margin of the area's edge
WANDER_KEEP = 0.95
WANDER_ACCEL_MPS2 = 1.0
WANDER_SPEED_MPS = 6.0
WANDER_EDGE_M = 100.0
NOISE_REDRAWS = 20
_Z_TOL_M = 1.0  # a target this far below an obstacle's base still counts as at its level


@dataclass(frozen=True)
class Mismatch:
    """A deliberate departure of one true target from the predictor's model, from ``at_step`` on.

    kind:
      ``stop``       the target brakes (within its force limits) and holds the position it had at
                     ``at_step``: its guidance goal becomes that position;
      ``turn_back``  it heads back to its initial mean position mu_0;
      ``other_goal`` it heads for goal region ``goal`` (an index into ``Scenario.goals``) instead
                     of its own;
      ``resume``     it heads again for the goal it had at the start (after a ``stop``).
    target is the target's index (0-based) in ``Scenario.targets``; at_step counts steps from 0
    (the mismatch applies to the step that starts at time ``at_step * dt``).
    """

    target: int
    kind: str
    at_step: int
    goal: int | None = None

    def __post_init__(self):
        if self.kind not in MISMATCH_KINDS:
            raise ValueError(f"mismatch kind must be one of {', '.join(MISMATCH_KINDS)}, got {self.kind!r}")
        if self.at_step < 0:
            raise ValueError(f"mismatch at_step must be >= 0, got {self.at_step}")
        if self.kind == "other_goal" and self.goal is None:
            raise ValueError("mismatch kind 'other_goal' needs goal (an index into the scenario's goals)")


def blocked(obstacles: Obstacles, start: np.ndarray, end: np.ndarray) -> bool:
    """True when the ground-plane move start -> end (positions, m) ends inside or crosses an obstacle."""
    ob = obstacles.extruded(float(end[2]), _Z_TOL_M)
    if not len(ob):
        return False
    s, e = np.asarray(start, float)[:3], np.asarray(end, float)[:3]
    return bool(ob.contains(e).any() or ob.segments_cross(s, e).any())


# finite-difference steps of the closed-loop gain: position (m) and velocity (m/s)
_FD_STEP = np.array([1.0, 1.0, 0.0, 0.1, 0.1, 0.0])


def closed_loop_gain(model: MotionModel, guidance: GuidanceParams, obstacles: Obstacles, x: np.ndarray,
                     goal: np.ndarray, plan: Plan, workspace: GuidanceWorkspace | None = None) -> np.ndarray:
    """du_0/dx (3, 6) of the guidance policy at state x: the plan's own ``feedback`` when the
    guidance provides one (``plan_guidance(..., ask=PlanAsk(Feedback.ALWAYS))``, the exact gain of
    the QP with its active set held), else central finite differences of plan_guidance in the planar
    states (warm-started from ``plan``, so the same face assignment is differentiated). A fallback plan
    has no feedback: zero gain. The closed-loop transition Jacobian is A + B du_0/dx."""
    if not plan.feasible:
        return np.zeros((3, 6))
    fb = plan.feedback
    if fb is not None:
        return np.asarray(fb, float)
    K = np.zeros((3, 6))
    for i in (0, 1, 3, 4):
        e = np.zeros(6)
        e[i] = _FD_STEP[i]
        up = plan_guidance(model, guidance, obstacles, x + e, goal, previous=plan, solver=Solver(workspace))
        dn = plan_guidance(model, guidance, obstacles, x - e, goal, previous=plan, solver=Solver(workspace))
        K[:, i] = (up.next_control - dn.next_control) / (2 * e[i])
    return K


class TruthWorld:
    """True targets (M, 6) ENU [x, y, z, vx, vy, vz] in m and m/s, advanced by ``step()``."""

    def __init__(self, model: MotionModel, guidance: GuidanceParams, obstacles: Obstacles,
                 goals: np.ndarray, initial_states: np.ndarray, rng: np.random.Generator,
                 mismatch: Sequence[Mismatch] = (), goal_choices: np.ndarray | None = None,
                 behaviours: Sequence[str] | None = None, area: tuple[np.ndarray, np.ndarray] | None = None):
        """behaviours: per target, ``guided`` (P1 to its goal, the paper's), ``stationary`` (never
        moves) or ``wander`` (random acceleration within ``area`` (min, max) and out of the
        obstacles); None: all guided."""
        self.model = model
        self.guidance = guidance
        self.obstacles = obstacles
        self._goals = np.array(goals, dtype=float)  # (M, 3), updated by mismatches
        self._start_goals = self._goals.copy()
        self._states = np.array(initial_states, dtype=float)
        self._initial = self._states.copy()
        self._rng = rng
        self._goal_choices = None if goal_choices is None else np.asarray(goal_choices, float)
        M = len(self._states)
        for m in mismatch:
            if not 0 <= m.target < M:
                raise ValueError(f"mismatch target must be in [0, {M - 1}], got {m.target}")
            if m.kind == "other_goal":
                n = 0 if self._goal_choices is None else len(self._goal_choices)
                if not 0 <= m.goal < n:
                    raise ValueError(f"mismatch goal must be an index into the scenario's {n} goal(s), got {m.goal}")
        self.mismatch = tuple(mismatch)
        self.behaviours = tuple(behaviours) if behaviours is not None else ("guided",) * M
        if len(self.behaviours) != M or any(b not in BEHAVIOURS for b in self.behaviours):
            raise ValueError(f"behaviours must be {M} of {', '.join(BEHAVIOURS)}, got {self.behaviours}")
        if "stationary" in self.behaviours or "wander" in self.behaviours:
            self._states[[b != "guided" for b in self.behaviours], 3:] = 0.0  # they start at rest
        self._area = area
        self._plans: list[Plan | None] = [None] * M
        self._ws = GuidanceWorkspace()
        self.step_count = 0
        self.time_s = 0.0
        self.stuck_steps = np.zeros(M, dtype=int)  # steps a target was held at a wall (diagnostic)
        self.redraws = np.zeros(M, dtype=int)  # noise draws rejected at obstacles (diagnostic)
        self.record_gains = False  # set True to record each step's closed-loop gains (costs solves)
        self.gains: list[np.ndarray] = []  # per step, (M, 3, 6) du_0/dx of each target's guidance at its true state

    @classmethod
    def from_scenario(cls, sc, rng: np.random.Generator, mismatch: Sequence[Mismatch] = (),
                      goals: np.ndarray | None = None, behaviours: Sequence[str] | None = None) -> "TruthWorld":
        """Initial states drawn from N(mu_0, Sigma_0) per target, redrawn if one lands in an obstacle;
        ``goals`` (M, 3): where each heads instead of its scenario goal (sim/truth/kinds.py)."""
        d = sc.dynamics
        model = MotionModel.create(d.dt_s, d.friction, d.mass_kg, d.process_noise_diag)
        obstacles = Obstacles.from_boxes(sc.obstacles)
        cov = sc.initial_cov
        states = []
        for t in sc.targets:
            for _ in range(100):
                x = rng.multivariate_normal(t.mean, cov, method="cholesky")
                if not blocked(obstacles, x[:3], x[:3]):
                    break
            else:
                x = t.mean.copy()  # the config guarantees mu_0 is outside every obstacle
            states.append(x)
        if goals is None:
            goals = np.array([sc.goal_point(t) for t in sc.targets], dtype=float)
        goal_choices = np.array([g.center_m for g in sc.goals], dtype=float)
        return cls(model, GuidanceParams.from_config(sc.guidance), obstacles, goals, np.array(states), rng,
                   mismatch, goal_choices, behaviours, (np.array(sc.area.min_m), np.array(sc.area.max_m)))

    @property
    def states(self) -> np.ndarray:
        """(M, 6) true states now (a copy)."""
        return self._states.copy()

    @property
    def goals(self) -> np.ndarray:
        """(M, 3) the goal each target is heading for now (a copy)."""
        return self._goals.copy()

    @property
    def plans(self) -> tuple[Plan | None, ...]:
        """Each target's own guidance plan of the last step (None before the first)."""
        return tuple(self._plans)

    def _apply_mismatch(self) -> None:
        for m in self.mismatch:
            if m.at_step != self.step_count:
                continue
            j = m.target
            if m.kind == "stop":
                self._goals[j] = np.r_[self._states[j, :2], self._goals[j, 2]]
            elif m.kind == "turn_back":
                self._goals[j] = np.r_[self._initial[j, :2], self._goals[j, 2]]
            elif m.kind == "resume":
                self._goals[j] = self._start_goals[j]
            else:
                self._goals[j] = self._goal_choices[m.goal]
            self._plans[j] = None  # a new goal: the old plan is no warm start

    def step(self) -> np.ndarray:
        """Advance one dt; return the new (M, 6) states (a copy)."""
        self._apply_mismatch()
        A, B, q_sqrt = self.model.A, self.model.B, self.model.Q_sqrt
        new = np.empty_like(self._states)
        gains = np.zeros((len(self._states), 3, 6))
        for j, x in enumerate(self._states):
            if self.behaviours[j] != "guided":
                new[j] = x if self.behaviours[j] == "stationary" else self._wander(x)
                continue
            plan = plan_guidance(self.model, self.guidance, self.obstacles, x, self._goals[j], previous=self._plans[j],
                                 ask=PlanAsk(Feedback.ALWAYS if self.record_gains else Feedback.NONE),
                                 solver=Solver(self._ws))
            self._plans[j] = plan
            if self.record_gains:
                gains[j] = closed_loop_gain(self.model, self.guidance, self.obstacles, x, self._goals[j], plan,
                                            self._ws)
            mean = A @ x + B @ plan.next_control
            for _ in range(NOISE_REDRAWS):
                cand = mean + self._rng.standard_normal(6) * q_sqrt
                if not blocked(self.obstacles, x[:3], cand[:3]):
                    break
                self.redraws[j] += 1
            else:
                cand = mean
                if blocked(self.obstacles, x[:3], cand[:3]):
                    cand = np.r_[x[:3], 0.0, 0.0, 0.0]
                    self.stuck_steps[j] += 1
            new[j] = cand
        self._states = new
        if self.record_gains:
            self.gains.append(gains)
        self.step_count += 1
        self.time_s = self.step_count * self.model.dt_s
        return self.states

    def _wander(self, x: np.ndarray) -> np.ndarray:
        """One step of a wandering target: velocity kept by WANDER_KEEP plus white acceleration,
        pushed inward near the area's edge, speed capped; a draw that would cross an obstacle is
        redrawn (then the target stops where it is)."""
        lo, hi = self._area[0][:2], self._area[1][:2]
        push = (np.clip(lo + WANDER_EDGE_M - x[:2], 0.0, None) - np.clip(x[:2] - (hi - WANDER_EDGE_M), 0.0, None))
        for _ in range(NOISE_REDRAWS):
            v = WANDER_KEEP * x[3:5] + self.model.dt_s * (WANDER_ACCEL_MPS2 * self._rng.standard_normal(2)
                                                          + 0.02 * push)
            speed = float(np.hypot(*v))
            if speed > WANDER_SPEED_MPS:
                v *= WANDER_SPEED_MPS / speed
            p = np.clip(x[:2] + self.model.dt_s * v, lo, hi)
            cand = np.r_[p, x[2], v, 0.0]
            if not blocked(self.obstacles, x[:3], cand[:3]):
                return cand
        return np.r_[x[:3], 0.0, 0.0, 0.0]


def simulate_truth(sc, n_steps: int, rng: np.random.Generator, mismatch: Sequence[Mismatch] = (),
                   with_gains: bool = False, world: TruthWorld | None = None):
    """(n_steps + 1, M, 6) true states at t = 0, dt, ..., n_steps dt; the same as stepping a TruthWorld.
    with_gains: also (n_steps, M, 3, 6), each step's closed-loop gain du/dx at the true state
    (``closed_loop_gain``), for the posterior Cramer-Rao bound. ``world``: a world to step instead
    of the scenario's nominal one (sim/truth/kinds.py ``simulate_kind``)."""
    world = TruthWorld.from_scenario(sc, rng, mismatch) if world is None else world
    world.record_gains = with_gains
    out = [world.states]
    for _ in range(n_steps):
        out.append(world.step())
    states = np.array(out)
    if with_gains:
        return states, (np.array(world.gains) if world.gains else np.zeros((0, states.shape[1], 3, 6)))
    return states
