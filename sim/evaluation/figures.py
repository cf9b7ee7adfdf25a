"""Figures of an evaluation (matplotlib, Agg backend: no display needed).

* ``rmse_vs_time``: eps_t of every method, averaged over targets and per target (Fig. 2(c));
* ``nees_vs_time``: ANEES of every method against its 95 % band;
* ``scenario``: the scenario in 3D and top-down: obstacles, goal region, start positions with
  error ellipses, the targets' planned trajectories over the horizon with their growing
  uncertainty, and the planned control inputs (Fig. 1(a)-(d));
* ``flight``: one trial: the UAV's trajectory with the true and estimated target tracks
  (Fig. 2(a)-(b)).
"""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Polygon  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from onboard.core.dynamics import MotionModel, predict_cov  # noqa: E402
from onboard.core.guidance.predictor import GuidanceParams, GuidanceWorkspace, Solver, plan_guidance  # noqa: E402
from onboard.core.obstacles import Obstacles  # noqa: E402
from groundstation.scene import GOAL_COLOUR, box_corners, covariance_ellipse, draw_scene  # noqa: E402
from groundstation.scene import target_colour as _colour  # noqa: E402  (the one palette)

METHOD_STYLES = {
    "greedy_l1": dict(color="black", lw=2.0),
    "greedy_l8": dict(color="black", lw=1.5, ls=":"),
    "fixed3": dict(color="tab:red", lw=1.8),
    "hover": dict(color="tab:gray", lw=1.2, ls="--"),
    "orbit": dict(color="tab:blue", lw=1.2, ls="-."),
    "random": dict(color="tab:green", lw=1.2, ls="--"),
}


def _style(name: str, i: int) -> dict:
    return METHOD_STYLES.get(name, dict(color=f"C{i % 10}", lw=1.2))


def _draw_box_3d(ax, box, **kw) -> None:
    p = box_corners(box)
    faces = [p[:4], p[4:], *[[p[i], p[(i + 1) % 4], p[4 + (i + 1) % 4], p[4 + i]] for i in range(4)]]
    ax.add_collection3d(Poly3DCollection(faces, **kw))


def _ellipse(ax, mean_xy, cov_xy, n_sigma=2.0, **kw) -> None:
    c = np.asarray(cov_xy, float)
    pts = covariance_ellipse(mean_xy[0], mean_xy[1], np.sqrt(max(c[0, 0], 0.0)), np.sqrt(max(c[1, 1], 0.0)),
                             c[0, 1], n_sigma)
    if pts is not None:
        ax.add_patch(Polygon(pts, closed=True, **kw))


def _scene_2d(ax, sc) -> None:
    draw_scene(ax, sc)
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")


def _scene_3d(ax, sc) -> None:
    for g in sc.goals:
        _draw_box_3d(ax, g, facecolor=GOAL_COLOUR, alpha=0.3, edgecolor=GOAL_COLOUR)
    for ob in sc.obstacles:
        _draw_box_3d(ax, ob, facecolor="0.6", alpha=0.35, edgecolor="0.3")
    ax.set_xlim(sc.area.min_m[0], sc.area.max_m[0])
    ax.set_ylim(sc.area.min_m[1], sc.area.max_m[1])
    ax.set_zlim(0, max(100.0, 2 * sc.uav.altitude_m))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_box_aspect((1.0, 1.0, 0.35))


def planned_trajectories(sc):
    """Each target's P1 plan from mu_0 at t = 0, and the predicted covariances Sigma_(tau+1|0)."""
    d = sc.dynamics
    model = MotionModel.create(d.dt_s, d.friction, d.mass_kg, d.process_noise_diag)
    params = GuidanceParams.from_config(sc.guidance)
    obstacles = Obstacles.from_boxes(sc.obstacles)
    ws = GuidanceWorkspace()
    plans = [plan_guidance(model, params, obstacles, t.mean, np.asarray(sc.goal_point(t)), solver=Solver(ws))
             for t in sc.targets]
    covs = predict_cov(model, sc.initial_cov, params.horizon)
    return plans, covs


def scenario(sc, path_3d, path_top, rng_seed: int = 0) -> None:
    """Fig. 1: (a) scene and starts, (b) planned trajectories, (c) their uncertainty, (d) controls."""
    plans, covs = planned_trajectories(sc)
    T = len(covs)
    rng = np.random.default_rng(rng_seed)  # only for the illustrative samples of panel (c)
    start_uav = np.array([sc.uav.start_m[0], sc.uav.start_m[1], sc.uav.altitude_m])
    P0 = sc.initial_cov[:2, :2]

    fig = plt.figure(figsize=(8, 6.5))
    ax = fig.add_subplot(projection="3d")
    _scene_3d(ax, sc)
    for j, (t, plan) in enumerate(zip(sc.targets, plans)):
        p = np.vstack([t.mean[:3], plan.means[:, :3]])
        ax.plot(p[:, 0], p[:, 1], p[:, 2], color=_colour(j), lw=1.5, label=f"{t.name} plan ({plan.status})")
        ax.scatter(*t.mean[:3], color=_colour(j), marker="*", s=120)
    ax.scatter(*start_uav, color="black", marker="D", s=40, label="UAV start (config)")
    ax.set_title(f"Scenario '{sc.name}': obstacles, goal, targets' plans over T = {T} steps")
    ax.legend(loc="upper left", fontsize=7)
    ax.view_init(elev=35, azim=-60)
    fig.tight_layout()
    fig.savefig(path_3d, dpi=120)
    plt.close(fig)

    fig, axes = plt.subplots(2, 2, figsize=(12, 11))
    (a, b), (c, d) = axes
    for axis in (a, b, c):
        _scene_2d(axis, sc)
    for j, t in enumerate(sc.targets):
        a.plot(*t.mean[:2], marker="*", ms=14, color=_colour(j), ls="none", label=t.name)
        _ellipse(a, t.mean[:2], P0, 3.0, fill=False, color=_colour(j), lw=1.2)
    a.plot(*start_uav[:2], marker="D", color="black", ls="none", label="UAV start")
    a.set_title("(a) starts, 3-sigma error ellipses of Sigma_0, obstacles, goal")
    a.legend(fontsize=8, loc="lower left")
    for j, (t, plan) in enumerate(zip(sc.targets, plans)):
        p = np.vstack([t.mean[:2], plan.means[:, :2]])
        b.plot(p[:, 0], p[:, 1], "-o", ms=2, color=_colour(j), label=f"{t.name}: {plan.status}")
        for k in range(4, T, 5):
            _ellipse(c, plan.means[k, :2], covs[k, :2, :2], 2.0, fill=False, color=_colour(j), lw=0.8, alpha=0.7)
        samples = np.concatenate([rng.multivariate_normal(plan.means[k, :2], covs[k, :2, :2], 20) for k in range(T)])
        c.scatter(samples[:, 0], samples[:, 1], s=1, color=_colour(j), alpha=0.3)
        taus = np.arange(T)
        d.plot(taus, plan.controls[:, 0] / 1e3, color=_colour(j), lw=1.5, label=f"{t.name} u_x")
        d.plot(taus, plan.controls[:, 1] / 1e3, color=_colour(j), lw=1.0, ls="--", label=f"{t.name} u_y")
    b.set_title(f"(b) planned mean trajectories mu_(tau+1|0), T = {T}")
    b.legend(fontsize=8, loc="lower left")
    c.set_title("(c) uncertainty: samples of N(mu, Sigma_(tau+1|0)),\n2-sigma ellipses every 5 steps")
    u_max = sc.guidance.u_max_n / 1e3
    d.axhline(u_max, color="0.5", lw=0.8, ls=":")
    d.axhline(-u_max, color="0.5", lw=0.8, ls=":")
    d.set_xlabel("tau [steps]")
    d.set_ylabel("control [kN]")
    d.set_title("(d) planned control inputs u_(tau|0) (solid x, dashed y)")
    d.legend(fontsize=7, ncol=2)
    d.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path_top, dpi=110)
    plt.close(fig)


def _filtered(summary) -> dict:
    """The methods that ran a filter (a bound-only method has no RMSE or NEES)."""
    return {n: s for n, s in summary.methods.items() if np.isfinite(s.rmse_mean_m)}


def rmse_vs_time(summary, path) -> None:
    cfg = summary.config
    dt = cfg.dt_s
    names = [t.name for t in cfg.scenario.targets]
    M = len(names)
    fig = plt.figure(figsize=(12, 8))
    gs = fig.add_gridspec(2, M)
    top = fig.add_subplot(gs[0, :])
    shown = _filtered(summary)
    for i, (n, s) in enumerate(shown.items()):
        t = np.arange(len(s.rmse_t_mean)) * dt
        top.plot(t, s.rmse_t_mean, label=f"{n} ({s.rmse_mean_m:.1f} m)", **_style(n, i))
    top.axvline(cfg.window_start * dt, color="0.5", lw=0.8, ls=":")
    top.set_yscale("log")
    top.set_xlabel("t [s]")
    top.set_ylabel("RMSE eps_t [m] (mean over targets)")
    top.set_title(f"Position RMSE over {summary.n_trials} trials; legend: time average from "
                  f"t = {cfg.window_start * dt:g} s (dotted)")
    top.grid(alpha=0.3, which="both")
    top.legend(fontsize=8, ncol=3)
    for j in range(M):
        ax = fig.add_subplot(gs[1, j], sharey=top)
        for i, (n, s) in enumerate(shown.items()):
            ax.plot(np.arange(s.rmse_t.shape[0]) * dt, s.rmse_t[:, j], **_style(n, i))
        ax.set_title(names[j], color=_colour(j))
        ax.set_xlabel("t [s]")
        ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def nees_vs_time(summary, path) -> None:
    cfg = summary.config
    lo, hi = summary.nees_band
    fig, ax = plt.subplots(figsize=(10, 5))
    for i, (n, s) in enumerate(_filtered(summary).items()):
        t = np.arange(s.anees_t.shape[0]) * cfg.dt_s
        ax.plot(t, s.anees_t.mean(axis=1), label=f"{n} ({s.nees_mean:.2f})", **_style(n, i))
    ax.axhspan(lo, hi, color="tab:green", alpha=0.15, label=f"95 % band, N = {summary.n_trials}, per target")
    ax.axhline(2.0, color="tab:green", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("ANEES (2-D position), mean over targets")
    ax.set_title("Filter consistency: NEES averaged over trials (2 = consistent)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def flight(cfg, trial, path, methods=("greedy_l1", "greedy_l8")) -> None:
    """Fig. 2(a)-(b): one trial, the UAV's trajectory with true and estimated target tracks."""
    sc = cfg.scenario
    traces = {n: tr for n, tr in trial.traces.items() if not np.isnan(tr.error_m).all()}  # a filter ran
    shown = [m for m in methods if m in traces and traces[m].uav is not None]
    if not shown:
        shown = [n for n, tr in traces.items() if tr.uav is not None][:1]
    if not shown:
        shown = list(traces)[:1]
    if not shown:
        return
    fig = plt.figure(figsize=(7 * len(shown), 12))
    for col, name in enumerate(shown):
        tr = trial.traces[name]
        ax3 = fig.add_subplot(2, len(shown), col + 1, projection="3d")
        _scene_3d(ax3, sc)
        ax2 = fig.add_subplot(2, len(shown), len(shown) + col + 1)
        _scene_2d(ax2, sc)
        for j, t in enumerate(sc.targets):
            true, est = trial.truth[:, j, :2], tr.estimate_xy[:, j]
            ax2.plot(true[:, 0], true[:, 1], color=_colour(j), lw=1.5, label=f"{t.name} true")
            ax2.plot(est[:, 0], est[:, 1], color=_colour(j), lw=0.8, ls="--", label=f"{t.name} estimate")
            ax2.plot(*true[0], marker="*", ms=12, color=_colour(j), ls="none")
            ax3.plot(true[:, 0], true[:, 1], 0 * true[:, 0], color=_colour(j), lw=1.2)
            ax3.plot(est[:, 0], est[:, 1], 0 * est[:, 0], color=_colour(j), lw=0.8, ls="--")
        if tr.uav is not None:
            u = tr.uav
            ax2.plot(u[:, 0], u[:, 1], "-", color="black", lw=1.5, label="UAV")
            ax2.plot(*u[0, :2], marker="D", color="black", ls="none")
            ax2.plot(*u[-1, :2], marker="s", color="black", ls="none")
            ax3.plot(u[:, 0], u[:, 1], u[:, 2], color="black", lw=1.5)
            ax3.scatter(*u[0], color="black", marker="D", s=30)
        else:
            from sim.truth.sensors import FIXED_SENSORS_M
            for s in FIXED_SENSORS_M:
                ax2.plot(*s, marker="^", ms=10, color="black", ls="none")
        err = np.sqrt(np.mean(tr.error_m[cfg.window_start:] ** 2))
        ax3.set_title(f"({'a' if col == 0 else chr(ord('a') + 2 * col)}) {name}, trial {trial.trial}: 3D")
        ax2.set_title(f"({'b' if col == 0 else chr(ord('b') + 2 * col)}) {name}: top-down; window RMSE {err:.1f} m")
        ax2.legend(fontsize=7, loc="lower left", ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def flown_paths(cfg, trials, path, methods=None, n_trials: int = 3) -> None:
    """The UAV methods' flown paths side by side (columns) on the first ``n_trials`` trials (rows),
    top-down, with the true target tracks (dots every 10 s) and each path's window RMSE."""
    names = [n for n in (methods or cfg.method_names) if trials and trials[0].traces[n].uav is not None]
    rows = list(trials[:n_trials])
    if not names or not rows:
        return
    sc = cfg.scenario
    every = max(int(round(10.0 / cfg.dt_s)), 1)
    fig, axs = plt.subplots(len(rows), len(names), figsize=(4.2 * len(names), 4.2 * len(rows)), squeeze=False)
    for r, trial in enumerate(rows):
        for c, name in enumerate(names):
            ax = axs[r, c]
            _scene_2d(ax, sc)
            truth = trial.truth
            for j in range(truth.shape[1]):
                ax.plot(truth[:, j, 0], truth[:, j, 1], color=_colour(j), lw=1.0)
                ax.plot(truth[::every, j, 0], truth[::every, j, 1], ".", color=_colour(j), ms=4)
            tr = trial.traces[name]
            u = tr.uav
            ax.plot(u[:, 0], u[:, 1], "-", color="black", lw=1.5)
            ax.plot(u[::every, 0], u[::every, 1], ".", color="black", ms=5)
            ax.plot(*u[0, :2], marker="D", color="black", ls="none")
            w = cfg.window_start
            if not np.isnan(tr.error_m).all():
                what = f"RMSE {np.sqrt(np.mean(tr.error_m[w:] ** 2)):.1f} m"
            else:  # bound only (the ceiling)
                what = f"PCRB {np.sqrt(np.mean(tr.bound_m2[w:])):.1f} m"
            ax.set_title(f"{name}, trial {trial.trial}: {what}", fontsize=9)
            lo, hi = sc.area.min_m, sc.area.max_m
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
            ax.set_aspect("equal")
    fig.suptitle("Flown UAV paths (black, dots every 10 s; diamond: start) and true targets", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
