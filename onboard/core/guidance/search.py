"""The face-assignment search of P1 from one start (docs/GUIDANCE.md, "The assignment search").

``FaceSearch`` holds the state every phase shares (the QP, the obstacles' geometry, the budget
spent, the assignments tried, every feasible one found and the best) and has one method per
phase, run in this order by ``run``:

1. ``warm_start``: last tick's assignment shifted by one step, refined. A warm plan with no
   obstacle row active solves a relaxation of every assignment, so it is globally optimal.
2. ``explore`` (no warm plan): assignments timed along the shortest path around the obstacles,
   from the obstacle-free optimum and copies of it pushed round the blocking obstacles on either
   side, and holding back; each refined; then ``local_search`` over the face switch times.
   ``unstick`` (a warm plan pressed against a face and crawling, a local optimum) is the light
   version: the shortest path at one speed and holding back.
3. ``refine`` (used by the phases): solve, re-pick faces by clearance, until the assignment
   repeats.

Every phase spends from one budget, ``max_qp_solves`` QP solves (and the solve's deadline,
``max_solve_time_s``, when set: onboard/core/clock_stops.py), and keeps the cheapest feasible plan that lies in the asked-for class of sides.
"""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Iterator

import numpy as np

from onboard.core.clock_stops import Deadline
from onboard.core.dynamics import MotionModel, predict_mean
from onboard.core.guidance.faces import (FEAS_TOL_M, NO_FACE, face_geometry, in_class, shift_switches,
                                         timed_path, winding, _opposite)
from onboard.core.guidance.laws import LocalLaw, first_control_gain, later_gains
from onboard.core.guidance.qp import KN, GuidanceWorkspace, QPSolution, controls_kn, integrate, speed_bound_mps
from onboard.core.obstacles import Obstacles

if TYPE_CHECKING:
    from onboard.core.guidance.params import GuidanceParams
    from onboard.core.guidance.plan import Plan

_STALL_SPEED_FRACTION = 0.25  # a warm plan against an obstacle this slow (of v_max) is stuck
_SWITCH_MOVES = (1, -1, 2, -2, 3, -3)  # local search: steps by which a face switch is moved
_GUIDE_SPEEDS = (0.8, 1.0, 0.6)  # fractions of v_max at which the shortest path is timed
_LOCAL_SEARCH_STARTS = 3  # local search from this many of the cheapest assignments found
_PAIR_MOVES = 4  # when no single move improves, pairs of this many cheapest ones are tried


@dataclass(frozen=True, eq=False)
class GuidanceRequest:
    """One P1 solve's inputs (``plan_guidance``'s): the dynamics and P1's settings, the
    obstacles, the start state (6,) and the goal centroid (3,), the warm start (last tick's plan,
    or None), the QP cache (None: a fresh one), the clock, and the sides to hold to (``sides``
    (K,), or None; ``strict_sides``: round each that way)."""

    model: MotionModel
    params: GuidanceParams
    obstacles: Obstacles
    mean0: np.ndarray
    goal: np.ndarray
    previous: Plan | None = None
    workspace: GuidanceWorkspace | None = None
    timer: Callable[[], float] = time.perf_counter
    sides: np.ndarray | None = None
    strict_sides: bool = False
    deadline: Deadline | None = None  # the solve's time limit (None: none)
    solves_before: int = 0  # QP solves the solve spent before this search (its deadline counts them)


@dataclass(frozen=True, eq=False)
class Found:
    """A feasible assignment in the asked-for class: P1's cost, the faces (T-1, K), the path
    p_1..p_(T+1) (T+1, 2) as the dynamics fly it, and the QP's solution."""

    cost: float
    faces: np.ndarray
    pts: np.ndarray
    sol: QPSolution


class FaceSearch:
    """P1's search over face assignments from one start; ``run`` it, then read ``best``."""

    def __init__(self, request: GuidanceRequest, lateral_margin_m: float):
        """The search for ``request`` with the obstacles inflated by ``lateral_margin_m`` sideways."""
        model, params, obstacles, timer = request.model, request.params, request.obstacles, request.timer
        mean0, goal, previous, workspace = request.mean0, request.goal, request.previous, request.workspace
        self.t_start = timer()
        self.model, self.params, self.timer = model, params, timer
        self.sides, self.strict_sides = request.sides, request.strict_sides
        self.T, self.K = T, K = params.horizon, len(obstacles)
        mean0 = np.asarray(mean0, dtype=float)
        self.goal2 = np.asarray(goal, dtype=float)[:2]
        ws = workspace or GuidanceWorkspace()
        self.qp = ws.qp(T, K, model, params)
        self.decay, self.gain = 1.0 - model.friction, self.qp.gain
        self.solves = 0
        x0 = mean0[[0, 1, 3, 4]]
        z = np.concatenate([[mean0[2]], predict_mean(model, mean0, np.zeros((T, 3)))[:, 2]])
        self.geo = ws.geometry((obstacles, params.obstacle_margin_m, lateral_margin_m, z.tobytes()),
                               lambda: face_geometry(obstacles, params.obstacle_margin_m, z, lateral_margin_m))
        # a start inside an inflated obstacle (noise carried the target into the margin, or an
        # estimate averages particles on both sides of an obstacle) has no feasible plan: plan from
        # the nearest point just outside, not moving into the obstacle
        out = self.geo.push_out(x0, self.geo.relevant[0]) if K else None
        if out is not None:
            mean0 = mean0.copy()
            mean0[[0, 1, 3, 4]] = x0 = out
        self.mean0, self.x0 = mean0, x0  # the start planned from (pushed out when it was inside)
        v0 = float(np.linalg.norm(x0[2:]))
        self.speed_bound = np.maximum(speed_bound_mps(params), v0 * self.decay ** np.arange(1, T + 1) + 1e-6)
        self.best: Found | None = None
        self.tried: set[bytes] = set()
        self.found: list[tuple[float, np.ndarray, np.ndarray]] = []  # every feasible (cost, faces, path)
        self.warm: tuple[np.ndarray, np.ndarray] | None = None  # last tick's assignment shifted, and its path
        # first working set of the QP: last tick's active rows shifted, then each solve's own
        self.hint = (previous.active.shifted(T) if previous is not None and previous.active is not None
                     and previous.faces.shape == (T - 1, K) else None)
        self.deadline, self.solves_before = request.deadline, request.solves_before

    # ------------------------------------------------------------------ the budget

    def timed_out(self) -> bool:
        return self.deadline is not None and self.deadline.passed(self.solves_before + self.solves)

    def budget_left(self) -> bool:
        return self.solves < self.params.max_qp_solves and not self.timed_out()

    def status(self) -> str:
        """``optimal`` (the search ended on its own), ``timeout`` or ``budget``."""
        return "optimal" if self.budget_left() else ("timeout" if self.timed_out() else "budget")

    # ------------------------------------------------------------------ one assignment

    def path(self, pts: np.ndarray) -> np.ndarray:
        """p_0..p_T from a QP's p_1..p_(T+1)."""
        return np.vstack([self.x0[:2], pts[:self.T]])

    def cost(self, pts: np.ndarray) -> float:
        w = controls_kn(self.x0, pts, self.model.dt_s, self.decay, self.gain)
        d2 = np.sum((pts[:self.T] - self.goal2) ** 2, axis=1)
        return float(self.qp.goal_weights @ d2 + self.params.smooth_weight * np.sum(np.diff(w, axis=0) ** 2))

    def solve(self, faces: np.ndarray, soft: bool = False) -> QPSolution | None:
        self.solves += 1
        out = self.qp.solve(self.x0, self.goal2, self.speed_bound, *self.geo.rows(faces), soft=soft, hint=self.hint)
        if out is not None:
            self.hint = out.active
        return out

    def evaluate(self, faces: np.ndarray) -> QPSolution | None:
        """Hard solve of an assignment; keep the best. Returns the result or None.

        The solution is re-integrated from its controls clipped to the input box, and checked
        again: what is kept is exactly what the dynamics do, within every bound.
        """
        self.tried.add(faces.tobytes())
        out = self.solve(faces)
        if out is None or out.violation > FEAS_TOL_M:
            return None
        dt, u_max = self.model.dt_s, self.params.u_max_n / KN
        w = np.clip(controls_kn(self.x0, out.pts, dt, self.decay, self.gain), -u_max, u_max)
        pts = integrate(self.x0, w, dt, self.decay, self.gain)
        if self.geo.violation(faces, self.path(pts)) > FEAS_TOL_M:
            return None
        # the speed rows the QP imposed, the polygon of apothem speed_bound: its corners lie
        # outside a circle of that radius, which a 2-norm check would reject whenever the bound
        # is relaxed above speed_max's (a target faster than speed_max / (1 - friction))
        vel = np.diff(pts, axis=0) / dt
        if np.any(vel @ self.qp.speed_normals.T > self.speed_bound[:, None] + 1e-3):
            return None
        c = self.cost(pts)
        if not in_class(faces, self.sides, self.strict_sides):
            return out  # its path still guides the re-pick
        self.found.append((c, faces, pts))
        best_cost = np.inf if self.best is None else self.best.cost
        if c < best_cost - 1e-9 * max(1.0, abs(c)):
            self.best = Found(c, faces, pts, out)
        return out

    def refine(self, faces: np.ndarray) -> None:
        """Solve, re-pick faces by clearance, repeat until the assignment repeats.

        An infeasible assignment is solved once more with slack: its path shows where the
        faces should change, which the re-pick then reads.
        """
        while self.budget_left():
            out = self.evaluate(faces)
            feasible = out is not None
            if not feasible:
                if self.K == 0 or not self.budget_left():
                    return
                out = self.solve(faces, soft=True)
                if out is None:
                    return
            pts = self.path(out.pts)
            nxt = self.geo.repick(pts)
            if nxt.tobytes() in self.tried or (feasible and self.geo.same_optimum(faces, nxt, pts, out.duals)):
                return
            faces = nxt

    def refine_new(self, faces: np.ndarray) -> None:
        """``refine`` an assignment not tried yet, while the budget lasts."""
        if faces.tobytes() not in self.tried and self.budget_left():
            self.refine(faces)

    def hold_assignment(self) -> np.ndarray:
        """Every obstacle kept, for every segment, on the face p_1 is outside of: the target
        does not pass any obstacle within the horizon."""
        T, K = self.T, self.K
        still = np.tile(self.x0[:2] + self.model.dt_s * self.x0[2:], (T + 1, 1))
        return self.geo.sanitise(np.broadcast_to(self.geo.repick(still)[:1], (T - 1, K)).copy(), still)

    # ------------------------------------------------------------------ the phases

    def run(self, previous: Plan | None, nearby: tuple[Plan, ...] = (), explore: bool = True) -> None:
        """The phases in order: the warm starts (``previous`` shifted, then each of ``nearby`` as it
        is, until one gives a plan); a stalled warm plan is unstuck; without a warm plan, ``explore``
        and the local search (``explore=False``: none, the search ends without a plan)."""
        if self.K == 0:
            self.evaluate(np.full((self.T - 1, 0), NO_FACE))
            return
        if self.warm_start(previous) or any(self.warm_start(p, shift=False) for p in nearby):
            if explore and self.no_progress(previous):
                self.explore()
                self.local_search()
            elif self.stalled():
                self.unstick()
            return
        if explore:
            self.repair()
            self.explore()
            self.local_search()

    def warm_start(self, previous: Plan | None, shift: bool = True) -> bool:
        """The previous plan's assignment, shifted by one step (``shift``: last tick's plan; else
        a plan of this tick from a nearby start, as it is), refined; True if a feasible plan in
        the class is found."""
        T, K = self.T, self.K
        if previous is None or not previous.feasible or previous.faces.shape != (T - 1, K):
            return False
        if shift:
            faces, path = self.shifted(previous)
            self.warm = (faces, path)
        else:
            path = np.vstack([self.x0[:2], previous.means[:, :2]])
            faces = self.geo.sanitise(previous.faces, path)
        self.refine(faces)
        return self.best is not None

    def shifted(self, previous: Plan) -> tuple[np.ndarray, np.ndarray]:
        """Last tick's assignment shifted by one step (its last row repeated), made consistent with
        its path from this tick's start (``sanitise``), and that path."""
        path = np.vstack([self.x0[:2], previous.means[1:, :2], previous.means[-1:, :2]])
        return self.geo.sanitise(np.vstack([previous.faces[1:], previous.faces[-1:]]), path), path

    def repair(self) -> None:
        """The previous plan's assignment shifted, when infeasible, with each face switch moved one to
        three steps (``neighbours``): a target pressed against a face near a corner can round it a
        step later than the shift says, and the re-pick by clearance, timing the corner too early
        again, and the target holds back in front of the obstacle at a much higher cost
        (docs/GUIDANCE.md, "Cost jumps near corners"). The feasible ones join the local search's
        starts."""
        if self.warm is None:
            return
        faces, path = self.warm
        for f in self.neighbours(faces, path):
            if f.tobytes() not in self.tried and self.budget_left():
                self.evaluate(f)

    def stalled(self) -> bool:
        """The warm plan is stuck: an obstacle row is active and the target is planned to crawl
        (under a quarter of v_max) at its first step. A shifted assignment can hold a target
        pressed against a face, a local optimum."""
        b = self.best
        pressed = bool(np.any(b.sol.duals != 0.0))
        first_speed = float(np.linalg.norm(b.pts[1] - b.pts[0])) / self.model.dt_s
        return pressed and first_speed < _STALL_SPEED_FRACTION * self.params.speed_max_mps

    def no_progress(self, previous: Plan | None) -> bool:
        """The warm plan holds the target back: it is pressed against an obstacle (a row active)
        that it does not round (winding 0), and costs no less than ``previous`` (last tick's plan)
        did: a local optimum that the warm start alone would keep, at several times the cost of
        rounding the obstacle (docs/GUIDANCE.md, "Cost jumps near corners"). Explored as without a
        warm start. Not every pressed plan whose cost has not fallen: that costs the flight tick
        too much (docs/LOG.md)."""
        b = self.best
        if previous is None or not b.cost >= previous.cost:  # False for a fallback's nan cost
            return False
        pressed = np.any(b.sol.duals != 0.0, axis=(1, 2))  # (K,)
        return bool(np.any(pressed & (winding(b.faces) == 0)))

    def follow_guides(self, thorough: bool) -> None:
        """Assignments along the shortest path around the obstacles timed at cruise speeds
        (``thorough``: three speeds, and first the class's own shortest path when sides are
        asked for; else one speed)."""
        if not self.budget_left():
            return
        x0, dt = self.x0, self.model.dt_s
        start = x0[:2] + dt * x0[2:]
        guides = [self.geo.guide_path(start, self.goal2)]
        if self.sides is not None and thorough:  # the class's own shortest path first
            guides.insert(0, self.geo.guide_path_around(start, self.goal2, self.sides))
        for guide in guides:
            if guide is None:
                continue
            for speed in _GUIDE_SPEEDS if thorough else _GUIDE_SPEEDS[:1]:
                self.refine_new(self.geo.repick(timed_path(guide, x0[:2], speed * self.params.speed_max_mps * dt,
                                                           self.T)))

    def explore(self) -> None:
        """A plan from scratch: the guides; the obstacle-free optimum, and copies of it pushed
        around the blocking obstacles on either side (the shortest path can be the dearer side
        given the initial velocity); holding back, alone and for each obstacle of the best."""
        self.follow_guides(thorough=True)
        if not self.budget_left():
            return
        free = self.solve(np.full((self.T - 1, self.K), NO_FACE))
        if free is not None:
            ref = self.path(free.pts)
            variants = [ref]
            blocking = self.geo.blocking(ref)[:3]
            for way in itertools.product((1.0, -1.0), repeat=len(blocking)):
                pts = ref
                for k, side in zip(blocking, way):
                    pts = self.geo.push_around(pts, k, side)
                variants.append(pts)
            for pts in variants:
                self.refine_new(self.geo.repick(pts))
        hold = self.hold_assignment()
        holds = [hold]
        if self.best is not None:
            for k in range(self.K):
                f = self.best.faces.copy()
                f[:, k] = np.where(f[:, k] >= 0, hold[:, k], f[:, k])
                holds.append(self.geo.sanitise(f, self.path(self.best.pts)))
        for faces in holds:
            self.refine_new(faces)

    def unstick(self) -> None:
        """A stalled warm plan's light search: the shortest path at one speed, holding back."""
        self.follow_guides(thorough=False)
        if self.budget_left():
            hold = self.hold_assignment()
            if hold.tobytes() not in self.tried:
                self.refine(hold)

    def local_search(self) -> None:
        """Move each face switch one to three steps either way (the switch between two faces
        happens where the path rounds a corner; its best step is what the re-pick by clearance
        guesses least well), and all switches together; descend while it improves. From the
        best few assignments found, not only the best: the cheapest homotopy class can start out
        dearer before its switch times are right."""
        starts, seen = [], set()
        for c, faces, pts in sorted(self.found, key=lambda x: x[0]):
            if faces.tobytes() not in seen:
                seen.add(faces.tobytes())
                starts.append((c, faces, pts))
        for c, faces, pts in starts[:_LOCAL_SEARCH_STARTS]:
            self.descend(c, faces, pts)

    def neighbours(self, faces0: np.ndarray, pts0: np.ndarray) -> Iterator[np.ndarray]:
        """Assignments with one face switch moved by each of ``_SWITCH_MOVES``, then with every
        switch moved together."""
        change = (faces0[1:] != faces0[:-1]) & (faces0[1:] >= 0) & (faces0[:-1] >= 0)
        for s, k in zip(*np.nonzero(change)):
            s += 1  # the face changes between segments s-1 and s
            before, after = faces0[s - 1, k], faces0[s, k]
            for d in _SWITCH_MOVES:
                f = faces0.copy()
                # past either end of the horizon the switch disappears
                seg = np.arange(s, min(s + d, len(f))) if d > 0 else np.arange(max(s + d, 0), s)
                if np.any(f[seg, k] != (after if d > 0 else before)):
                    continue  # runs into another switch
                f[seg, k] = before if d > 0 else after
                if not _opposite(f[1:, k], f[:-1, k]).any():
                    yield f
        for d in _SWITCH_MOVES:
            f = shift_switches(faces0, d)
            if f is not None:
                yield self.geo.sanitise(f, self.path(pts0))

    def descend(self, c: float, faces: np.ndarray, pts: np.ndarray) -> None:
        """Steepest descent over ``neighbours`` from one assignment."""
        while self.budget_left():
            n_found = len(self.found)
            for f in self.neighbours(faces, pts):
                if f.tobytes() not in self.tried and self.budget_left():
                    self.evaluate(f)
            better = [x for x in self.found[n_found:] if x[0] < c - 1e-9 * max(1.0, abs(c))]
            if not better:
                # switch times interact (rounding one corner later can pay only if the next
                # switch goes too): combine pairs of the cheapest feasible single moves
                near = sorted(self.found[n_found:], key=lambda x: x[0])[:_PAIR_MOVES]
                for (_, f1, _), (_, f2, _) in itertools.combinations(near, 2):
                    d1, d2 = f1 != faces, f2 != faces
                    if np.any(d1 & d2):
                        continue
                    f = np.where(d1, f1, np.where(d2, f2, faces))
                    if f.tobytes() not in self.tried and self.budget_left():
                        self.evaluate(f)
                better = [x for x in self.found[n_found:] if x[0] < c - 1e-9 * max(1.0, abs(c))]
                if not better:
                    return
            c, faces, pts = min(better, key=lambda x: x[0])

    # ------------------------------------------------------------------ the result

    def controls(self) -> np.ndarray:
        """(T, 3) the best plan's controls, N."""
        controls = np.zeros((self.T, 3))
        controls[:, :2] = controls_kn(self.x0, self.best.pts, self.model.dt_s, self.decay, self.gain) * KN
        return controls

    def law(self, controls: np.ndarray, means: np.ndarray, ahead: int = 0) -> tuple[LocalLaw | None, tuple]:
        """The closed-loop gain du_0/dx of the best plan: the optimum is affine in the state while
        its active set holds, so a nearby state would be steered by u_0 + K dx (about 1 ms); and
        the laws of its next ``ahead`` controls at the states it predicts (``later_gains``)."""
        sol = self.best.sol
        if not np.all(np.isfinite(sol.y)):
            return None, ()
        try:
            dP = self.qp.sensitivity(self.x0, self.goal2, self.speed_bound, *self.geo.rows(self.best.faces), sol)
        except np.linalg.LinAlgError:
            dP = np.full((self.T, 2, 4), np.nan)
        feedback = first_control_gain(dP, self.model, self.decay, self.gain)
        if feedback is None:
            return None, ()
        later = later_gains(dP, self.model, self.decay, self.gain, ahead) if ahead else []
        return (LocalLaw(self.x0.copy(), controls[0].copy(), feedback),
                tuple(LocalLaw(means[k - 1][[0, 1, 3, 4]].copy(), controls[k].copy(), g)
                      for k, g in enumerate(later, start=1)))
