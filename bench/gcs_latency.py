"""How long each ground-station command takes to answer on loopback, against the SITL stack
(mock ArduCopter + onboard app + DF feed, real time: speedup 1).

Answer time = one whole ``pmon gcs`` command in-process (``groundstation.cli.main``): open the
link, find the vehicle, send, wait for the acknowledgement (or the data), close. Python's
start-up and imports are not in it; a cold ``pmon-gcs status`` process is measured separately.
Target: median <= 1 s per command. Ends with one JSON line.

    python -m bench.gcs_latency [--repeat 5]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path

from sim.stack.sitl_stack import SitlStack

from groundstation.cli import main

TARGET_S = 1.0
RNG = random.Random(6)


def timed(url: str, *argv: str) -> tuple[float, int]:
    if argv[0] in ("status", "watch"):
        # these wait for the app's next PMON_STAT (1 Hz): calls made back to back lock onto
        # its phase and always wait ~1 s; an operator's calls come at random phases
        time.sleep(RNG.uniform(0.0, 1.0))
    t0 = time.perf_counter()
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = main(["--connect", url, "--timeout", "5", *argv])
    timed.last_error = err.getvalue().strip()
    return time.perf_counter() - t0, rc


def run(repeat: int) -> dict:
    times: dict[str, list[float]] = {}
    failures: list[str] = []

    def measure(name: str, *argv: str, n: int = 1, ok=(0,)):
        for _ in range(n):
            dt, rc = timed(url, *argv)
            times.setdefault(name, []).append(dt)
            if rc not in ok:
                failures.append(f"{name}: exit {rc}: {timed.last_error}")

    with SitlStack(speedup=1.0, ready_s=5.0) as st:  # the boot is not what is timed here
        url = st.gcs_url
        st.wait_ready()
        st.start_feed()
        measure("status", "status", n=repeat)
        measure("params list", "params", "list", n=repeat)
        measure("params get", "params", "get", "PMON_CLUTTER", n=repeat)
        measure("params set", "params", "set", "PMON_CLUTTER", "1", n=repeat)
        measure("start (refused)", "start", n=repeat, ok=(1,))
        measure("arm", "arm", n=repeat)
        measure("takeoff", "takeoff", "40")
        assert timed(url, "takeoff", "40", "--wait", "--timeout", "60")[1] in (0, 1)
        st.ap.wait_until(lambda s: s.alt_rel > 39, 30)
        time.sleep(1.0)
        for _ in range(repeat):
            measure("start", "start")
            measure("watch (first update)", "watch", "--count", "1")
            measure("pause", "pause")
            measure("resume", "resume")
            measure("stop", "stop")
        measure("hold", "hold", n=repeat)
        measure("rtl", "rtl", n=repeat)
        measure("land", "land", n=repeat)
        cold = []
        exe = Path(sys.executable).parent / "pmon-gcs"
        for _ in range(3):
            t0 = time.perf_counter()
            subprocess.run([str(exe) if exe.exists() else sys.executable, *([] if exe.exists() else
                            ["-m", "groundstation.cli"]), "--connect", url, "status"],
                           capture_output=True, timeout=30)
            cold.append(time.perf_counter() - t0)
    med = {k: round(statistics.median(v), 3) for k, v in times.items()}
    return {"bench": "gcs_latency", "speedup": 1.0, "target_s": TARGET_S, "median_s": med,
            "max_s": {k: round(max(v), 3) for k, v in times.items()},
            "n": {k: len(v) for k, v in times.items()},
            "cold_process_status_median_s": round(statistics.median(cold), 3),
            "all_within_target": all(v <= TARGET_S for v in med.values()), "failures": failures}


def main_(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeat", type=int, default=5)
    args = p.parse_args(argv)
    res = run(args.repeat)
    width = max(len(k) for k in res["median_s"])
    print(f"{'command':{width}s}  median s   max s   n")
    for k, v in res["median_s"].items():
        print(f"{k:{width}s}  {v:8.3f} {res['max_s'][k]:7.3f} {res['n'][k]:3d}")
    print(f"cold 'pmon-gcs status' process (python start-up and imports included): "
          f"{res['cold_process_status_median_s']:.2f} s")
    print(json.dumps(res))
    return 0 if res["all_within_target"] and not res["failures"] else 1


if __name__ == "__main__":
    sys.exit(main_())
