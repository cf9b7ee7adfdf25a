"""Where a flight case's tick time goes: cProfile over bench/planner.py's closed loops.

    python -m bench.tick_profile [--case flight] [--seeds 1,2,3] [--ticks 60] [--top 25] [--set KEY=VALUE ...]

The same loops as `python -m bench.planner --cases CASE` (one BLAS thread, the paper scenario under the
flight policy at ArduCopter's stock limits), profiled whole; prints the functions of onboard/ by
cumulative time with their call counts, then one JSON line: total seconds and calls of the
guidance's searches (``plan_guidance``, ``FaceSearch.explore``) and the steering's plans
(``steering.side_modes``), the counts that say why one setting's tick costs more than another's.
"""
from __future__ import annotations

from sim.evaluation.workers import one_blas_thread  # no numpy import

one_blas_thread()  # before numpy loads: one core's figures

import argparse
import cProfile
import json
import pstats
import time
from pathlib import Path

from bench import add_set_option, set_overrides
from sim.evaluation.closed_loop import tick_timings
from bench.planner import CASES, setup_for
from onboard.config import load_scenario

WATCH = {"plan_guidance": "guidance/predictor.py", "explore": "guidance/search.py", "side_modes": "steering.py",
         "tick": "monitor.py"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="flight", choices=CASES)
    ap.add_argument("--seeds", default="1,2,3")
    ap.add_argument("--ticks", type=int, default=60)
    ap.add_argument("--top", type=int, default=25)
    add_set_option(ap)
    args = ap.parse_args()
    setup = setup_for(load_scenario("paper", set_overrides(ap, args)), args.case)
    prof = cProfile.Profile()
    prof.enable()
    for seed in (int(s) for s in args.seeds.split(",")):
        tick_timings(setup, args.ticks, seed, timer=time.process_time)
    prof.disable()
    stats = pstats.Stats(prof)
    rows = [(k, v) for k, v in stats.stats.items() if "/onboard/" in k[0]]
    rows.sort(key=lambda kv: -kv[1][3])
    print(f"{'cumulative [s]':>14} {'calls':>8}  function")
    for (path, line, name), (_, calls, _, cum, _) in rows[:args.top]:
        print(f"{cum:14.2f} {calls:8d}  {Path(path).name}:{line}({name})")
    out = {}
    for (path, _, name), (_, calls, _, cum, _) in rows:
        if WATCH.get(name) == Path(path).name:
            out[name] = {"s": round(cum, 2), "calls": calls}
    print(json.dumps({"case": args.case, "seeds": args.seeds, "ticks": args.ticks, **out}))


if __name__ == "__main__":
    main()
