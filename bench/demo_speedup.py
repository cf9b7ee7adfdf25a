"""`pmon demo`'s speed-up choice (sim/stack/demo.py ``measure_tick_s``, ``choose_speedup``) idle and
beside N busy processes at normal priority: the tick's CPU time (what the demo measures) and its
wall time (what it measured before), each a median of ``--repeat`` measurements, and the
speed-up each would choose. In this process's BLAS threads; the demo measures in one
(``measure_tick_apart``): ``OPENBLAS_NUM_THREADS=1 python -m bench.demo_speedup`` for its figure.

    python -m bench.demo_speedup [--busy 2] [--repeat 5]

Last line: JSON figures.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

BUSY = "while True: pass"


def _measure(sc, clock, repeat: int) -> list[float]:
    from sim.stack.demo import measure_tick_s

    return [measure_tick_s(sc, clock=clock) for _ in range(repeat)]


def main(argv: list[str] | None = None) -> int:
    from onboard.argcheck import integer

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--busy", type=integer(0, 64), default=2, help="busy processes beside the loaded half")
    ap.add_argument("--repeat", type=integer(1, 100), default=5)
    args = ap.parse_args(argv)
    from onboard.config import load_scenario
    from onboard.policy import with_policy
    from sim.stack.demo import choose_speedup

    sc = with_policy(load_scenario("paper"), "flight")
    out = {"busy": args.busy, "repeat": args.repeat, "cpus": os.cpu_count()}
    for load in ("idle", "loaded"):
        procs = []
        if load == "loaded":
            procs = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(args.busy)]
            time.sleep(1.0)
        try:
            for name, clock in (("cpu", time.thread_time), ("wall", time.perf_counter)):
                ms = [1e3 * t for t in _measure(sc, clock, args.repeat)]
                med = statistics.median(ms)
                out[f"{load}_{name}_ms"] = round(med, 1)
                out[f"{load}_{name}_speedup"] = choose_speedup(med / 1e3)
                print(f"{load:6s} {name:4s} tick median {med:6.1f} ms (each: {', '.join(f'{m:.0f}' for m in ms)}) "
                      f"-> speedup {choose_speedup(med / 1e3):g}x", flush=True)
        finally:
            for p in procs:
                p.kill()
                p.wait()
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
