"""The evaluation's trials, cached for bench/ceiling.py: truth, closed-loop gains, UAV start and
the flight default's flown path, PCRB and error, one ``.npz`` per trial.

    python -m bench.ceiling_cache --trials 100 [--seed 2024] [--cache /tmp/ceiling_cache]
                                  [--methods flight@stock] [--workers 1]

Each trial is ``sim.evaluation.trials.run_trial`` (``pmon eval paper --seed 2024 --methods ...``, trial
i) in a spawned worker with one BLAS thread and the pinned kernels, as ``pmon eval`` runs it, so
the truths and the methods' figures are those of the evaluation to the last digit. Trials
already in the cache are skipped; each is written as soon as it is done. Last line: JSON.
"""
from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path

import numpy as np

from onboard.config import load_scenario
from onboard.core.monitor import MonitorSetup
from sim.evaluation import trials as ev
from sim.evaluation.numerics import pin_kernels

DEFAULT_CACHE = "/tmp/ceiling/cache"
FLIGHT = "flight_at_stock"
ROOT = Path(__file__).resolve().parents[1]


def _setup():
    return MonitorSetup.from_scenario(load_scenario("paper"))


def load_trial(cache: Path, seed: int, trial: int) -> dict:
    with np.load(trial_path(cache, seed, trial)) as d:
        return {k: d[k] for k in d.files}


def label(speed: float, accel: float) -> str:
    return f"v{speed:g}_a{accel:g}"


def trial_path(cache: Path, seed: int, trial: int) -> Path:
    return Path(cache) / f"s{seed}_t{trial:03d}.npz"


def _one(cfg, trial: int) -> dict:
    r = ev.run_trial(cfg, trial)
    out = {"truth": r.truth, "gains": r.gains, "start": r.start, "wall_s": np.array(r.wall_s)}
    for name, tr in r.traces.items():
        key = name.replace("@", "_at_")
        out[f"{key}.error_m"] = tr.error_m
        out[f"{key}.bound_m2"] = tr.bound_m2
        if tr.uav is not None:
            out[f"{key}.uav"] = tr.uav
    return out


def fill_cache(trials, seed: int, methods: list[str], cache: Path, workers: int = 1) -> list[int]:
    """Run the trials missing from the cache; returns those written."""
    cache = Path(cache)
    cache.mkdir(parents=True, exist_ok=True)
    todo = [t for t in trials if not trial_path(cache, seed, t).exists()]
    if not todo:
        return []
    cfg = ev.make_config(load_scenario("paper"), max(todo) + 1, seed, methods=methods)
    import multiprocessing as mp

    ev._one_blas_thread()
    pin_kernels()
    ctx = mp.get_context("spawn")
    done = []
    with ev._worker_pool(ctx, workers) as pool:
        for t, res in zip(todo, pool.imap(functools.partial(_one, cfg), todo)):
            tmp = trial_path(cache, seed, t).with_suffix(".tmp.npz")
            np.savez_compressed(tmp, **res)
            tmp.rename(trial_path(cache, seed, t))
            done.append(t)
            print(f"trial {t}: {float(res['wall_s']):.1f} s", flush=True)
    return done


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--cache", default=DEFAULT_CACHE)
    ap.add_argument("--methods", default="flight@stock")
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args()
    t0 = time.perf_counter()
    done = fill_cache(range(args.first, args.first + args.trials), args.seed, args.methods.split(","),
                      Path(args.cache), args.workers)
    print(json.dumps({"written": len(done), "wall_s": round(time.perf_counter() - t0, 1)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
