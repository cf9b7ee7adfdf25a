"""KrakenSDR as the DF (issue 32): is the spectrum's set of peaks worth it, and does the KrakenSDR
path lose anything against the datagram feed?

    python -m bench.kraken core [--trials 20] [--seed 2024] [--workers 1] [--arms main,peaks,peaks_adaptive,native]
                                [--duration 100] [--df-clutter LAMBDA] [--set KEY=VALUE ...]
                                (an arm peaks:F or peaks_adaptive:F: with peak_floor_db F)
    python -m bench.kraken stack [--seeds 1,2,3] [--duration 100] [--speedup 3] [--multipath off]

``core``: the paper's scenario and method (the greedy one-step rule, jump moves, as ``pmon eval``'s
greedy_l1), 100 s per trial, each trial's truth and UAV start shared by every arm. Per tick the
DF model's scan (p_D 0.95, sigma 1 deg, Poisson(1) clutter: sim/truth/sensors.py) is written by the
simulated KrakenSDR (sim/stack/kraken.py: the target's lobe, each clutter bearing a multipath lobe of
-10..+3 dB against the direct path, a smooth floor 25 dB down, its main DoA the argmax on its
1-degree grid) as its "Kraken App" line, read back by the app's own KrakenSource
(onboard/app/kraken/source.py: parse, heading, measurement set) and paired with the vehicle's pose
(onboard/app/df/pairing.py) into the tick:

* ``main``: the main DoA alone, the filter's clutter rate the scenario's (Lambda = 1);
* ``peaks``: the spectrum's peaks as the set, the filter's Lambda = 1 (the default settings);
* ``peaks_adaptive``: the peaks, the clutter rate they show (``clutter: adaptive``; never less
  than the filter's own unless ``--set kraken.clutter_min=...``);
* ``native``: the DF model's bearings themselves (what the datagram feed sends), Lambda = 1.

``--df-clutter``: the DF model's clutter rate (more multipath than the filter is set for), the
filter keeping the scenario's. Every arm draws the same random numbers (DF, spectrum, filter: common random numbers), so the
paired per-trial differences measure the processing. Printed: each arm's RMSE (``pmon eval``'s
rmse_mean_m: the time-averaged, target-averaged eps_t over t >= 10 s), the paired per-trial
difference from ``main`` with its 95 % t-interval, and how many trials each arm did no worse.

``stack``: the whole stack on loopback, stood up by sim/stack/rig.py (mock ArduCopter and the app,
launching itself, in this process; the feed, ``pmon feed live``, a process of its own), 100 s missions, once with the datagram feed and once with the simulated
KrakenSDR, the same seed (the same truth and DF draws), with ``sensor.clutter_rate: 0`` for both
(the spectrum has only the target's peak: ``--multipath off``, the default here; the datagrams
then carry the same bearings). Printed per seed: RMSE of each, their ratio, scans written and
ticked with every target. Timing differs between runs of the same seed (threads, the machine's
load), so the flights differ too: compare over seeds.

Last line: JSON.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from onboard.config import load_scenario
from onboard.policy import with_policy

ARMS = ("main", "peaks", "peaks_adaptive", "native")
UNIX0 = 1_700_000_000.0
T0 = 100.0  # autopilot s of the first scan


# ----------------------------------------------------------------------------- core
def _kraken_cfg(sc, arm: str):
    """An arm's kraken settings (the scenario's, ``--set`` included); ``peaks:F`` /
    ``peaks_adaptive:F``: with ``peak_floor_db`` F."""
    k = sc.kraken
    name, _, floor = arm.partition(":")
    if floor:
        k = replace(k, peak_floor_db=float(floor))
    if name == "main":
        return replace(k, measurements="main", clutter="fixed")
    if name == "peaks_adaptive":
        return replace(k, measurements="peaks", clutter="adaptive")
    return replace(k, measurements="peaks", clutter="fixed")


def run_arm(sc, arm: str, truth: np.ndarray, start: np.ndarray, seed: int, trial: int,
            df_clutter: float | None = None) -> np.ndarray:
    """(K, M) position errors of one arm on one trial's truth."""
    from onboard.app.autopilot.clock import ManualClock, UtcMap
    from onboard.app.kraken.source import KrakenSource
    from onboard.app.df.pairing import scans_for_tick
    from onboard.app.autopilot.pose import PoseHistory, PoseSample
    from onboard.core.guidance.predictor import GuidanceWorkspace
    from onboard.core.monitor import MonitorSetup, Scan, UavState, initial_state, tick
    from sim.stack.kraken import KrakenModel, frame_lines
    from sim.truth.sensors import DirectionFinder, df_scan_labelled

    setup = MonitorSetup.from_scenario(sc)  # the filter: the scenario's sensor (Lambda = 1)
    df = DirectionFinder(sc.sensor.sigma_rad, sc.sensor.p_detect, sc.sensor.clutter_rate if df_clutter is None else df_clutter)
    # common random numbers: every arm the same DF draws, spectra and filter stream
    sensor_ss, render_ss, filter_ss = np.random.SeedSequence(seed, spawn_key=(trial, 32)).spawn(3)
    sensor_rng, render_rng, filter_rng = (np.random.default_rng(s) for s in (sensor_ss, render_ss, filter_ss))
    K, M = truth.shape[0], truth.shape[1]
    names = tuple(t.name for t in sc.targets)
    freqs = {names.index(v.target): v.freq_hz for v in sc.kraken.vfos}
    model = KrakenModel()
    clock, poses, utc = ManualClock(T0), PoseHistory(keep_s=10.0), UtcMap()
    for j in range(9):
        utc.observe(int((UNIX0 + j) * 1e6), j * 1000)
    made: dict[int, object] = {}
    src = KrakenSource(_kraken_cfg(sc, arm), names, clock, poses, utc,
                       lambda d, now: made.__setitem__(d.ch, d), lambda: sc.sensor.p_detect, lambda r, m: None,
                       lambda: sc.sensor.clutter_rate)
    state = initial_state(setup, filter_rng)
    ws = GuidanceWorkspace()
    uav, yaw = np.asarray(start, float).copy(), 0.0
    err = np.zeros((K, M))
    for k in range(K):
        t = T0 + k
        labelled = df_scan_labelled(truth[k], uav, df, sensor_rng)
        if arm == "native":
            scans = [Scan(uav.copy(), tuple(b for b, _ in labelled))]
        else:
            clock.t = t + 0.05
            poses.add(PoseSample(t, uav.copy(), np.zeros(3), yaw))
            epoch = int(round((UNIX0 + t) * 1000 + model.latency_ms / 2))
            made.clear()
            src.offer("doa", frame_lines(epoch, labelled, freqs, yaw, model, render_rng).encode())
            scans, _ = scans_for_tick(dict(made), t, M, lambda tm: uav.copy())
        state, res = tick(setup, state, scans, filter_rng, plan_from=UavState(uav), workspace=ws)
        err[k] = np.linalg.norm(res.means[:, :2] - truth[k, :, :2], axis=1)
        nxt = res.next_position
        if nxt is not None and k < K - 1:
            d = np.asarray(nxt, float)[:2] - uav[:2]
            if np.hypot(*d) > 1.0:  # the vehicle turns to where it goes
                yaw = math.atan2(d[0], d[1])
            uav = np.asarray(nxt, float).copy()
    return err


def run_trial(args_tuple) -> dict:
    sc_path, overrides, seed, trial, arms, n_ticks, df_clutter = args_tuple
    from sim.evaluation import trials as ev
    from sim.evaluation.metrics import seeded_rng
    from sim.truth.world import simulate_truth

    sc = with_policy(load_scenario(sc_path, overrides), "paper")  # the paper's method and filter
    cfg = ev.make_config(sc, 1, seed, ("greedy_l1",), duration_s=n_ticks * sc.dynamics.dt_s)
    truth = simulate_truth(sc, cfg.n_ticks - 1, seeded_rng(seed, trial, 0))
    start = ev.draw_start(cfg, seeded_rng(seed, trial, 1))
    t0 = time.perf_counter()
    out = {arm: run_arm(sc, arm, truth, start, seed, trial, df_clutter) for arm in arms}
    return {"trial": trial, "errors": out, "wall_s": time.perf_counter() - t0}


def core(args) -> dict:
    from sim.evaluation.metrics import t_interval

    arms = tuple(a for a in args.arms.split(",") if a)
    bad = [a for a in arms if a.partition(":")[0] not in ARMS or (":" in a and a.startswith(("main", "native")))]
    if bad or "main" not in arms:
        raise SystemExit(f"--arms: known {', '.join(ARMS)}, and main must be among them (got {args.arms})")
    n_ticks = int(round(args.duration))
    from bench import set_overrides
    overrides = set_overrides(args.parser, args)
    jobs = [("paper", overrides, args.seed, n, arms, n_ticks, args.df_clutter) for n in range(args.trials)]
    t0 = time.perf_counter()
    if args.workers > 1:
        import multiprocessing as mp
        with mp.get_context("spawn").Pool(args.workers) as pool:
            results = sorted(pool.imap_unordered(run_trial, jobs), key=lambda r: r["trial"])
    else:
        results = []
        for j in jobs:
            results.append(run_trial(j))
            print(f"  trial {j[3] + 1}/{args.trials}: " + ", ".join(
                f"{a} {np.sqrt(np.mean(results[-1]['errors'][a][10:] ** 2)):.1f} m" for a in arms), flush=True)
    wall = time.perf_counter() - t0
    w0 = min(10, n_ticks // 2)
    E = {a: np.stack([r["errors"][a] for r in results]) for a in arms}  # (N, K, M)
    eps = {a: np.sqrt((E[a] ** 2).mean(axis=0)) for a in arms}  # (K, M): eps_t per target
    rmse = {a: float(eps[a][w0:].mean(axis=1).mean()) for a in arms}
    per_trial = {a: np.sqrt((E[a][:, w0:] ** 2).mean(axis=(1, 2))) for a in arms}
    lam = "1 (the scenario's)" if args.df_clutter is None else f"{args.df_clutter:g} (the filter's: 1)"
    from bench import set_label
    print(f"paper scenario{set_label(args)}, greedy rule, {args.trials} trials x {n_ticks} s, seed {args.seed}; "
          f"multipath Poisson({lam}), -10..+3 dB (sim/stack/kraken.py KrakenModel); wall {wall:.0f} s")
    print(f"{'arm':16s} {'RMSE m':>7s} {'minus main, per trial (95 % CI)':>34s} {'trials no worse':>16s}")
    out = {"trials": args.trials, "seed": args.seed, "ticks": n_ticks, "df_clutter": args.df_clutter,
           "rmse_m": {}, "minus_main_m": {},
           "no_worse_than_main": {}, "wall_s": round(wall, 1)}
    for a in arms:
        d = per_trial[a] - per_trial["main"]
        m, lo, hi = t_interval(d)
        no_worse = int((d <= 0).sum())
        out["rmse_m"][a] = round(rmse[a], 2)
        if a != "main":
            out["minus_main_m"][a] = [round(m, 2), round(lo, 2), round(hi, 2)]
            out["no_worse_than_main"][a] = no_worse
        ci = "" if a == "main" else f"{m:+.2f} ({lo:+.2f}, {hi:+.2f})"
        print(f"{a:16s} {rmse[a]:7.2f} {ci:>34s} {'' if a == 'main' else f'{no_worse}/{args.trials}':>16s}")
    return out


# ----------------------------------------------------------------------------- stack
def stack_run(df: str, seed: int, duration: float, speedup: float, multipath: bool, overrides: dict) -> dict:
    """One mission on sim/stack/rig.py: the mock ArduCopter and the app (launching itself) in this
    process, the feed a process of its own (``pmon feed live``: its truth world must not hold this
    process's GIL while the app reads and ticks), sending datagrams or serving KrakenSDR's output."""
    import tempfile

    import yaml

    from sim.stack.demo import DEMO_READY_S
    from sim.stack.rig import Rig, RigConfig

    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as tmp:
        scen = Path(tmp) / "scenario.yaml"
        scen.write_text(yaml.safe_dump(_overridden(yaml.safe_load(open(root / "config" / "paper.yaml")), overrides)))
        run, truth = Path(tmp) / "run.jsonl", Path(tmp) / "truth.jsonl"
        rig = Rig(RigConfig(scenario=str(scen), seed=seed, feed_seed=seed, speedup=speedup, ready_s=DEMO_READY_S,
                            in_process=True, auto_launch=True, df=df, multipath=multipath,
                            feed_duration_s=float(int(duration)), out_dir=str(Path(tmp) / "rig"),
                            runlog_path=str(run), truth_path=str(truth)))
        with rig:
            app = rig.app
            feed = rig.feed.p
            try:
                feed.wait(timeout=duration / speedup * 6 + 300)
            finally:
                if feed.poll() is None:
                    feed.terminate()
                    feed.wait(timeout=10)
            scans = [json.loads(x) for x in open(truth)][1:]
            last = scans[-1]["t"] if scans else math.inf
            deadline = time.monotonic() + 10
            while time.monotonic() < deadline and not any(tk["t"] >= last for tk in list(app.ticks)):
                time.sleep(0.05)
            time.sleep(1.0)
        ticks = {tk["t"]: tk for tk in (json.loads(x) for x in open(run))}
        kraken = None
        if app.kraken is not None:
            k = app.kraken.source
            kraken = {"frames": k.frames, "missed": k.missed, "scans": k.scans, "decimated": k.decimated,
                      "rejected": {r: n for r, n in k.rejected.items() if n}}
    out = {**_scan_figures(scans, ticks), "ticks_skipped": app.counters.get("ticks_skipped", 0),
           "ticks_late": app.counters.get("ticks_late", 0),
           "load_avg_1m_end": round(__import__("os").getloadavg()[0], 2)}
    if kraken is not None:
        out["kraken"] = kraken
    return out


def _overridden(tree: dict, overrides: dict) -> dict:
    """The scenario tree with each dotted ``overrides`` key set (in place)."""
    for key, value in overrides.items():
        node = tree
        *parents, last = key.split(".")
        for part in parents:
            node = node[part]
        node[last] = value
    return tree


def _scan_figures(scans: list[dict], ticks: dict) -> dict:
    """The truth's scans against the run log's ticks: how many were ticked on every channel, when
    the others came, and the tracking RMSE (after the first ten ticked scans, or half)."""
    errs, ticked, unticked = [], 0, []
    for s in scans:
        tk = ticks.get(s["t"])
        if tk is not None and tk["channels"] == list(range(len(s["targets"]))):
            ticked += 1
        else:
            unticked.append(s["t"] - scans[0]["t"])  # s after the first scan
        if tk is not None:
            errs.append(np.linalg.norm(np.array(tk["means"])[:, :2] - np.array(s["targets"])[:, :2], axis=1))
    e = np.array(errs)
    w0 = min(10, len(e) // 2)
    return {"scans": len(scans), "ticked_all_channels": ticked, "unticked_s_after_first": unticked,
            "rmse_m": float(np.sqrt((e[w0:] ** 2).mean())) if len(e) else float("nan"),
            "rmse_per_target_m": np.sqrt((e[w0:] ** 2).mean(axis=0)).round(2).tolist() if len(e) else []}


def stack(args) -> dict:
    overrides = {"sensor.clutter_rate": 0.0} if args.multipath == "off" else {}
    rows = []
    print(f"stack: mock ArduCopter at {args.speedup:g}x, {args.duration:g} s missions, "
          f"{'sensor.clutter_rate 0, the spectrum only the target peak' if args.multipath == 'off' else 'multipath on'}")
    print(f"{'seed':>5s} {'datagram RMSE':>14s} {'kraken RMSE':>12s} {'ratio':>6s} {'scans ticked d/k':>18s}")
    for seed in args.seeds:
        d = stack_run("datagram", seed, args.duration, args.speedup, True, overrides)
        k = stack_run("kraken", seed, args.duration, args.speedup, args.multipath == "on", overrides)
        ratio = k["rmse_m"] / d["rmse_m"]
        rows.append({"seed": seed, "datagram": d, "kraken": k, "ratio": round(ratio, 3)})
        print(f"{seed:5d} {d['rmse_m']:14.2f} {k['rmse_m']:12.2f} {ratio:6.3f} "
              f"{d['ticked_all_channels']:>5d}/{d['scans']} {k['ticked_all_channels']:>4d}/{k['scans']}", flush=True)
    dm = float(np.mean([r["datagram"]["rmse_m"] for r in rows]))
    km = float(np.mean([r["kraken"]["rmse_m"] for r in rows]))
    print(f"mean over seeds: datagram {dm:.2f} m, kraken {km:.2f} m, ratio {km / dm:.3f}")
    return {"runs": rows, "mean_rmse_m": {"datagram": round(dm, 2), "kraken": round(km, 2)},
            "ratio_of_means": round(km / dm, 3)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.kraken", description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="mode", required=True)
    c = sub.add_parser("core", help="paired trials of the measurement set, no sockets")
    c.add_argument("--trials", type=int, default=20)
    c.add_argument("--seed", type=int, default=2024)
    c.add_argument("--duration", type=float, default=100.0)
    c.add_argument("--workers", type=int, default=1)
    c.add_argument("--arms", default=",".join(ARMS))
    from bench import add_set_option
    add_set_option(c, "kraken.clutter_min=0.1")
    c.set_defaults(parser=c)
    c.add_argument("--df-clutter", type=float, default=None, metavar="LAMBDA",
                   help="the DF model's clutter (multipath) rate, the filter keeping the scenario's (default: "
                        "the scenario's, 1)")
    s = sub.add_parser("stack", help="the stack with the datagram feed and with the simulated KrakenSDR")
    s.add_argument("--seeds", type=lambda v: [int(x) for x in v.split(",")], default=[1, 2, 3])
    s.add_argument("--duration", type=float, default=100.0)
    s.add_argument("--speedup", type=float, default=3.0)
    s.add_argument("--multipath", choices=("on", "off"), default="off")
    args = ap.parse_args(argv)
    out = core(args) if args.mode == "core" else stack(args)
    print(json.dumps({"bench": f"kraken {args.mode}", **out}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
