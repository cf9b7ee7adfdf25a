"""One target's plan at one step of a trial's truth, checked against every face-switch timing.

    python -m bench.guidance_switches TRIAL TARGET T OBSTACLE FACES [--trials 100] [--seed 2024]
    e.g.  python -m bench.guidance_switches 65 4 24 2 1,0,3

Flies trial TRIAL's truth (as ``pmon eval paper --trials N --seed S`` does) to the plan target
TARGET (from 1) makes at t = T s, and prints: that plan; the best plan on the previous plan's side
of every obstacle (``sides``, strict, 1000 QPs, no warm start) and the best on either side (1000
QPs); then, at the obstacle margin and without it, every assignment whose faces of obstacle
OBSTACLE (from 0) follow FACES (lateral faces 0 east, 1 north, 2 west, 3 south, each for at least
one segment, in that order) at every switch timing, the other obstacles' faces those of the
previous plan shifted: how many are feasible and the cheapest. Whether a cheaper side is
feasible from that state, or only not found (docs/GUIDANCE.md, "Cost jumps near corners", names
the commit its figures are of: the truth depends on the guidance).
"""
from __future__ import annotations

from sim.evaluation.workers import one_blas_thread  # no numpy import

one_blas_thread()  # before numpy loads: one core's figures

import argparse
import itertools
from dataclasses import replace

import numpy as np

from onboard.config import load_scenario
from onboard.core.guidance.predictor import GuidanceWorkspace, PlanAsk, Solver, plan_guidance, winding
from onboard.core.guidance.search import FaceSearch, GuidanceRequest
from sim.evaluation import trials as ev
from sim.truth.world import TruthWorld


def describe(name: str, plan) -> str:
    return (f"{name:34s} {plan.status:17s} {plan.qp_solves:4d} QPs  cost {plan.cost:10.4g}  margin "
            f"{plan.margin_m}  winding {winding(plan.faces).tolist()}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    for name in ("trial", "target", "t", "obstacle"):
        ap.add_argument(name, type=int)
    ap.add_argument("faces", help="obstacle's faces in order, e.g. 1,0,3 (north, east, south)")
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--seed", type=int, default=2024)
    args = ap.parse_args()
    try:
        seq = [int(f) for f in args.faces.split(",")]
        if not seq or any(f not in range(4) for f in seq):
            raise ValueError
    except ValueError:
        ap.error(f"FACES takes lateral faces 0-3 separated by commas: {args.faces!r}")
    cfg = ev.make_config(load_scenario("paper", {}), args.trials, args.seed)
    world = TruthWorld.from_scenario(cfg.scenario, ev._rng(cfg.seed, args.trial, 0))
    j = args.target - 1
    if not 0 <= j < len(cfg.scenario.targets) or not 0 < args.t < cfg.n_ticks - 1:
        ap.error(f"TARGET from 1 to {len(cfg.scenario.targets)}, T from 1 to {cfg.n_ticks - 2}")
    for _ in range(args.t):
        world.step()
    m, params, obs = world.model, world.guidance, world.obstacles
    if not 0 <= args.obstacle < len(obs):
        ap.error(f"OBSTACLE from 0 to {len(obs) - 1}")
    x, prev, goal = world.states[j], world.plans[j], world.goals[j]
    ws = GuidanceWorkspace()
    print(f"trial {args.trial} T{args.target} at t = {args.t} s: x = {np.round(x[[0, 1, 3, 4]], 2).tolist()} "
          f"(px, py, vx, vy)")
    print(describe(f"last plan (t = {args.t - 1} s)", prev))
    print(describe("this plan", plan_guidance(m, params, obs, x, goal, previous=prev, solver=Solver(ws))))
    big = replace(params, max_qp_solves=1000)
    side = np.sign(winding(prev.faces))
    sided = plan_guidance(m, big, obs, x, goal, ask=PlanAsk(sides=side, strict_sides=True), solver=Solver(ws))
    print(describe(f"best with sides {side.tolist()}", sided))
    print(describe("best, 1000 QPs", plan_guidance(m, big, obs, x, goal, solver=Solver(ws))))
    T, k = params.horizon, args.obstacle
    for margin in (params.obstacle_margin_m, 0.0):
        search = FaceSearch(GuidanceRequest(m, replace(params, max_qp_solves=10**6), obs, x, goal, prev, ws), margin)
        base, _ = search.shifted(prev)
        n = 0
        for cuts in itertools.combinations(range(1, T - 1), len(seq) - 1):
            col = np.repeat(seq, np.diff((0,) + cuts + (T - 1,)))
            faces = base.copy()
            faces[:, k] = np.where(search.geo.relevant[:, k], col, -1)
            if faces.tobytes() not in search.tried:
                search.evaluate(faces)
                n += 1
        b = search.best
        print(f"margin {margin:g} m: {n} timings of obstacle {k}'s faces {seq}, {len(search.found)} feasible; best "
              + ("none" if b is None else f"{b.cost:.4g}, winding {winding(b.faces).tolist()}"))


if __name__ == "__main__":
    main()
