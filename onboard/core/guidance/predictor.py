"""The guidance predictor: Problem P1 solved without a mixed-integer solver.

P1 (Sec. III) is a mixed-integer QP: per horizon step and obstacle, binaries pick a face of the
cuboid that the target is outside of. Here the binaries are fixed to a *face assignment*, the
remaining convex QP is solved (DAQP, OSQP behind it), and the assignment is improved until it is
stable:

1. candidate assignments: the previous tick's shifted by one step (warm start); and, when there
   is none or it fails, the faces with the most clearance along the obstacle-free optimum and
   along copies of it pushed around each blocking obstacle on either side (homotopy classes);
2. each candidate: solve, re-pick every segment's face by largest clearance, re-solve until the
   assignment repeats;
3. local search on the best: move each face change that has an active constraint one step
   earlier or later, keep improvements, within a budget of QP solves.

Exactness is measured against an exact MIQP solve (``bench/guidance_vs_miqp.py``).

This module holds ``plan_guidance`` and the guidance's interface; by role: ``params``
(P1's settings), ``plan`` (the plan it gives), ``qp`` (the QP of one assignment), ``faces`` (assignments, their geometry and sides),
``search`` (the search, one method per phase), ``laws`` (the first control
as a map of the start state, for the tracker).

Deliberate differences from the paper's text (docs/GUIDANCE.md says why):

* Segments, not only points: the two end points of the straight segment between consecutive
  horizon points must be outside the *same* face, so the segment cannot cut a corner.
* Ground plane: with u_z = 0 the vertical state is not a decision variable, so the top/bottom
  faces' binaries are fixed by the predicted altitude; obstacles are solved as polygons of their
  four lateral faces wherever the target's altitude is within their (inflated) height.
* Cost: sum_tau q_tau ||p_tau - G_o||^2 + r sum ||u_tau - u_(tau-1)||^2 with u in kN.
  ``terminal_weight`` is the paper's term (tau = T); ``stage_weight`` adds tau < T, without
  which a receding-horizon target never arrives (the optimum reaches the goal exactly at T).
* The 2-norm speed bound is an inscribed polygon of ``speed_polygon_sides`` sides; from a state
  faster than the bound, the bound at step tau relaxes to what friction alone achieves.
* Position p_(t+1) = p_t + dt v_t does not depend on the controls, so constraints on it are
  dropped (they can only be infeasible, never helpful).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace
from enum import Enum
from typing import Callable, Sequence

import numpy as np

from onboard.core.clock_stops import deadline_of
from onboard.core.dynamics import MotionModel, predict_mean
from onboard.core.guidance.faces import NO_FACE, in_class, winding
from onboard.core.guidance.laws import FreeLaw, LocalLaw, free_law
from onboard.core.guidance.params import GuidanceParams
from onboard.core.guidance.plan import Plan
from onboard.core.guidance.qp import KN, GuidanceWorkspace
from onboard.core.guidance.search import FaceSearch, GuidanceRequest
from onboard.core.obstacles import Obstacles

# the guidance's interface, wherever its parts are held
__all__ = ["GuidanceParams", "Plan", "plan_guidance", "PlanAsk", "Solver", "Feedback", "GuidanceWorkspace",
           "LocalLaw", "FreeLaw", "free_law", "winding", "in_class", "KN"]


class Feedback(str, Enum):
    """Which plans ``plan_guidance`` gives their law: ``Plan.law`` (u_0 + du_0/dx (x - start)) and
    ``Plan.feedback`` (its gain du_0/dx).

    NONE: no plan (the open-loop plan alone). ALWAYS: every plan (the particle steering's own
    plans, the closed-loop gain of a target that steers by this guidance). CONSTRAINED: only a
    plan with an active constraint row; the free law (``free_law``) describes the others (the
    tracker's mean plans under ``plan_steering``).
    """

    NONE = "none"
    ALWAYS = "always"
    CONSTRAINED = "constrained"


@dataclass(frozen=True, eq=False)
class PlanAsk:
    """What a P1 solve is asked for beyond the cheapest plan from its start (``plan_guidance``).

    ``feedback`` (``Feedback``): which plans also get ``Plan.feedback``, the closed-loop gain
    du_0/dx (for the posterior Cramer-Rao bound of a target that steers by this guidance), and
    ``Plan.law`` (for the tracker's ``plan_steering``): none, every one, or only one with an active
    row (the free law describes the others: the tracker's mean plans); ``ahead``: with a law, the
    laws of that many controls after the first too (``Plan.ahead``, ``Plan.shifted``: the
    side-aware tracker's).
    ``sides`` (K,): the best plan that rounds no obstacle k the other way than counterclockwise
    (+1) or clockwise (-1) (0: either); ``strict_sides``: that does round each of them that way
    (``in_class``; the tracker's ``plan_sides``).
    ``nearby``: plans of this tick from nearby starts (the tracker's: a side's plan for its
    reference plans, the side modes' for the mean's), their assignments the next warm starts in
    turn; ``explore=False``: no search beyond the warm starts (no plan if they fail; the margin is
    never given up).
    """

    feedback: Feedback = Feedback.NONE
    ahead: int = 0
    sides: np.ndarray | None = None
    strict_sides: bool = False
    nearby: Plan | Sequence[Plan] | None = ()
    explore: bool = True

    def __post_init__(self):
        nearby = self.nearby
        object.__setattr__(self, "feedback", Feedback(self.feedback))
        object.__setattr__(self, "nearby", () if nearby is None else (nearby,) if isinstance(nearby, Plan)
                           else tuple(nearby))


@dataclass(frozen=True, eq=False)
class Solver:
    """What a P1 solve runs with: the QP cache (``GuidanceWorkspace``; None: a fresh one each
    solve) and the clock that the time limit (``max_solve_time_s``) and ``Plan.solve_time_s`` read."""

    workspace: GuidanceWorkspace | None = None
    timer: Callable[[], float] = time.perf_counter


def plan_guidance(model: MotionModel, params: GuidanceParams, obstacles: Obstacles, mean0: np.ndarray,
                  goal: np.ndarray, previous: Plan | None = None, ask: PlanAsk = PlanAsk(),
                  solver: Solver = Solver()) -> Plan:
    """Solve P1 for one target from state mean0 (6,) toward goal centroid (3,).

    ``previous`` (this target's plan of the last tick) warm-starts the face assignment and is the
    fallback when no feasible plan is found. ``ask`` (``PlanAsk``): the law, the sides and the warm
    starts asked for beyond the plan; ``solver`` (``Solver``): the QP cache and the clock.
    """
    timer = solver.timer
    t_start = timer()
    deadline = deadline_of(timer, params.max_solve_time_s)
    request = GuidanceRequest(model, params, obstacles, mean0, goal, previous, solver.workspace, timer, ask.sides,
                              ask.strict_sides, deadline)
    plan = _search(request, params.obstacle_margin_m, ask.feedback, ask.nearby, ask.explore, ask.ahead)
    if (plan.feasible or not ask.explore or not len(obstacles) or params.obstacle_margin_m <= 0.0
            or (deadline is not None and deadline.passed(plan.qp_solves))):
        return plan
    # noise has carried the target so close to an obstacle, or so fast toward it, that no control
    # keeps the margin: it keeps clear of the obstacle itself (the margin stays vertical, which
    # keeps ground targets level with the obstacles' bases)
    retry = _search(replace(request, solves_before=plan.qp_solves), 0.0, ask.feedback, ask.nearby, True, ask.ahead)
    return replace(retry, solve_time_s=timer() - t_start, qp_solves=plan.qp_solves + retry.qp_solves)


def _search(request: GuidanceRequest, lateral_margin_m: float, with_feedback: Feedback,
            nearby: tuple[Plan, ...] = (), explore: bool = True, ahead: int = 0) -> Plan:
    """``plan_guidance``'s search (``FaceSearch``) with the obstacles inflated by
    ``lateral_margin_m`` sideways, as a plan."""
    model, timer = request.model, request.timer
    search = FaceSearch(request, lateral_margin_m)
    search.run(request.previous, nearby, explore)
    best = search.best
    if best is None:
        return _fallback(model, request.params, search.mean0, request.previous, search.K, timer() - search.t_start,
                         search.solves)
    controls = search.controls()
    status = search.status()
    active = best.sol.active
    if with_feedback is Feedback.CONSTRAINED:
        wanted = bool(active.fixed.any() or active.obstacles.any())
    else:
        wanted = with_feedback is Feedback.ALWAYS
    means = predict_mean(model, search.mean0, controls)
    law, later = search.law(controls, means, ahead) if wanted else (None, ())
    return Plan(status, best.cost, timer() - search.t_start, search.solves, controls, means, best.faces, active, law,
                lateral_margin_m, later)


def _fallback(model, params, mean0, previous, K, elapsed, solves) -> Plan:
    T = params.horizon
    if previous is not None and previous.controls.shape == (T, 3):
        controls = np.vstack([previous.controls[1:], np.zeros((1, 3))])
        status = "fallback_previous"
    else:
        controls = np.zeros((T, 3))
        status = "fallback_coast"
    return Plan(status, float("nan"), elapsed, solves, controls, predict_mean(model, mean0, controls),
                np.full((T - 1, K), NO_FACE))
