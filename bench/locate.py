"""``pmon locate`` over simulated recordings: each emitter's final error and the ellipse's consistency.

    python -m bench.locate [--recordings 20] [--seed 2024] [--bearings kraken|datagram]
                           [--poses LOG] [--set KEY=VALUE ...]

Each recording (sim/stack/locate_recording.py) is a hand-flown lawnmower over two stationary emitters,
its bearings KrakenSDR's data recording (``mydata.csv``; or the same bearings as datagrams), its
poses a tlog; with ``--poses LOG`` (a firmware's DataFlash .bin or PX4 ULog, or a tlog) the
vehicle's poses and UTC are that log's and each recording's bearings are drawn along them. The
emitters' priors are drawn around the truth with the prior the scenario states (100 m), so the
estimate's NEES is meaningful: per recording and emitter, the final position error and NEES
(e' P^-1 e, 2 degrees of freedom), then the mean NEES over all of them with its two-sided 95 %
chi-square band (a consistent filter's mean lies in it 95 % of the time). Last line: JSON.
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from bench import add_set_option, set_overrides
from groundstation.locate import Request, locate, stationary_share
from onboard.app.autopilot.pose import Frame
from onboard.config import load_scenario
from onboard.policy import DEFAULT, with_policy
from sim.stack import locate_recording as rec


def firmware_poses(path: str) -> tuple:
    """(path, airborne poses, autopilot s -> Unix s) of a firmware's log (groundstation/poses.py)."""
    from groundstation.poses import read

    log = read(path, Frame(*rec.ORIGIN))
    flying = [s for s in log.samples if s.pos[2] > 10.0 and s.yaw is not None]
    if log.utc.unix_time(0.0) is None:  # PX4's SIH writes no UTC: the recording stamped from a boot time
        return path, flying, None
    return path, flying, log.utc.unix_time


def one(folder: Path, seed: int, bearings: str, overrides: dict, firmware: tuple | None = None) -> list[dict]:
    """One recording written in ``folder`` and located (its bearings drawn along ``firmware``'s
    poses when given, else a simulated lawnmower's): per emitter, error, NEES, ranges."""
    boot = None  # the Unix time of the autopilot's boot, for a log without UTC
    if firmware is None:
        r = rec.write_recording(folder, seed)
        log_path = r["tlog"]
    else:
        log_path, poses, unix_of = firmware
        boot = rec.UNIX_AT_BOOT if unix_of is None else None
        r = rec.write_recording(folder, seed, poses=poses, unix_of=unix_of or (lambda t: rec.UNIX_AT_BOOT + t))
    sc = with_policy(load_scenario(str(r["scenario"]), overrides), DEFAULT)
    src = r["mydata"] if bearings == "kraken" else r["datagrams"]
    found, log = locate(Request(str(src), str(log_path), sc, seed=seed,
                                unix_at_boot=boot))
    xy = np.array([s.pos[:2] for s in log.samples])
    out = []
    for j, truth in enumerate(r["truth_m"]):
        e = found.final_means[j][:2] - truth
        P = found.final_covs[j][:2, :2]
        e_tick = found.means[-1][j][:2] - truth  # the filter's last tick, for comparison
        rng_m = np.linalg.norm(xy - truth, axis=1)
        out.append({"error_m": float(np.linalg.norm(e)), "nees": float(e @ np.linalg.solve(P, e)),
                    "final": found.final_kind[j], "error_tick_m": float(np.linalg.norm(e_tick)),
                    "nees_tick": float(e_tick @ np.linalg.solve(found.covs[-1][j][:2, :2], e_tick)),
                    "sd_m": float(np.sqrt(np.trace(P))), "sd_tick_m": float(np.sqrt(np.trace(found.covs[-1][j][:2, :2]))),
                    "p_stationary": stationary_share(found, j), "reseeds": len(found.reseeds[j]),
                    "range_min_m": float(rng_m.min()), "range_max_m": float(rng_m.max()),
                    "notes": len(found.notes)})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--recordings", type=int, default=20)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--bearings", choices=("kraken", "datagram"), default="kraken")
    ap.add_argument("--poses", help="a firmware's log (.bin, .ulg, .tlog) to draw the bearings along")
    add_set_option(ap, "tracking.particles=4000")
    args = ap.parse_args(argv)
    overrides = set_overrides(ap, args)
    firmware = firmware_poses(args.poses) if args.poses else None
    rows = []
    with tempfile.TemporaryDirectory(prefix="pmon-locate-") as tmp:
        for k in range(args.recordings):
            res = one(Path(tmp) / f"r{k}", args.seed + k, args.bearings, overrides, firmware)
            rows += res
            print(f"recording {k:2d} (seed {args.seed + k}): " + "  ".join(
                f"T{j + 1} error {x['error_m']:6.2f} m NEES {x['nees']:6.2f} (range {x['range_min_m']:.0f}-"
                f"{x['range_max_m']:.0f} m)" for j, x in enumerate(res)), flush=True)
    return report(rows, args)


def report(rows: list[dict], args) -> int:
    err = np.array([r["error_m"] for r in rows])
    nees = np.array([r["nees"] for r in rows])
    n = len(nees)
    lo, hi = chi2.ppf([0.025, 0.975], 2 * n) / n
    within = int((err <= 15.0).sum())
    print(f"{args.recordings} recordings x {n // max(args.recordings, 1)} emitters, bearings {args.bearings}, "
          f"poses {args.poses or 'simulated tlog'}")
    print(f"final error: mean {err.mean():.2f} m, median {np.median(err):.2f} m, max {err.max():.2f} m; "
          f"{within}/{n} within 15 m")
    print(f"NEES (2 dof): mean {nees.mean():.2f}, 95 % band for the mean of {n} [{lo:.2f}, {hi:.2f}]: "
          f"{'in band' if lo <= nees.mean() <= hi else 'OUT of band'}; median {np.median(nees):.2f}, "
          f"max {nees.max():.2f}; share of single NEES under chi2(2)'s 95 % quantile "
          f"{float((nees <= chi2.ppf(0.95, 2)).mean()):.2f}")
    tick_err = np.array([r["error_tick_m"] for r in rows])
    tick_nees = np.array([r["nees_tick"] for r in rows])
    kinds = {k: sum(r["final"] == k for r in rows) for k in sorted({r["final"] for r in rows})}
    print(f"final estimates: {', '.join(f'{v} {k}' for k, v in kinds.items())}; the filter's last tick instead: "
          f"error mean {tick_err.mean():.2f} m, max {tick_err.max():.2f} m, {int((tick_err <= 15.0).sum())}/{n} "
          f"within 15 m, mean NEES {tick_nees.mean():.2f}")
    print(f"1-sigma radius sqrt(trace P): final mean {np.mean([r['sd_m'] for r in rows]):.2f} m, the filter's last "
          f"tick {np.mean([r['sd_tick_m'] for r in rows]):.2f} m; stationary mode's probability over the ticks "
          f"{np.mean([r['p_stationary'] or 0.0 for r in rows]):.3f}; targets the filter re-seeded "
          f"{sum(r['reseeds'] > 0 for r in rows)}/{n}")
    print(json.dumps({"recordings": args.recordings, "error_mean_m": round(float(err.mean()), 3),
                      "error_max_m": round(float(err.max()), 3), "within_15m": within, "n": n,
                      "nees_mean": round(float(nees.mean()), 3), "tick_error_max_m": round(float(tick_err.max()), 3),
                      "tick_nees_mean": round(float(tick_nees.mean()), 3), "nees_band": [round(lo, 3), round(hi, 3)],
                      "range_m": [round(min(r["range_min_m"] for r in rows)), round(max(r["range_max_m"] for r in rows))],
                      "finite": bool(np.isfinite(nees).all() and math.isfinite(err.sum()))}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
