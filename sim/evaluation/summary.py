"""The evaluation's summary of its trials (sim.evaluation.trials runs them; sim.evaluation.metrics holds the
statistics, sim.evaluation.report the outputs).

Metrics (``summarise``), all on the horizontal position (x, y) in metres:

* eps_t (the paper's RMSE at step t): sqrt of the mean over trials of |x^_t - x_t|^2, per target;
  "averaged over targets" is the mean over the M targets of the per-target eps_t;
* ``rmse_mean_m``: the time average of the target-averaged eps_t over the convergence window
  t in [window_start, K) (default: from 10 s on; the second half if the mission is shorter);
* per-trial RMSE r_n = sqrt(mean over window steps and targets of |error|^2): the paired
  differences r_n(method) - r_n(greedy_l1) over the same trials, with a 95 % t-interval;
* ``uav_vs_fixed_ratio`` = rmse_mean_m(greedy_l1) / rmse_mean_m(fixed3), 95 % CI by a paired
  percentile bootstrap over trials (trials resampled with replacement, both methods together);
* NEES on the 2-D position: e^T P^-1 e with P the filter's (x, y) covariance; a consistent
  filter has E = 2. The average over N trials, per step and target (ANEES), has the 95 % band
  [chi2_(0.025)(2N), chi2_(0.975)(2N)] / N. ``nees_mean`` is ANEES averaged over targets and the
  window; ``nees_in_band`` is the fraction of (step, target) cells whose ANEES is in the band.
  (The full 6-D state is not used: z and v_z have variances of 1e-10 by construction and their
  NEES would measure round-off.)
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from sim.evaluation.config import EvalConfig, _setup_for
from sim.evaluation.methods import Method
from sim.evaluation.metrics import (FIXED, REFERENCE, MethodSummary, MethodTrace, Summary, TrialResult, bound_summary, is_flight,
                         motion_stats, nees_band, paired_bound_ratio, paired_ratio, t_interval, truth_stats)


def _flown_stats(cfg: EvalConfig, method: Method, traces: Sequence[MethodTrace]) -> dict:
    """How a flown method's vehicle followed its plans: the flown position's distance from the
    planned one at the next tick (median, p95, max over all ticks and trials), the plan's and
    the vehicle's speeds (mean over ticks, max), and the limits it planned and flew with."""
    if traces[0].plan_miss_m is None:
        return {}
    miss = np.concatenate([t.plan_miss_m for t in traces])
    plan_v = np.concatenate([t.plan_speed_mps for t in traces])
    v = np.concatenate([t.speed_mps for t in traces])
    setup, _, limits = _setup_for(cfg, method)
    return dict(autopilot=method.autopilot or "stock", wpnav_speed_mps=limits.speed_xy,
                wpnav_accel_mps2=limits.accel_xy, plan_speed_max_mps=setup.motion.speed_max_mps,
                plan_accel_max_mps2=setup.motion.accel_max_mps2,
                miss_median_m=float(np.median(miss)), miss_p95_m=float(np.percentile(miss, 95)),
                miss_max_m=float(miss.max()), planned_speed_mean_mps=float(plan_v.mean()),
                planned_speed_peak_mps=float(plan_v.max()), speed_mean_mps=float(v.mean()),
                speed_peak_mps=float(v.max()))


def summarise(cfg: EvalConfig, trials: Sequence[TrialResult], wall_s: float = float("nan")) -> Summary:
    N, w0 = len(trials), cfg.window_start
    band = nees_band(N)
    out: dict[str, MethodSummary] = {}
    errs = {m.name: np.stack([t.traces[m.name].error_m for t in trials]) for m in cfg.methods}  # (N, K, M)
    ref_r = None
    if REFERENCE in errs:
        ref_err = errs[REFERENCE]
        ref_r = np.sqrt(np.mean(ref_err[:, w0:] ** 2, axis=(1, 2)))
    full_step = cfg.scenario.uav.n_radial * cfg.scenario.uav.step_m
    for m in cfg.methods:
        err = errs[m.name]
        nees = np.stack([t.traces[m.name].nees for t in trials])
        eps = np.sqrt(np.mean(err ** 2, axis=0))
        anees = nees.mean(axis=0)
        per_trial = np.sqrt(np.mean(err[:, w0:] ** 2, axis=(1, 2)))
        filtered = ref_r is not None and not m.bound_only
        diff = t_interval(per_trial - ref_r) if filtered else None
        ratio_ref = paired_ratio(ref_err, err, w0, cfg.seed) if filtered else None
        motion: dict = {}
        if m.sensing != "fixed":
            st = [motion_stats(t.traces[m.name], t.truth) for t in trials]
            steps = np.concatenate([s["step_m"] for s in st])
            motion = dict(
                mean_step_m=float(steps.mean()),
                full_step_fraction=float(np.mean(steps > full_step - 1e-3)),
                stay_fraction=float(np.mean(steps < 1e-3)),
                mean_away_m=float(np.mean(np.concatenate([s["away_m"] for s in st]))),
                mean_across_m=float(np.mean(np.concatenate([s["across_m"] for s in st]))),
                mean_range_m=float(np.mean([s["range_m"][w0:].mean() for s in st])),
            )
        out[m.name] = MethodSummary(
            m.name, m.description, eps, eps.mean(axis=1), float(eps.mean(axis=1)[w0:].mean()),
            eps[w0:].mean(axis=0), per_trial, anees, float(anees[w0:].mean()),
            float(np.mean((anees[w0:] >= band[0]) & (anees[w0:] <= band[1]))), diff, ratio_ref, motion,
            1e3 * float(np.mean([t.traces[m.name].tick_s for t in trials])),
            int(sum(t.traces[m.name].degenerate for t in trials)),
            *bound_summary([t.traces[m.name].bound_m2 for t in trials], w0),
            vs_jump=None if m.jump_twin not in errs else (m.jump_twin, paired_ratio(err, errs[m.jump_twin], w0,
                                                                                       cfg.seed)),
            flown=_flown_stats(cfg, m, [t.traces[m.name] for t in trials]),
            truth={} if m.bound_only else truth_stats([t.traces[m.name] for t in trials], w0, cfg.dt_s))
    ratio = ratio_ci = None
    if REFERENCE in out and FIXED in out:
        # the headline is the table's fixed3 row, so the two print one CI
        ratio, lo, hi = out[FIXED].ratio_vs_ref
        ratio_ci = (lo, hi) if N > 1 else None
    speed = np.linalg.norm(np.stack([t.truth[:, :, 3:5] for t in trials]), axis=-1).mean(axis=(0, 2))  # (K,)
    per10 = int(round(10.0 / cfg.dt_s))
    speed_10s = tuple(float(speed[k:k + per10].mean()) for k in range(0, len(speed), per10))
    filtered = [m.name for m in cfg.methods if not m.bound_only]
    pairs = {(a, b): (paired_ratio(errs[a], errs[b], w0, cfg.seed),
                      t_interval(out[a].per_trial_rmse - out[b].per_trial_rmse))
             for a in filtered if is_flight(a) for b in filtered if b != a}
    return Summary(cfg, out, band, ratio, ratio_ci, wall_s, N, speed_10s, pairs, _over_ceiling(cfg, trials))


def _over_ceiling(cfg: EvalConfig, trials: Sequence[TrialResult]) -> dict:
    """Each UAV method's PCRB over the (first) bound-only method's, paired over the trials
    (``Summary.ceiling``)."""
    ceil = next((m for m in cfg.methods if m.bound_only), None)
    if ceil is None:
        return {}
    w0 = cfg.window_start
    ref = np.stack([t.traces[ceil.name].bound_m2 for t in trials])
    ratios, limits = {}, {}
    for m in cfg.methods:
        if m.sensing == "fixed":
            continue
        mo = _setup_for(cfg, m)[0].motion
        limits[m.name] = (f"{mo.speed_max_mps:g} m/s, {mo.accel_max_mps2:g} m/s²" if mo.kind == "vehicle" else
                          f"jumps of {cfg.scenario.uav.n_radial * cfg.scenario.uav.step_m:g} m")
        if m.sensing == "uav":
            b = np.stack([t.traces[m.name].bound_m2 for t in trials])
            per_trial = np.sqrt(b[:, w0:].mean(axis=(1, 2)) / ref[:, w0:].mean(axis=(1, 2)))
            ratios[m.name] = (paired_bound_ratio(b, ref, w0, cfg.seed), per_trial)
    return {"name": ceil.name, "limits": limits, "ratios": ratios}
