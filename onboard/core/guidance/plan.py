"""What the guidance gives for one target (``Plan``): its controls and path, its face
assignment, the QP rows active at the solution and the laws of its controls."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from onboard.core.guidance.laws import LocalLaw
    from onboard.core.guidance.qp import ActiveRows


@dataclass(frozen=True, eq=False)
class Plan:
    """A guidance solution for one target.

    ``status``: ``optimal`` (assignment stable, local search done), ``budget`` (best found when
    the QP budget ran out), ``timeout`` (best found when ``max_solve_time_s`` ran out),
    ``fallback_previous`` (no feasible plan: the previous plan shifted by one step) or ``fallback_coast`` (no feasible plan and none before: zero control, the target
    coasting under friction). ``cost`` is P1's objective (nan for fallbacks). ``margin_m``: the
    clearance from the obstacles the plan keeps: ``obstacle_margin_m``, or 0 where noise carried the
    target too close to an obstacle, or too fast toward it, for any plan to keep the margin.
    """

    status: str
    cost: float
    solve_time_s: float
    qp_solves: int
    controls: np.ndarray  # (T, 3) N, u_(t+tau|t)
    means: np.ndarray  # (T, 6) mu_(t+tau+1|t)
    faces: np.ndarray  # (T-1, K) lateral face per segment p_s -> p_(s+1), s = 1..T-1; -1: none
    active: "ActiveRows | None" = None  # the QP rows active at the solution: next tick's warm start
    law: "LocalLaw | None" = None  # u_0 + du_0/dx (x - start) around the start (``PlanAsk.feedback``)
    margin_m: float | None = None  # m; None when not set (plans built by hand)
    # the laws of the next controls at the states the plan predicts (``shifted``; ``PlanAsk.ahead``)
    ahead: tuple[LocalLaw, ...] = ()

    def shifted(self) -> "Plan":
        """This plan one tick later, from the state it predicted (status ``shifted``): its controls
        and path from the next step on, its assignment and active rows one step on, and as its law
        the next control's (``ahead``; None when there is none). What the tracker keeps of a plan
        it did not make again this tick."""
        T = len(self.controls)
        return Plan("shifted", self.cost, 0.0, 0, np.vstack([self.controls[1:], np.zeros((1, 3))]),
                    np.vstack([self.means[1:], self.means[-1:]]), np.vstack([self.faces[1:], self.faces[-1:]]),
                    None if self.active is None else self.active.shifted(T), self.ahead[0] if self.ahead else None,
                    self.margin_m, self.ahead[1:])

    @property
    def feedback(self) -> np.ndarray | None:
        """(3, 6) du_0/dx, N per state unit (when it has a law: ``PlanAsk.feedback``), else None."""
        return None if self.law is None else self.law.gain

    @property
    def feasible(self) -> bool:
        return not self.status.startswith("fallback")

    @property
    def next_control(self) -> np.ndarray:
        return self.controls[0]

    @property
    def unconstrained(self) -> bool:
        """No row of P1 is active (no obstacle face, input or speed limit): the plan is the free
        optimum, which is affine in the state (``FreeLaw``). False when unknown."""
        return self.active is not None and not self.active.fixed.any() and not self.active.obstacles.any()

    @property
    def touches_obstacle(self) -> bool:
        """An obstacle row is active somewhere on the horizon: the plan rounds an obstacle, and a
        target could take another way around it. True when unknown (fallback plans)."""
        return self.active is None or bool(self.active.obstacles.any())
