"""How the true targets move in an evaluation (``pmon eval --truth KIND``), beyond the model the
scenario states: truths the filter's model did not write.

Every kind starts from the nominal truth's initial states (drawn first, from the same stream) and
takes its own choices from a separate stream (``kind_rng``), so a trial of any kind is paired with
the nominal trial of the same number: same starts, same UAV start, same DF draws where the
targets are where the nominal ones are. A kind is scenario-independent:

* ``nominal``        each target heads for its scenario goal with P1 (the paper's model);
* ``candidate_goal`` each heads for one of the scenario's goal regions, drawn uniformly (the
                     scenario must declare at least three);
* ``unknown_goal``   each heads for a point nobody named: uniform in the area 50 m in from its
                     edge, outside the obstacles, at least 200 m from every goal region's centre
                     and 300 m from its start;
* ``stationary``     each stands where it starts (the transmitter hunt);
* ``stop_turn``      each heads for its goal and either stops for 20 s at a time drawn in the
                     first half of the mission then goes on, or turns back to its start half-way;
* ``wander``         each wanders: random acceleration, in the area and out of the obstacles.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from onboard.core.obstacles import Obstacles
from sim.truth.world import Mismatch, TruthWorld, blocked, simulate_truth

TRUTH_KINDS = ("nominal", "candidate_goal", "unknown_goal", "stationary", "stop_turn", "wander")
MIN_CANDIDATES = 3
STOP_S = 20.0
UNKNOWN_EDGE_M = 50.0
UNKNOWN_FROM_GOALS_M = 200.0
UNKNOWN_FROM_START_M = 300.0


@dataclass(frozen=True)
class KindDraw:
    """What a kind drew for one trial, per target: where it heads (None: its scenario goal), the
    name of the goal region it heads for (None: none named), its behaviour, and its events."""

    goals: tuple[tuple[float, float, float] | None, ...]
    goal_names: tuple[str | None, ...]
    behaviours: tuple[str, ...]
    mismatch: tuple[Mismatch, ...]


def check_kind(sc, kind: str) -> None:
    """ValueError (one line) when ``kind`` is unknown or the scenario cannot host it."""
    if kind not in TRUTH_KINDS:
        raise ValueError(f"--truth must be one of {', '.join(TRUTH_KINDS)}, got {kind!r}")
    if kind == "candidate_goal" and len(sc.goals) < MIN_CANDIDATES:
        raise ValueError(f"--truth candidate_goal needs a scenario with at least {MIN_CANDIDATES} goal regions; "
                         f"{sc.name} has {len(sc.goals)}")


def draw_kind(sc, kind: str, rng: np.random.Generator | None, n_steps: int) -> KindDraw:
    """The kind's choices for one trial (``rng``: the kind's own stream; unused by ``nominal``)."""
    check_kind(sc, kind)
    M = len(sc.targets)
    goals: list = [None] * M
    names: list = [t.goal for t in sc.targets]
    behaviours = ["guided"] * M
    events: list[Mismatch] = []
    if kind == "candidate_goal":
        for j in range(M):
            g = sc.goals[int(rng.integers(len(sc.goals)))]
            goals[j], names[j] = g.center_m, g.name
    elif kind == "unknown_goal":
        obstacles = Obstacles.from_boxes(sc.obstacles)
        for j, t in enumerate(sc.targets):
            goals[j], names[j] = _unnamed_point(sc, obstacles, np.array(t.position_m, float), rng), None
    elif kind in ("stationary", "wander"):
        behaviours = [kind] * M
        names = [None] * M
    elif kind == "stop_turn":
        half = n_steps // 2
        stop_steps = int(round(STOP_S / sc.dynamics.dt_s))
        for j in range(M):
            if rng.random() < 0.5:
                at = int(rng.integers(max(1, half // 4), max(2, half)))
                events += [Mismatch(j, "stop", at), Mismatch(j, "resume", at + stop_steps)]
            else:
                events.append(Mismatch(j, "turn_back", half))
                names[j] = None
    return KindDraw(tuple(goals), tuple(names), tuple(behaviours), tuple(events))


def _unnamed_point(sc, obstacles: Obstacles, start: np.ndarray, rng: np.random.Generator):
    lo = np.array(sc.area.min_m[:2], float) + UNKNOWN_EDGE_M
    hi = np.array(sc.area.max_m[:2], float) - UNKNOWN_EDGE_M
    centres = np.array([g.center_m[:2] for g in sc.goals], float)
    best, best_d = None, -1.0
    for _ in range(1000):
        p = rng.uniform(lo, hi)
        q = np.r_[p, start[2]]
        if blocked(obstacles, q, q):
            continue
        d = min(np.min(np.linalg.norm(centres - p, axis=1)) / UNKNOWN_FROM_GOALS_M,
                np.linalg.norm(p - start[:2]) / UNKNOWN_FROM_START_M)
        if d >= 1.0:
            return (float(p[0]), float(p[1]), float(start[2]))
        if d > best_d:
            best, best_d = q, d
    return (float(best[0]), float(best[1]), float(best[2]))  # a small area: the farthest found


def truth_world(sc, rng: np.random.Generator, kind: str = "nominal", kind_rng: np.random.Generator | None = None,
                n_steps: int = 0, mismatch: Sequence[Mismatch] = ()) -> TruthWorld:
    """The kind's truth world: the nominal initial states from ``rng``, the kind's choices from
    ``kind_rng`` (default: a stream spawned from ``rng``'s seed, not drawn from it)."""
    if kind == "nominal":
        return TruthWorld.from_scenario(sc, rng, mismatch)
    if kind_rng is None:
        kind_rng = np.random.default_rng(rng.bit_generator.seed_seq.spawn(1)[0])
    d = draw_kind(sc, kind, kind_rng, n_steps)
    nominal = np.array([sc.goal_point(t) for t in sc.targets], float)
    goals = np.array([nominal[j] if g is None else g for j, g in enumerate(d.goals)], float)
    return TruthWorld.from_scenario(sc, rng, tuple(mismatch) + d.mismatch, goals=goals, behaviours=d.behaviours)


def filter_scenario(sc, kind: str, draw: KindDraw | None = None, told: bool = False):
    """The scenario the filter flies on a truth of ``kind``: as written, except that for
    ``candidate_goal`` every target declares the scenario's goal regions as its candidates (it
    knows them, not which), and, ``told``, each target declares what it really does (its true goal,
    or that it stands still: the upper reference an untold filter is measured against)."""
    from dataclasses import replace

    if kind == "candidate_goal":
        every = tuple(g.name for g in sc.goals)
        sc = replace(sc, targets=tuple(replace(t, goal=None, goals=every) if len(t.candidates) < 2 else t
                                       for t in sc.targets))
    if not told:
        return sc
    if draw is None:
        raise ValueError("a told filter needs the trial's draw")
    if kind == "candidate_goal":
        targets = tuple(replace(t, goal=n, goals=()) for t, n in zip(sc.targets, draw.goal_names))
    elif kind == "stationary":
        targets = tuple(replace(t, goal=None, goals=(), stationary=True) for t in sc.targets)
    else:
        raise ValueError(f"--told applies to --truth candidate_goal or stationary, not {kind}")
    return replace(sc, targets=targets)


def simulate_kind(sc, n_steps: int, rng: np.random.Generator, kind: str = "nominal",
                  kind_rng: np.random.Generator | None = None, with_gains: bool = False):
    """``sim.truth.world.simulate_truth`` on the truth of ``kind`` (``truth_world``): the same states and
    gains as the nominal truth's for ``nominal``."""
    return simulate_truth(sc, n_steps, rng, with_gains=with_gains,
                          world=truth_world(sc, rng, kind, kind_rng, n_steps))
