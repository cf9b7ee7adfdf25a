"""Exact MIQP solve of Problem P1 with SCIP (pyscipopt): the reference our OSQP route is measured
against. Tests and benchmarks only; never flown.

The same problem as ``onboard.core.guidance.predictor``: positions p_2..p_(T+1) as variables (p_1 is fixed
by the current state), controls and velocities as linear maps of them, the speed polygon, the
input box, and per segment s = 1..T-1 and obstacle k big-M binaries choosing one lateral face that
both end points p_s and p_(s+1) are outside of (the paper's eqs. (8d)-(8e), per segment).
The quadratic objective is an epigraph variable (SCIP takes linear objectives only).
"""
from __future__ import annotations

import time

import numpy as np

from types import SimpleNamespace

from onboard.core.dynamics import MotionModel
from onboard.core.guidance.predictor import KN, GuidanceParams
from onboard.core.obstacles import N_LATERAL, Obstacles


def random_instance(rng: np.random.Generator, margin_m: float, blocked: bool = False):
    """A random P1 instance: 1-3 rotated cuboids, a start near y = 0 and a goal.

    Returns (obstacles, mean0 (6,), goal (3,)); the start, its p_1 and the goal are clear of the
    obstacles inflated by ``margin_m`` + 2 m. Default: the goal near y = 460, the cuboids anywhere
    between. ``blocked``: the goal 120-180 m ahead and the cuboids on the straight line to it
    (short horizons that must go around: instances an exact solver finishes).
    """
    while True:
        start = np.r_[rng.uniform(0, 500), rng.uniform(0, 80), 0.0]
        vel = np.r_[rng.normal(0, 4, 2), 0.0]
        if blocked:
            goal = start + np.r_[rng.uniform(-40, 40), rng.uniform(120, 180), 0.0]
            t = rng.uniform(0.3, 0.7, 3)[:, None]
            centres = start[:2] + t * (goal - start)[:2] + rng.uniform(-30, 30, (3, 2))
            sizes = rng.uniform(20, 60, (3, 2))
        else:
            goal = np.array([rng.uniform(100, 400), rng.uniform(420, 500), 0.0])
            centres = np.column_stack([rng.uniform(100, 400, 3), rng.uniform(150, 350, 3)])
            sizes = rng.uniform(20, 90, (3, 2))
        n = rng.integers(1, 4)
        boxes = [SimpleNamespace(center_m=(c[0], c[1], 15.0), size_m=(w[0], w[1], 30.0),
                                 yaw_rad=float(rng.uniform(0, np.pi))) for c, w in zip(centres[:n], sizes[:n])]
        obs = Obstacles.from_boxes(boxes)
        if not obs.inflate(margin_m + 2.0).contains(np.vstack([start, start + vel, goal])).any():
            return obs, np.r_[start, vel], goal


def solve_p1_exact(model: MotionModel, params: GuidanceParams, obstacles: Obstacles, mean0: np.ndarray,
                   goal: np.ndarray, time_limit_s: float = 60.0, big_m: float = 1e4):
    """Returns dict(status, cost, time_s, positions (T, 2) p_1..p_T) ; cost is nan when none found."""
    from pyscipopt import Model, quicksum

    T = params.horizon
    dt, decay = model.dt_s, 1.0 - model.friction
    gain = dt / model.mass_kg * KN
    x0 = np.asarray(mean0, float)[[0, 1, 3, 4]]
    g = np.asarray(goal, float)[:2]
    normals, offsets, _, _ = obstacles.inflate(params.obstacle_margin_m).lateral()

    m = Model("P1")
    m.hideOutput()
    m.setParam("limits/time", time_limit_s)
    m.setParam("limits/gap", 1e-7)
    p1 = x0[:2] + dt * x0[2:]
    # p[tau] for tau = 1..T+1 (index 0 unused): p_1 constant
    p = {1: (float(p1[0]), float(p1[1]))}
    for tau in range(2, T + 2):
        p[tau] = (m.addVar(f"px{tau}", lb=None), m.addVar(f"py{tau}", lb=None))
    v = {0: (float(x0[2]), float(x0[3]))}
    for tau in range(1, T + 1):
        v[tau] = tuple((p[tau + 1][a] - p[tau][a]) * (1.0 / dt) for a in range(2))
    w = {tau: tuple((v[tau + 1][a] - decay * v[tau][a]) * (1.0 / gain) for a in range(2)) for tau in range(T)}
    box = params.u_max_n / KN
    for tau in range(T):
        for a in range(2):
            m.addCons(w[tau][a] <= box)
            m.addCons(w[tau][a] >= -box)
    ang = 2 * np.pi * np.arange(params.speed_polygon_sides) / params.speed_polygon_sides
    v0n = float(np.linalg.norm(x0[2:]))
    for tau in range(1, T + 1):
        bound = max(params.speed_max_mps * np.cos(np.pi / params.speed_polygon_sides), v0n * decay**tau + 1e-6)
        for c in ang:
            m.addCons(np.cos(c) * v[tau][0] + np.sin(c) * v[tau][1] <= bound)
    for k in range(len(offsets)):
        for s in range(1, T):
            y = [m.addVar(f"y{k}_{s}_{f}", vtype="B") for f in range(N_LATERAL)]
            m.addCons(quicksum(y) >= 1)
            for f in range(N_LATERAL):
                a, b = normals[k, f], offsets[k, f]
                for tau in (s, s + 1):
                    m.addCons(a[0] * p[tau][0] + a[1] * p[tau][1] >= b - big_m * (1 - y[f]))
    qw = np.full(T, params.stage_weight)
    qw[-1] = params.terminal_weight
    obj = quicksum(qw[tau - 1] * ((p[tau][0] - g[0]) ** 2 + (p[tau][1] - g[1]) ** 2) for tau in range(1, T + 1))
    obj += quicksum(params.smooth_weight * ((w[tau][a] - w[tau - 1][a]) ** 2) for tau in range(1, T) for a in range(2))
    t = m.addVar("t", lb=0.0)
    m.addCons(t >= obj)
    m.setObjective(t, "minimize")
    t0 = time.perf_counter()
    m.optimize()
    elapsed = time.perf_counter() - t0
    status = m.getStatus()
    if m.getNSols() == 0:
        return {"status": status, "cost": float("nan"), "time_s": elapsed, "positions": None}
    pos = np.array([[m.getVal(p[tau][a]) if tau > 1 else p[tau][a] for a in range(2)] for tau in range(1, T + 1)])
    # report the objective recomputed from the positions, as ours is
    return {"status": status, "cost": float(m.getObjVal()), "time_s": elapsed, "positions": pos}
