"""Cost of one evaluation trial, per method, and of one DAQP call in either form of the QP.

    python -m bench.eval_trial [--trial 0] [--methods greedy_l1,greedy_l8,fixed3,hover,orbit,random]
                               [--set tracking.plan_steering=true ...]

One trial as `pmon eval` runs it (seed 2024), in this process on one core: the truth (with the
closed-loop gains the bound needs) and each method's closed loop, wall seconds each; then the
guidance's DAQP call on a QP of the paper's size (100 variables, 10/30/60 rows) with the
Hessian as it is and whitened to the identity (docs/GUIDANCE.md), median ms over 200 calls.
`pmon eval --trials 100` on 2 cores takes about 100 x (the trial's total) / 2. Last line: JSON.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from sim.evaluation.workers import one_blas_thread  # no numpy import

one_blas_thread()  # before numpy loads: one core's figures

import daqp
import numpy as np

from bench import add_set_option, set_overrides
from onboard.config import load_scenario
from onboard.core.guidance.predictor import GuidanceParams, GuidanceWorkspace
from onboard.core.monitor import MonitorSetup
from sim.evaluation import trials as ev
from sim.truth.world import simulate_truth


def trial_times(trial: int, methods: list[str], overrides: dict | None = None) -> dict:
    cfg = ev.make_config(load_scenario("paper", overrides), trial + 1, 2024, methods=methods)
    t0 = time.perf_counter()
    truth, gains = simulate_truth(cfg.scenario, cfg.n_ticks - 1, ev._rng(cfg.seed, trial, 0), with_gains=True)
    out = {"truth": time.perf_counter() - t0}
    start = ev.draw_start(cfg, ev._rng(cfg.seed, trial, 1))
    for m in cfg.methods:
        t0 = time.perf_counter()
        ev.run_method(cfg, m, trial, truth, start, gains)
        out[m.name] = time.perf_counter() - t0
    out["total"] = sum(out.values())
    return {k: round(v, 2) for k, v in out.items()}


def daqp_forms(calls: int = 200) -> dict:
    setup = MonitorSetup.from_scenario(load_scenario("paper"))
    qp = GuidanceWorkspace().qp(setup.guidance.horizon, len(setup.obstacles), setup.model,
                                GuidanceParams.from_config(load_scenario("paper").guidance))
    rng = np.random.default_rng(0)
    f = rng.normal(size=qp.ny)
    out = {}
    for m in (10, 30, 60):
        A = rng.normal(size=(m, qp.ny))
        free = np.linalg.solve(qp.H, -f)
        lo = A @ free + 0.5 * np.abs(rng.normal(size=m))  # every row violated by the free optimum
        hi = np.full(m, 1e30)
        for name, H, ff, AA in (("hessian", qp.H, f, A), ("whitened", qp.I, qp.Rinv.T @ f, A @ qp.Rinv)):
            times = []
            for _ in range(calls):
                t0 = time.perf_counter()
                daqp.solve(H, ff, AA, hi, lo)
                times.append(time.perf_counter() - t0)
            out[f"{name}_{m}_rows_ms"] = round(1e3 * float(np.median(times)), 3)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trial", type=int, default=0)
    ap.add_argument("--methods", default=",".join(ev.DEFAULT_METHODS))
    add_set_option(ap)
    args = ap.parse_args()
    overrides = set_overrides(ap, args)
    t = trial_times(args.trial, args.methods.split(","), overrides)
    print("one trial, s of one core: " + ", ".join(f"{k} {v}" for k, v in t.items()))
    d = daqp_forms()
    print("DAQP call, median ms: " + ", ".join(f"{k} {v}" for k, v in d.items()))
    print(json.dumps({"trial_s": t, "daqp": d}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
