"""``python -m bench.ceiling report``: the tables and figures of the clairvoyant ceiling from what
the other stages left in --out (bench/ceiling.py's docstring).

Figures (``--figures DIR``): ceiling_paths.png (the ceiling's, the flight default's and the
myopic path on a few trials, with the targets' true tracks), ceiling_range.png (mean UAV-target
range over time), ceiling_bearing_rate.png (mean |d bearing / dt| over time), ceiling_bound.png
(the PCRB over time, averaged as the evaluation averages it).
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from bench.ceiling_cache import FLIGHT, ROOT, _setup, label, load_trial
from sim.evaluation import ceiling as ce

W0 = 10  # the evaluation's window starts at tick 10
PHASES = ((10, 30), (30, 60), (60, 100))
BOOT = 2000


def _load_dir(d: Path, trials) -> dict[int, dict]:
    out = {}
    for t in trials:
        f = d / f"t{t:03d}.npz"
        if f.exists():
            with np.load(f) as z:
                out[t] = {k: z[k] for k in z.files}
    return out


def _rmse(err: np.ndarray) -> float:
    """Per-trial window RMSE (the evaluation's r_n)."""
    return float(np.sqrt(np.mean(err[W0:] ** 2)))


def _boot_ratio(a: np.ndarray, b: np.ndarray, seed: int = 0) -> tuple[float, float, float]:
    """aggregate_bound(a) / aggregate_bound(b), (N, K, M) each, paired percentile bootstrap."""
    r = ce.aggregate_bound(a, W0) / ce.aggregate_bound(b, W0)
    rng = np.random.default_rng(seed)
    n = len(a)
    rs = [ce.aggregate_bound(a[i], W0) / ce.aggregate_bound(b[i], W0) for i in (rng.integers(0, n, n) for _ in range(BOOT))]
    return r, float(np.percentile(rs, 2.5)), float(np.percentile(rs, 97.5))


def path_features(path: np.ndarray, targets: np.ndarray, speed_max: float) -> dict:
    """Range, bearing rate and speed of a UAV path (K, 2) against the true targets (K, M, 2)."""
    d = targets - path[:, None]
    rng_m = np.linalg.norm(d, axis=2)  # (K, M)
    phi = np.arctan2(d[..., 0], d[..., 1])
    rate = np.abs((np.diff(phi, axis=0) + np.pi) % (2 * np.pi) - np.pi)  # (K-1, M) rad per tick
    speed = np.linalg.norm(np.diff(path, axis=0), axis=1)
    cen = targets.mean(axis=1)
    to_cen = np.linalg.norm(cen - path, axis=1)
    near = np.flatnonzero(to_cen < 150.0)
    return dict(range_t=rng_m.mean(axis=1), rate_t=np.degrees(rate.mean(axis=1)), speed_t=speed,
                to_final_t=np.linalg.norm(targets[-1].mean(axis=0) - path, axis=1),
                first_near_s=float(near[0]) if len(near) else float("nan"),
                full_speed=float(np.mean(speed[W0:] > 0.97 * speed_max)),
                min_range_t=rng_m.min(axis=1))


def _phase(x: np.ndarray, a: int, b: int) -> float:
    return float(np.mean(x[a:b]))


def report(args) -> dict:
    out = Path(args.out)
    trials = list(range(args.first, args.first + args.trials))
    setup = _setup()
    data = {t: load_trial(Path(args.cache), args.seed, t) for t in trials}
    ref = {}
    ref_file = ROOT / "docs/results_flight/per_trial.csv"
    if ref_file.exists():
        with open(ref_file, encoding="utf-8") as f:
            ref = {int(r["trial"]): float(r["rmse_window_m"]) for r in csv.DictReader(f) if r["method"] == "flight@stock"}
    match = sum(1 for t in trials if t in ref and f"{_rmse(data[t][f'{FLIGHT}.error_m']):.4f}" == f"{ref[t]:.4f}")
    print(f"truths: flight@stock per-trial RMSE equals docs/results_flight/per_trial.csv to 4 decimals on "
          f"{match} of {len(trials)} trials")
    runs = {}
    for sp, ac in ((9.0, 2.5), (20.0, 20.0 / 9.0 * 2.5)):
        for starts in ("quick", "all"):
            r = _load_dir(out / label(sp, round(ac, 2)) / starts, trials)
            if r:
                runs[(sp, starts)] = r
    check = _load_dir(out / label(9.0, 2.5) / "check", trials)
    mm = _load_dir(out / label(9.0, 2.5) / "aggregate", trials)
    hop = _load_dir(out / label(9.0, 2.5) / "hop", trials)
    greedy = _load_dir(out / "greedy", trials)
    res: dict = {"truths_match": match, "trials": len(trials)}
    res.update(_aggregate(trials, data, runs, greedy))
    if check:
        res["check"] = _check_table(check, runs.get((9.0, "quick"), {}), hop)
    if len(mm) == len(trials) and (9.0, "quick") in runs:
        before = ce.aggregate_bound(np.stack([runs[(9.0, "quick")][t]["bound_m2"] for t in trials]), W0)
        after = ce.aggregate_bound(np.stack([mm[t]["bound_m2"] for t in trials]), W0)
        res["aggregate_round"] = {"before_m": round(before, 4), "after_m": round(after, 4),
                                  "improved_trials": int(sum(bool(mm[t]["improved"]) for t in trials))}
        print(f"\none majorise-minimise round on the N-trial bound: {before:.4f} -> {after:.4f} m "
              f"({100 * (after / before - 1):+.2f} %, {res['aggregate_round']['improved_trials']} trials moved)")
    res["features"] = _features(trials, data, runs, greedy, setup)
    if (9.0, "quick") in runs:
        res["counterfactual"] = _counterfactual(trials, data, runs[(9.0, "quick")], setup)
    res["route_pursuit_mps"] = _route_pursuit_speed()
    _per_trial_csv(Path(args.figures or out) / "per_trial.csv", trials, data, runs, greedy)
    if args.figures:
        _figures(Path(args.figures), trials, data, runs, greedy)
    return res


def _aggregate(trials, data, runs, greedy) -> dict:
    """N-trial bound_m of each path set (the evaluation's formula) on the trials each has."""
    res = {}
    fb = {t: data[t][f"{FLIGHT}.bound_m2"] for t in trials}
    print("\n| path | trials | PCRB [m] | flight / it (95 % CI) | flight RMSE [m] on them |")
    print("|---|---:|---:|---|---:|")
    have = [t for t in trials]
    err = np.stack([data[t][f"{FLIGHT}.error_m"] for t in have])
    rmse = float(np.sqrt(np.mean(err ** 2, axis=0))[W0:].mean())
    print(f"| flight@stock (flown) | {len(have)} | {ce.aggregate_bound(np.stack([fb[t] for t in have]), W0):.2f} | — | {rmse:.1f} |")
    res["flight"] = {"trials": len(have), "bound_m": round(ce.aggregate_bound(np.stack([fb[t] for t in have]), W0), 3),
                     "rmse_m": round(rmse, 2)}
    sets = {f"ceiling {sp:g} m/s ({st})": r for (sp, st), r in runs.items()}
    sets.update({"myopic9 (one-step greedy, 9 m jumps)": {t: {"bound_m2": g["bound_m2"]} for t, g in greedy.items()}})
    for name, r in sets.items():
        ts = [t for t in trials if t in r]
        if len(ts) < 2:
            continue
        b = np.stack([r[t]["bound_m2"] for t in ts])
        f = np.stack([fb[t] for t in ts])
        v, lo, hi = _boot_ratio(f, b)
        e = np.stack([data[t][f"{FLIGHT}.error_m"] for t in ts])
        rm = float(np.sqrt(np.mean(e ** 2, axis=0))[W0:].mean())
        print(f"| {name} | {len(ts)} | {ce.aggregate_bound(b, W0):.2f} | {v:.3f} ({lo:.3f}, {hi:.3f}) | {rm:.1f} |")
        res[name] = {"trials": len(ts), "bound_m": round(ce.aggregate_bound(b, W0), 3),
                     "flight_over": [round(v, 4), round(lo, 4), round(hi, 4)],
                     "flight_bound_m": round(ce.aggregate_bound(f, W0), 3)}
        if "greedy" in name or "myopic" in name:
            ge = np.stack([greedy[t]["error_m"] for t in ts])
            res[name]["rmse_m"] = round(float(np.sqrt(np.mean(ge ** 2, axis=0))[W0:].mean()), 2)
            res[name]["flight_rmse_m"] = round(rm, 2)
            print(f"|   myopic9 RMSE on them | {len(ts)} | | | {res[name]['rmse_m']:.1f} (flight {rm:.1f}) |")
            res["myopic9_rmse"] = _myopic_rmse(ts, data, greedy)
    r9, r20 = runs.get((9.0, "quick")), runs.get((20.0, "quick"))
    if r9 and r20:
        ts = [t for t in trials if t in r9 and t in r20]
        if len(ts) >= 2:
            v, lo, hi = _boot_ratio(np.stack([r9[t]["bound_m2"] for t in ts]), np.stack([r20[t]["bound_m2"] for t in ts]))
            print(f"\nceiling 9 m/s / ceiling 20 m/s on {len(ts)} trials: {v:.3f} ({lo:.3f}, {hi:.3f})")
            res["ceiling9_over_ceiling20"] = [round(v, 4), round(lo, 4), round(hi, 4), len(ts)]
    if r9:
        res.update(_ceiling9(r9))
    return res


def _ceiling9(r9: dict) -> dict:
    """The 9 m/s ceiling's winning starts, its speed and turn radius at 60-99 s, its CPU per trial."""
    res: dict = {}
    wins: dict = {}
    for t in r9:
        name = str(r9[t]["names"][int(r9[t]["refined"][np.argmin(r9[t]["refined_values"])])])
        if float(r9[t]["value"]) < float(np.min(r9[t]["refined_values"])) - 1e-12:
            name = "a start as it is"
        wins[name] = wins.get(name, 0) + 1
    res["winning_start_9"] = wins
    print(f"\nthe 9 m/s ceiling came from (refined start: trials): {wins}")
    rad, spd = [], []
    for t in r9:
        a = r9[t]["acc"]
        v = np.vstack([[0.0, 0.0], np.cumsum(a, axis=0)])
        sp = np.linalg.norm(v[60:-1], axis=1)
        an = np.abs(v[60:-1, 0] * a[60:, 1] - v[60:-1, 1] * a[60:, 0]) / np.maximum(sp, 1e-9)
        keep = (sp > 0.5) & (an > 1e-3)
        rad += list(sp[keep] ** 2 / an[keep])
        spd += list(np.linalg.norm(v[60:], axis=1))
    res["ceiling9_60_99"] = {"speed_median_mps": round(float(np.median(spd)), 2),
                             "turn_radius_quartiles_m": np.percentile(rad, [25, 50, 75]).round(1).tolist()}
    print(f"the 9 m/s ceiling at 60-99 s: speed {np.median(spd):.2f} m/s (median), turn radius "
          f"{res['ceiling9_60_99']['turn_radius_quartiles_m']} m (quartiles)")
    cpu = [float(r9[t]["cpu_s"]) for t in r9]
    res["cpu_s_per_trial"] = {"median": round(float(np.median(cpu)), 1), "max": round(float(np.max(cpu)), 1),
                              "total_min": round(float(np.sum(cpu)) / 60, 1)}
    print(f"\nCPU per trial (9 m/s, quick): median {np.median(cpu):.1f} s, max {np.max(cpu):.1f} s, "
          f"total {np.sum(cpu) / 60:.1f} min for {len(cpu)} trials")
    return res


def _rmse_agg(err: np.ndarray) -> float:
    """The evaluation's RMSE over trials: (N, K, M) errors -> rmse_mean_m."""
    return float(np.sqrt(np.mean(err ** 2, axis=0))[W0:].mean())


def _myopic_rmse(ts, data, greedy) -> dict:
    """The myopic path's RMSE against the flight's: on trials 0-9 (the issue's), 10-19 and all,
    the paired bootstrap ratio, and the trials where it is lower."""
    f = np.stack([data[t][f"{FLIGHT}.error_m"] for t in ts])
    g = np.stack([greedy[t]["error_m"] for t in ts])
    out = {}
    for lo, hi in ((0, 10), (10, 20), (0, len(ts))):
        if hi <= len(ts):
            out[f"{lo}-{hi - 1}"] = [round(_rmse_agg(g[lo:hi]), 2), round(_rmse_agg(f[lo:hi]), 2)]
    rng = np.random.default_rng(0)
    n = len(ts)
    rs = [_rmse_agg(g[i]) / _rmse_agg(f[i]) for i in (rng.integers(0, n, n) for _ in range(BOOT))]
    out["ratio"] = [round(_rmse_agg(g) / _rmse_agg(f), 4), round(float(np.percentile(rs, 2.5)), 4),
                    round(float(np.percentile(rs, 97.5)), 4)]
    per_f, per_g = np.sqrt(np.mean(f[:, W0:] ** 2, axis=(1, 2))), np.sqrt(np.mean(g[:, W0:] ** 2, axis=(1, 2)))
    out["lower_on"] = int(np.sum(per_g < per_f))
    print("myopic9 / flight RMSE: " + ", ".join(f"trials {k}: {v[0]:.1f} vs {v[1]:.1f} m" for k, v in out.items()
                                                  if "-" in k)
          + f"; ratio {out['ratio'][0]:.2f} ({out['ratio'][1]:.2f}, {out['ratio'][2]:.2f}); lower on {out['lower_on']}"
          f" of {n} trials")
    return out


def _check_table(check: dict, quick: dict, hop: dict) -> dict:
    """How near the searches are to the best path known, per trial."""
    rows = []
    print("\n| trial | quick (the run) | all starts | basin hopping from the run | CEM (2 seeds) | CEM + SQP | best known "
          "| coarse optima: min-max over starts |")
    print("|---:|---:|---:|---:|---|---|---:|---|")
    for t, c in sorted(check.items()):
        hv = float(hop[t]["best"]) if t in hop else float("nan")
        vals = [float(c["full"]), hv, *map(float, c["cem"]), *map(float, c["cem_polished"])]
        qv = float(quick[t]["value"]) if t in quick else float("nan")
        best = np.nanmin([qv, *vals])
        loc = c["full_local"][np.isfinite(c["full_local"])]
        rows.append(dict(trial=t, quick=qv / best - 1, full=float(c["full"]) / best - 1, hop=hv / best - 1,
                         cem=[float(v) / best - 1 for v in c["cem"]],
                         cem_sqp=[float(v) / best - 1 for v in c["cem_polished"]],
                         spread=float(loc.max() / loc.min() - 1)))
        print(f"| {t} | {qv:.3f} | {float(c['full']):.3f} | {hv:.3f} | {c['cem'][0]:.3f}, {c['cem'][1]:.3f} | "
              f"{c['cem_polished'][0]:.3f}, {c['cem_polished'][1]:.3f} | {best:.3f} | {loc.min():.3f}-{loc.max():.3f} |")

    def pct(key, agg=np.mean):
        v = np.array([np.min(r[key]) if isinstance(r[key], list) else r[key] for r in rows], float)
        return round(100 * float(agg(v[np.isfinite(v)])), 2)
    out = {"n": len(rows), "quick_gap_mean_pct": pct("quick"), "quick_gap_max_pct": pct("quick", np.max),
           "all_gap_mean_pct": pct("full"), "all_gap_max_pct": pct("full", np.max),
           "hop_gap_mean_pct": pct("hop"), "hop_gap_max_pct": pct("hop", np.max),
           "hop_trials": int(sum(np.isfinite(r["hop"]) for r in rows)),
           "best_on": {k: int(sum(np.min(r[k]) < 1e-11 for r in rows)) for k in ("quick", "full", "hop", "cem_sqp")},
           "quick_second_max_pct": round(100 * float(np.sort([r["quick"] for r in rows])[-2]), 2),
           "cem_gap_mean_pct": pct("cem"), "cem_sqp_gap_mean_pct": pct("cem_sqp"),
           "cem_sqp_gap_max_pct": pct("cem_sqp", np.max),
           "coarse_spread_median_pct": round(100 * float(np.median([r["spread"] for r in rows])), 2),
           "cem_sqp_below_quick": int(sum(min(r["cem_sqp"]) < r["quick"] - 1e-9 for r in rows))}
    print(f"\ngap to the best known (mean / max over {len(rows)} trials): quick {out['quick_gap_mean_pct']} / "
          f"{out['quick_gap_max_pct']} %, all starts {out['all_gap_mean_pct']} / {out['all_gap_max_pct']} %, "
          f"basin hopping {out['hop_gap_mean_pct']} / {out['hop_gap_max_pct']} % ({out['hop_trials']} trials), "
          f"CEM (better seed) {out['cem_gap_mean_pct']} %, CEM + SQP {out['cem_sqp_gap_mean_pct']} / "
          f"{out['cem_sqp_gap_max_pct']} %; local optima from the starts span {out['coarse_spread_median_pct']} % "
          f"(median); CEM + SQP below the quick search on {out['cem_sqp_below_quick']} trials; the best known "
          f"from (quick, all starts, hopping, CEM + SQP) on {out['best_on']} trials; quick's second-largest gap "
          f"{out['quick_second_max_pct']} %")
    return out


def _paths(trials, data, runs, greedy) -> dict[str, dict[int, np.ndarray]]:
    ps = {"flight@stock": {t: data[t][f"{FLIGHT}.uav"][:, :2] for t in trials}}
    for (sp, st), r in runs.items():
        if st == "quick":
            ps[f"ceiling {sp:g} m/s"] = {t: r[t]["path"] for t in r}
    if greedy:
        ps["myopic9"] = {t: g["uav"][:, :2] for t, g in greedy.items()}
    return ps


def _features(trials, data, runs, greedy, setup) -> dict:
    ps = _paths(trials, data, runs, greedy)
    res = {}
    print("\n| path | trials | range 10-30 / 30-60 / 60-100 s [m] | bearing rate 10-30 / 30-60 / 60-100 s [deg/s] "
          "| PCRB 10-30 / 30-60 / 60-100 s [m] | first within 150 m of the centroid [s] | at full speed | "
          "to the final centroid at 30 / 60 s [m] |")
    print("|---|---:|---|---|---|---:|---:|---|")
    for name, p in ps.items():
        ts = sorted(p)
        speed = 9.0 if "9" in name or name.startswith("flight") else 20.0
        fs = [path_features(p[t], data[t]["truth"][:, :, :2], speed) for t in ts]
        if name == "flight@stock":
            b = np.stack([data[t][f"{FLIGHT}.bound_m2"] for t in ts])
        elif name == "myopic9":
            b = np.stack([greedy[t]["bound_m2"] for t in ts])
        else:
            r = runs[(float(name.split()[1]), "quick")]
            b = np.stack([r[t]["bound_m2"] for t in ts])
        bt = np.sqrt(b.mean(axis=0)).mean(axis=1)
        rng_t = np.mean([f["range_t"] for f in fs], axis=0)
        rate_t = np.mean([f["rate_t"] for f in fs], axis=0)
        to_fin = np.mean([f["to_final_t"] for f in fs], axis=0)
        near = np.nanmedian([f["first_near_s"] for f in fs])
        full = float(np.mean([f["full_speed"] for f in fs]))
        print(f"{name}: mean range at 35 / 45 s {rng_t[35]:.0f} / {rng_t[45]:.0f} m")
        res[name] = dict(trials=len(ts), range_m=[round(_phase(rng_t, a, z), 0) for a, z in PHASES],
                         rate_dps=[round(_phase(rate_t, a - 1, z - 1), 2) for a, z in PHASES],
                         bound_m=[round(_phase(bt, a, z), 2) for a, z in PHASES], first_near_s_median=near,
                         full_speed=round(full, 3), to_final_30_60=[round(float(to_fin[30]), 0), round(float(to_fin[60]), 0)],
                         range_window_m=round(float(rng_t[W0:].mean()), 0))
        x = res[name]
        print(f"| {name} | {len(ts)} | {' / '.join(f'{v:.0f}' for v in x['range_m'])} | "
              f"{' / '.join(f'{v:.2f}' for v in x['rate_dps'])} | {' / '.join(f'{v:.2f}' for v in x['bound_m'])} | "
              f"{near:.0f} | {100 * full:.0f} % | {x['to_final_30_60'][0]:.0f} / {x['to_final_30_60'][1]:.0f} |")
    return res


def _route_pursuit_speed(vmax: float = 9.0, accel: float = 2.5) -> list[float]:
    """The speed the flight planner's route pursuit (``routes.fly_routes``) settles at on a straight
    2 km route at v_max 9 m/s, from rest and from 9 m/s: the mean over ticks 20-49 and 5-9."""
    from onboard.core.planning.inputs import CandidateGrid, UavMotion, UavState
    from onboard.core.planning.routes import fly_routes, sample_routes

    motion, grid = UavMotion("vehicle", vmax, accel, 0.0), CandidateGrid(5.0, 4, 15, 40.0)
    route = sample_routes([np.array([[0.0, 0.0], [2000.0, 0.0]])], 40.0, vmax * 52, 2.0)[:1]  # turning left
    out = []
    for v0, ticks in ((0.0, slice(20, 50)), (vmax, slice(5, 10))):
        _, vel = fly_routes(route, UavState(np.zeros(2), np.array([v0, 0.0])), motion, grid, 50, 1.0, 2.0)
        out.append(round(float(np.linalg.norm(vel[0, ticks], axis=1).mean()), 2))
    print(f"\nthe flight's route pursuit on a straight route at v_max {vmax:g} m/s settles at {out[0]:.2f} m/s "
          f"from rest, {out[1]:.2f} m/s from {vmax:g} m/s")
    return out


def _arrival(path: np.ndarray, centroid: np.ndarray, radius_m: float) -> int:
    """First tick the path is within radius_m of the targets' (moving) centroid; K if never."""
    near = np.flatnonzero(np.linalg.norm(path - centroid, axis=1) < radius_m)
    return int(near[0]) if len(near) else len(path)


def _counterfactual(trials, data, ceil, setup, at: int = 60, radius_m: float = 30.0) -> dict:
    """The bound on spliced sensor positions, to attribute the ceiling's lead (the splices are
    not all flyable; they say what a part of the path is worth): the ceiling holding still from
    ``at`` s (the last phase's approach), and on the targets' moving centroid from when it first
    comes within radius_m of it (weaving against sitting in the middle of the targets)."""
    ts = [t for t in trials if t in ceil]

    def on_centroid(p, c):
        k = _arrival(p, c, radius_m)
        return np.r_[p[:k], c[k:]]
    variants = {"ceiling": lambda p, c, f: p,
                f"ceiling, holding still from {at} s": lambda p, c, f: np.r_[p[:at], np.repeat(p[at - 1:at], len(p) - at, 0)],
                f"ceiling, on the targets' centroid once within {radius_m:g} m of it": lambda p, c, f: on_centroid(p, c),
                f"flight, on the targets' centroid once within {radius_m:g} m of it": lambda p, c, f: on_centroid(f, c),
                "flight": lambda p, c, f: f}
    out = {}
    arr = {"ceiling": [], "flight": []}
    print(f"\n| sensor positions | PCRB [m] | {at}-100 s [m] |")
    print("|---|---:|---:|")
    for name, fn in variants.items():
        bs = []
        for t in ts:
            d = data[t]
            pb = ce.problem_for_trial(setup, d["truth"], d["gains"], d["start"], W0, 9.0, 2.5)
            c, f = pb.targets.mean(axis=1), d[f"{FLIGHT}.uav"][:, :2]
            bs.append(ce.bound_m2(pb, fn(ceil[t]["path"], c, f)[None])[0])
            if name in arr:
                arr[name].append(_arrival(ceil[t]["path"] if name == "ceiling" else f, c, radius_m))
        b = np.stack(bs)
        late = float(np.sqrt(b.mean(axis=0)).mean(axis=1)[at:].mean())
        out[name] = [round(ce.aggregate_bound(b, W0), 3), round(late, 3)]
        print(f"| {name} | {out[name][0]:.2f} | {late:.2f} |")
    for name, a in arr.items():
        a = np.array(a)
        out[f"{name} arrival"] = {"within_radius_share": round(float(np.mean(a < 100)), 3),
                                  "median_s": float(np.median(a[a < 100])) if np.any(a < 100) else None}
        print(f"{name}: within {radius_m:g} m of the targets' centroid on {np.sum(a < 100)} of {len(a)} trials, "
              f"first at {np.median(a[a < 100]) if np.any(a < 100) else float('nan'):.0f} s (median)")
    return out


def _per_trial_csv(path: Path, trials, data, runs, greedy) -> None:
    cols = ["trial", "flight_rmse_m", "flight_pcrb_m"]
    keys = sorted(runs)
    cols += [f"ceiling_{sp:g}_{st}_pcrb_m" for sp, st in keys] + ["myopic9_rmse_m", "myopic9_pcrb_m"]
    lines = [",".join(cols)]
    path.parent.mkdir(parents=True, exist_ok=True)
    for t in trials:
        d = data[t]
        row = [str(t), f"{_rmse(d[f'{FLIGHT}.error_m']):.4f}", f"{np.sqrt(d[f'{FLIGHT}.bound_m2'][W0:]).mean():.4f}"]
        row += [f"{float(runs[k][t]['value']):.4f}" if t in runs[k] else "" for k in keys]
        g = greedy.get(t)
        row += ["", ""] if g is None else [f"{_rmse(g['error_m']):.4f}", f"{np.sqrt(g['bound_m2'][W0:]).mean():.4f}"]
        lines.append(",".join(row))
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"\nper-trial table: {path}")


def _figures(outdir: Path, trials, data, runs, greedy) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    outdir.mkdir(parents=True, exist_ok=True)
    ps = _paths(trials, data, runs, greedy)
    colors = {"flight@stock": "tab:blue", "ceiling 9 m/s": "tab:red", "ceiling 20 m/s": "tab:purple",
              "myopic9": "tab:green"}
    _paths_figure(plt, outdir, trials, data, ps, colors)
    _time_figures(plt, outdir, data, ps, colors)
    _bound_figure(plt, outdir, data, runs, greedy, ps, colors)
    print(f"figures: {outdir}")


def _paths_figure(plt, outdir: Path, trials, data, ps: dict, colors: dict) -> None:
    """ceiling_paths.png: the paths of the first three trials every method has, whole and zoomed."""
    from matplotlib.patches import Rectangle

    setup = _setup()
    show = [t for t in trials[:6] if all(t in p for p in ps.values())][:3]
    fig, axes = plt.subplots(2, len(show), figsize=(6.5 * len(show), 13), squeeze=False)
    n, b, lo, hi = setup.uav_obstacles.lateral()
    for col, t in enumerate(show):
        truth = data[t]["truth"]
        fin = truth[-1, :, :2].mean(axis=0)
        for row, ax in enumerate(axes[:, col]):
            k0 = 0 if row == 0 else 60  # the zoom: the last 40 s round the targets' final centroid
            for k in range(len(b)):
                blocking = lo[k] < setup.grid.altitude_m < hi[k]
                x0, x1, y0, y1 = -b[k, 2], b[k, 0], -b[k, 3], b[k, 1]
                ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, color="0.35" if blocking else "0.8", alpha=0.6))
            for j in range(truth.shape[1]):
                ax.plot(truth[k0:, j, 0], truth[k0:, j, 1], color="k", lw=0.8, alpha=0.6,
                        label="targets (truth)" if j == 0 else None)
                ax.plot(truth[k0::10, j, 0], truth[k0::10, j, 1], "k.", ms=3)
            for name, p in ps.items():
                q = p[t][k0:]
                c = colors.get(name, "tab:gray")
                ax.plot(q[:, 0], q[:, 1], color=c, lw=1.6, label=name)
                ax.plot(q[::10, 0], q[::10, 1], "o", color=c, ms=3)
                ax.plot(q[-1, 0], q[-1, 1], "s", color=c, ms=6)
            if row == 0:
                ax.plot(*data[t]["start"][:2], "k^", ms=9, label="UAV start")
                ax.set_xlim(0, 1000)
                ax.set_ylim(0, 1000)
                ax.set_title(f"trial {t} (dots every 10 s, square: end)")
            else:
                ax.set_xlim(fin[0] - 130, fin[0] + 130)
                ax.set_ylim(fin[1] - 130, fin[1] + 130)
                ax.set_title(f"trial {t}: t = 60-99 s near the targets' final centroid")
            ax.set_aspect("equal")
            ax.set_xlabel("x east [m]")
            ax.set_ylabel("y north [m]")
    axes[0][0].legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(outdir / "ceiling_paths.png", dpi=110)
    plt.close(fig)


def _time_figures(plt, outdir: Path, data, ps: dict, colors: dict) -> None:
    """ceiling_range.png, ceiling_bearing_rate.png: the mean range and bearing rate against time."""
    for key, ylab, fname in (("range_t", "mean UAV-target range [m]", "ceiling_range.png"),
                             ("rate_t", "mean |bearing rate| [deg/s]", "ceiling_bearing_rate.png")):
        fig, ax = plt.subplots(figsize=(8, 4.5))
        for name, p in ps.items():
            ts = sorted(p)
            y = np.mean([path_features(p[t], data[t]["truth"][:, :, :2], 9.0)[key] for t in ts], axis=0)
            x = np.arange(len(y)) + (0.5 if key == "rate_t" else 0.0)
            ax.plot(x, y, color=colors.get(name, "tab:gray"), label=f"{name} ({len(ts)} trials)")
        ax.set_xlabel("t [s]")
        ax.set_ylabel(ylab)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(outdir / fname, dpi=110)
        plt.close(fig)


def _bound_figure(plt, outdir: Path, data, runs, greedy, ps: dict, colors: dict) -> None:
    """ceiling_bound.png: each path's PCRB against time, averaged as pmon eval averages it."""
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, p in ps.items():
        ts = sorted(p)
        if name == "flight@stock":
            bb = np.stack([data[t][f"{FLIGHT}.bound_m2"] for t in ts])
        elif name == "myopic9":
            bb = np.stack([greedy[t]["bound_m2"] for t in ts])
        else:
            r = runs[(float(name.split()[1]), "quick")]
            bb = np.stack([r[t]["bound_m2"] for t in ts])
        ax.plot(np.sqrt(bb.mean(axis=0)).mean(axis=1), color=colors.get(name, "tab:gray"), label=f"{name} ({len(ts)} trials)")
    ax.axvline(W0, color="0.6", ls=":")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("PCRB [m] (as pmon eval averages it)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(outdir / "ceiling_bound.png", dpi=110)
    plt.close(fig)
