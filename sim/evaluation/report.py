"""The evaluation's outputs: the JSON headline, the CSV files, results.md and the figures
(``write_outputs``), from a ``sim.evaluation.trials.summarise`` summary."""
from __future__ import annotations

import math
import os
import platform
from typing import TYPE_CHECKING, Sequence

import numpy as np

from sim.evaluation.methods import method_scenario
from sim.evaluation.metrics import BOOTSTRAP_RESAMPLES, FIXED, REFERENCE
from sim.evaluation.numerics import numerics_description

if TYPE_CHECKING:
    from sim.evaluation.metrics import Summary, TrialResult


def headline(summary: Summary) -> dict:
    """The JSON line ``pmon eval`` ends with."""
    def r(x):
        return None if x is None or not math.isfinite(x) else round(float(x), 4)
    return {
        "methods": {n: {"rmse_mean_m": r(s.rmse_mean_m), "nees_mean": r(s.nees_mean),
                        "bound_m": r(s.bound_mean_m), "rmse_over_bound": r(s.rmse_over_bound),
                        "ratio_vs_ref": None if s.ratio_vs_ref is None else [r(v) for v in s.ratio_vs_ref],
                        **({} if s.vs_jump is None else {"ratio_vs_jump": [r(v) for v in s.vs_jump[1]]}),
                        **({} if not s.flown else {"from_plan_median_m": r(s.flown["miss_median_m"]),
                                                   "speed_peak_mps": r(s.flown["speed_peak_mps"])}),
                        **{k: (r(v) if isinstance(v, float) else v) for k, v in s.truth.items()}}
                    for n, s in summary.methods.items()},
        "truth": summary.config.truth_kind + (" (filter told)" if summary.config.told else ""),
        "uav_vs_fixed_ratio": r(summary.ratio),
        "uav_vs_fixed_ratio_ci95": None if summary.ratio_ci is None else [r(v) for v in summary.ratio_ci],
        **({} if not summary.pairs else {"flight_over": {f"{a} / {b}": [r(v) for v in ratio]
                                                          for (a, b), (ratio, _) in summary.pairs.items()}}),
        **({} if not summary.ceiling else {"pcrb_over_ceiling": {n: [r(v) for v in ratio] for n, (ratio, _)
                                                                 in summary.ceiling["ratios"].items()}}),
    }


def _bound_only(summary: Summary) -> set:
    """The methods that ran no filter (their RMSE rows are not written)."""
    return {m.name for m in summary.config.methods if m.bound_only}


def write_csv(summary: Summary, path) -> None:
    """step, method, target, rmse_m: per target (names from the scenario) and ``mean``."""
    names = [t.name for t in summary.config.scenario.targets]
    dt = summary.config.dt_s
    lines = ["step,time_s,method,target,rmse_m"]
    skip = _bound_only(summary)
    for mname, s in summary.methods.items():
        if mname in skip:
            continue
        for k in range(s.rmse_t.shape[0]):
            for j, tn in enumerate(names):
                lines.append(f"{k},{k * dt:g},{mname},{tn},{s.rmse_t[k, j]:.4f}")
            lines.append(f"{k},{k * dt:g},{mname},mean,{s.rmse_t_mean[k]:.4f}")
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


def write_per_trial_csv(summary: Summary, path) -> None:
    """trial, method, rmse_window_m (r_n): the numbers the paired differences are made of."""
    lines = ["trial,method,rmse_window_m"]
    skip = _bound_only(summary)
    for mname, s in summary.methods.items():
        if mname in skip:
            continue
        lines += [f"{n},{mname},{v:.4f}" for n, v in enumerate(s.per_trial_rmse)]
    with open(path, "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


def machine_description() -> str:
    return f"{platform.node() or 'host'}: {platform.machine()}, {os.cpu_count()} cores, {platform.system()} " \
           f"{platform.release()}, Python {platform.python_version()}"


def results_markdown(summary: Summary, command: str) -> str:
    """results.md: the run, its table, then each section that applies."""
    L = _rmse_section(summary, command)
    for section in (_fixed_ratio, _vehicle_ratios, _ceiling_section, _motion_section, _pairs_section, _flown_section,
                    _methods_section):
        L += section(summary)
    return "\n".join(L)


def _rmse_section(summary: Summary, command: str) -> list[str]:
    """The run's header and the table of RMSE and consistency per method."""
    cfg = summary.config
    dt = cfg.dt_s
    lo, hi = summary.nees_band
    names = [t.name for t in cfg.scenario.targets]
    L = [f"# Evaluation results: scenario `{cfg.scenario.name}`", "",
         f"- Command: `{command}`",
         f"- Trials: {summary.n_trials}, seed {cfg.seed}, {cfg.n_ticks} ticks of {dt:g} s "
         f"({cfg.n_ticks * dt:g} s missions); particles per target: {cfg.scenario.tracking.particles}",
         f"- Convergence window: ticks {cfg.window_start}..{cfg.n_ticks - 1} "
         f"(t = {cfg.window_start * dt:g} s to the end)",
         f"- Machine: {machine_description()}; wall time {summary.wall_s:.0f} s",
         f"- Numerics: {numerics_description()} (figures reproduce exactly where these match)", "",
         "## Time-averaged RMSE and consistency", "",
         f"RMSE: the paper's eps_t (root mean square over trials of the horizontal position error), "
         f"averaged over the {len(names)} targets and over the window. Paired difference: per-trial "
         f"window RMSE minus {REFERENCE}'s on the same trial, mean and 95 % t-interval. ANEES: 2-D "
         f"position NEES averaged over trials (consistent: 2; 95 % band for N = {summary.n_trials}: "
         f"[{lo:.2f}, {hi:.2f}]), then over targets and the window; 'in band' is the share of "
         f"(step, target) cells inside the band. Ratio: {REFERENCE}'s time-averaged RMSE over the "
         f"method's, 95 % paired percentile bootstrap CI ({BOOTSTRAP_RESAMPLES} resamples). PCRB: the posterior "
         f"Cramér-Rao bound of the position along each trial's truth and flown path (closed-loop guidance "
         f"Jacobian in the transition, information reduced by q for p_D and clutter), averaged like the RMSE; "
         f"RMSE / bound >= 1 for any estimator.", "",
         "| method | RMSE [m] | " + " | ".join(f"{n} [m]" for n in names)
         + f" | minus {REFERENCE} [m] (95 % CI) | {REFERENCE} / method (95 % CI) | PCRB [m] | RMSE / bound "
           f"| ANEES | in band | ms/tick |",
         "|---|---:|" + "---:|" * len(names) + "---|---|---:|---:|---:|---:|---:|"]
    for n, s in summary.methods.items():
        if n in _bound_only(summary):
            L.append(f"| {n} | — | " + " | ".join("—" for _ in names) + f" | — | — | {s.bound_mean_m:.1f} | — | — | — "
                     f"| {s.tick_ms:.0f} (search CPU) |")
            continue
        if s.diff_vs_ref is None or n == REFERENCE:
            d = "—"
        else:
            d = f"{s.diff_vs_ref[0]:+.1f} ({s.diff_vs_ref[1]:+.1f}, {s.diff_vs_ref[2]:+.1f})"
        if s.ratio_vs_ref is None or n == REFERENCE:
            rr = "—"
        else:
            rr = f"{s.ratio_vs_ref[0]:.2f} ({s.ratio_vs_ref[1]:.2f}, {s.ratio_vs_ref[2]:.2f})"
        L.append(f"| {n} | {s.rmse_mean_m:.1f} | " + " | ".join(f"{v:.1f}" for v in s.rmse_target_m)
                 + f" | {d} | {rr} | {s.bound_mean_m:.1f} | {s.rmse_over_bound:.2f} | {s.nees_mean:.2f} "
                   f"| {100 * s.nees_in_band:.0f} % | {s.tick_ms:.0f} |")
    L.append("")
    return L


def _fixed_ratio(summary: Summary) -> list[str]:
    """The UAV over the fixed sensors, when both ran."""
    L: list[str] = []
    if summary.ratio is not None:
        ci = "" if summary.ratio_ci is None else f", 95 % CI [{summary.ratio_ci[0]:.2f}, {summary.ratio_ci[1]:.2f}] " \
                                                  f"(paired percentile bootstrap over trials, {BOOTSTRAP_RESAMPLES} resamples)"
        L += [f"**Single UAV (Lambda = 1) over fixed sensors:** RMSE ratio {REFERENCE} / {FIXED} = "
              f"{summary.ratio:.2f}{ci}.", ""]
    return L


def _vehicle_ratios(summary: Summary) -> list[str]:
    """Each vehicle method over its jump twin."""
    cfg = summary.config
    dt = cfg.dt_s
    L: list[str] = []
    u = cfg.scenario.uav
    jump_m = u.n_radial * u.step_m
    methods = {m.name: m for m in cfg.methods}
    for n, s in summary.methods.items():
        if s.vs_jump is not None:
            pl = method_scenario(cfg.scenario, methods[n]).planning  # the limits under its policy
            equal_step = pl.speed_max_mps * dt / u.n_radial  # the grid step that makes the jump as fast
            twin, (v, a, b) = s.vs_jump
            tb = summary.methods[twin].bound_mean_m
            L += [f"**Vehicle limits:** {n} / {twin} (the same planner, jump model): RMSE ratio {v:.2f}, "
                  f"95 % CI [{a:.2f}, {b:.2f}] (paired bootstrap); PCRB ratio {s.bound_mean_m / tb:.2f}. "
                  f"The jump model moves up to {jump_m:g} m per tick, the vehicle at most {pl.speed_max_mps:g} m/s "
                  f"({pl.accel_max_mps2:g} m/s^2); the same comparison at equal speed: "
                  f"`--set uav.step_m={equal_step:g}`.", ""]
    return L


def _ceiling_section(summary: Summary) -> list[str]:
    """Each UAV method's PCRB over the clairvoyant ceiling's, paired."""
    if not summary.ceiling:
        return []
    name, limits = summary.ceiling["name"], summary.ceiling["limits"]
    L = ["## Each path's PCRB over the clairvoyant ceiling", "",
         f"`{name}`: the path a vehicle at {limits[name]} would fly knowing the true target trajectories, "
         f"chosen to minimise this PCRB (sim/evaluation/ceiling_search.py: multi-start SQP, the run's flown paths at the "
         f"same limits among the starts): PCRB {summary.methods[name].bound_mean_m:.2f} m. Ratio: a method's "
         f"PCRB over the ceiling's, averaged as the table's, 95 % paired percentile bootstrap CI over trials "
         f"({BOOTSTRAP_RESAMPLES} resamples); per trial: its window PCRB over the ceiling's. A method planned "
         f"with other limits than the ceiling's is compared with a vehicle of another speed (the column says).", "",
         "| method | planned with | PCRB [m] | over the ceiling (95 % CI) | per trial: median (min, max) |",
         "|---|---|---:|---|---|"]
    for n, ((v, lo, hi), per) in summary.ceiling["ratios"].items():
        L.append(f"| {n} | {limits[n]} | {summary.methods[n].bound_mean_m:.2f} | {v:.3f} ({lo:.3f}, {hi:.3f}) "
                 f"| {np.median(per):.3f} ({per.min():.3f}, {per.max():.3f}) |")
    L.append("")
    return L


def _motion_section(summary: Summary) -> list[str]:
    """How the UAV moved."""
    cfg = summary.config
    L: list[str] = []
    uav = {n: s for n, s in summary.methods.items() if s.motion}
    if uav:
        L += ["## How the UAV moved", "",
              "Per step (tick to tick), averaged over trials: step length; share of steps at the full "
              f"N_r Delta_r = {cfg.scenario.uav.n_radial * cfg.scenario.uav.step_m:g} m and of 'stay'; "
              "the component of the step away from the targets (+: away) and across the lines of sight "
              "(both averaged over targets); mean UAV-target range over the window.", "",
              "| method | step [m] | full steps | stays | away [m/step] | across [m/step] | range [m] |",
              "|---|---:|---:|---:|---:|---:|---:|"]
        for n, s in uav.items():
            mo = s.motion
            L.append(f"| {n} | {mo['mean_step_m']:.1f} | {100 * mo['full_step_fraction']:.0f} % | "
                     f"{100 * mo['stay_fraction']:.0f} % | {mo['mean_away_m']:+.2f} | {mo['mean_across_m']:.2f} | "
                     f"{mo['mean_range_m']:.0f} |")
        L.append("")
        if summary.target_speed_10s:
            L += ["The targets' mean true speed per 10 s of the mission [m/s]: "
                  + ", ".join(f"{v:.1f}" for v in summary.target_speed_10s) + ".", ""]
    return L


def _pairs_section(summary: Summary) -> list[str]:
    """The flight default against each method."""
    L: list[str] = []
    if summary.pairs:
        L += ["## The flight default against each method", "",
              "Paired over the same trials: the ratio of time-averaged RMSEs (flight / other; 95 % paired "
              f"percentile bootstrap CI, {BOOTSTRAP_RESAMPLES} resamples) and the mean per-trial difference of "
              "window RMSE (flight minus other; 95 % t-interval).", "",
              "| flight method | other | flight / other (95 % CI) | other / flight | flight minus other [m] (95 % CI) |",
              "|---|---|---|---:|---|"]
        for (a, b), ((v, lo, hi), (d, dlo, dhi)) in summary.pairs.items():
            L.append(f"| {a} | {b} | {v:.2f} ({lo:.2f}, {hi:.2f}) | {1 / v:.2f} | {d:+.1f} ({dlo:+.1f}, {dhi:+.1f}) |")
        L.append("")
    return L


def _flown_section(summary: Summary) -> list[str]:
    """How the vehicle flew its plans."""
    L: list[str] = []
    flown = {n: s.flown for n, s in summary.methods.items() if s.flown}
    if flown:
        L += ["## How the vehicle flew its plans", "",
              "Flown methods: at each tick the plan's position, velocity and acceleration are sent to the "
              "vehicle model fitted to ArduCopter SITL (sim/mock/guided.py), which flies with its autopilot's "
              "parameters; the next scan is where it is a tick later. Autopilot: WPNAV_SPEED, WPNAV_ACCEL "
              "of its parameter set; planned with: the planner's speed and acceleration limits; from the plan: "
              "the flown position's distance from the planned one at the next tick (median, p95, max over "
              "ticks and trials); speeds: mean over ticks / peak.", "",
              "| method | autopilot | planned with | from the plan [m] | planned speed [m/s] | flown speed [m/s] |",
              "|---|---|---|---|---|---|"]
        for n, f in flown.items():
            L.append(f"| {n} | {f['autopilot']}: {f['wpnav_speed_mps']:g} m/s, {f['wpnav_accel_mps2']:g} m/s² | "
                     f"{f['plan_speed_max_mps']:g} m/s, {f['plan_accel_max_mps2']:g} m/s² | "
                     f"{f['miss_median_m']:.2f} / {f['miss_p95_m']:.2f} / {f['miss_max_m']:.2f} | "
                     f"{f['planned_speed_mean_mps']:.1f} / {f['planned_speed_peak_mps']:.1f} | "
                     f"{f['speed_mean_mps']:.1f} / {f['speed_peak_mps']:.1f} |")
        L.append("")
    return L


def _methods_section(summary: Summary) -> list[str]:
    """The methods, the orbit, the files."""
    cfg = summary.config
    L: list[str] = []
    L += ["## Methods", ""] + [f"- `{m.name}`: {m.description}" for m in cfg.methods]
    L += ["", f"Orbit: radius {cfg.orbit_radius_m:g} m around the targets' initial centroid "
              f"({cfg.orbit_center[0]:.0f}, {cfg.orbit_center[1]:.0f}) m, counter-clockwise.",
          "", "Files: rmse.csv (step, method, target, rmse_m), per_trial.csv, rmse_vs_time.png, "
              "nees_vs_time.png, scenario_3d.png, scenario_top.png, flight.png, "
              "flown_paths.png (the UAV methods' paths side by side on the first trials).", ""]
    deg = {n: s.degenerate for n, s in summary.methods.items() if s.degenerate}
    if deg:
        L += [f"Degenerate updates (no finite weight; prior kept): {deg}", ""]
    return L


def write_outputs(summary: Summary, trials: Sequence[TrialResult], out_dir, command: str,
                  figures: bool = True) -> dict:
    """rmse.csv, per_trial.csv, results.md and the figures in out_dir; returns the headline dict."""
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_csv(summary, out / "rmse.csv")
    write_per_trial_csv(summary, out / "per_trial.csv")
    (out / "results.md").write_text(results_markdown(summary, command), encoding="utf-8")
    if figures:
        from sim.evaluation import figures as figs

        figs.rmse_vs_time(summary, out / "rmse_vs_time.png")
        figs.nees_vs_time(summary, out / "nees_vs_time.png")
        figs.scenario(summary.config.scenario, out / "scenario_3d.png", out / "scenario_top.png")
        figs.flight(summary.config, trials[0], out / "flight.png")
        figs.flown_paths(summary.config, trials, out / "flown_paths.png")
    return headline(summary)
