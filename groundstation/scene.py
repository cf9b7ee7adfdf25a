"""The scene as every picture of a mission draws it: one colour per target, the area, the goal
regions and the obstacles, dark where the UAV cannot overfly them.

One palette and one geometry for the evaluation figures (sim/evaluation/figures.py), ``pmon demo``'s
flight.png, ``pmon gcs plot`` / ``watch --png`` (groundstation/plot.py), the live page
(groundstation/view.py sends these colours and footprints to the browser) and the GeoJSON /
KML export (groundstation/export.py). Mission ENU frame, metres; matplotlib only inside the
drawing functions (the live view and the export do not need it).
"""
from __future__ import annotations

import math

import numpy as np

# matplotlib's tab10 red, blue, purple, green, orange, brown, in that order per target (T1, T2, ...)
TARGET_COLOURS = ("#d62728", "#1f77b4", "#9467bd", "#2ca02c", "#ff7f0e", "#8c564b")
UAV_COLOUR = "#000000"
GOAL_COLOUR = "#b8860b"  # dark goldenrod: no target's colour
BLOCKING_COLOUR = "#4d4d4d"  # obstacles the UAV cannot overfly at h
OVERFLOWN_COLOUR = "#c8c8c8"  # obstacles it flies over


def target_colour(j: int) -> str:
    """The colour of target j (0-based), '#rrggbb'."""
    return TARGET_COLOURS[j % len(TARGET_COLOURS)]


def box_corners(box) -> np.ndarray:
    """(8, 3) corners of a config Box (centre, size, yaw): bottom four counter-clockwise seen
    from above, then the top four."""
    c, h = np.asarray(box.center_m, float), 0.5 * np.asarray(box.size_m, float)
    cy, sy = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    R = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    signs = np.array([[sx, sy_, sz] for sz in (-1, 1) for sx, sy_ in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    return c + (signs * h) @ R.T


def footprint(box) -> np.ndarray:
    """(4, 2) ground outline of a Box, counter-clockwise (east, north), m."""
    return box_corners(box)[:4, :2]


def area_outline(area) -> np.ndarray:
    """(4, 2) the area's ground outline, counter-clockwise, m."""
    (x0, y0), (x1, y1) = area.min_m[:2], area.max_m[:2]
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)


def blocks_uav(box, altitude_m: float, margin_m: float) -> bool:
    """True when the UAV flying at ``altitude_m`` cannot overfly the obstacle: the planner's
    rule (onboard.core.planning.next_position: the obstacle inflated by the UAV's margin spans h)."""
    lo = box.center_m[2] - box.size_m[2] / 2 - margin_m
    hi = box.center_m[2] + box.size_m[2] / 2 + margin_m
    return lo < altitude_m < hi


def covariance_ellipse(x: float, y: float, sigma_x: float, sigma_y: float, cov_xy: float,
                       n_sigma: float = 1.0, n: int = 120) -> np.ndarray | None:
    """(n, 2) points, counter-clockwise, of the n-sigma ellipse of the 2x2 covariance
    [[sx^2, cxy], [cxy, sy^2]] around (x, y), m; None if the covariance is not finite.

    Points are (x, y) + n_sigma * A [cos t, sin t] with A the lower Cholesky factor (A A^T =
    covariance), so t = 0 is the ellipse's easternmost point: its east-west extent is exactly
    +-n_sigma * sigma_x. The live page (static/view.js ``ellipse``) draws the same points."""
    vals = (x, y, sigma_x, sigma_y, cov_xy)
    if not all(math.isfinite(v) for v in vals) or sigma_x < 0 or sigma_y < 0:
        return None
    c = max(-sigma_x * sigma_y, min(sigma_x * sigma_y, cov_xy))  # |rho| <= 1 (float32 rounding)
    a21 = c / sigma_x if sigma_x > 1e-9 else 0.0
    A = np.array([[sigma_x, 0.0], [a21, math.sqrt(max(sigma_y ** 2 - a21 ** 2, 0.0))]])
    t = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
    return np.array([x, y]) + n_sigma * (np.stack([np.cos(t), np.sin(t)], axis=1) @ A.T)


# ----------------------------------------------------------------------------- matplotlib
def draw_scene(ax, sc, altitude_m: float | None = None, labels: bool = True) -> None:
    """Area outline, goal regions and obstacles (dark: the UAV cannot overfly them at h =
    ``altitude_m``, default the scenario's), with names; limits the axes to the area."""
    from matplotlib.patches import Polygon

    altitude_m = sc.uav.altitude_m if altitude_m is None else altitude_m
    ax.add_patch(Polygon(area_outline(sc.area), closed=True, fill=False, edgecolor="0.3", lw=1.0, zorder=1))
    for g in sc.goals:
        ax.add_patch(Polygon(footprint(g), closed=True, facecolor=GOAL_COLOUR, alpha=0.25,
                             edgecolor=GOAL_COLOUR, lw=1.5, zorder=1))
        if labels:
            ax.annotate(f"goal {g.name}", g.center_m[:2], ha="center", va="center", fontsize=8,
                        color=GOAL_COLOUR, zorder=2)
    for ob in sc.obstacles:
        dark = blocks_uav(ob, altitude_m, sc.uav.obstacle_margin_m)
        ax.add_patch(Polygon(footprint(ob), closed=True, facecolor=BLOCKING_COLOUR if dark else OVERFLOWN_COLOUR,
                             edgecolor="0.2", lw=0.8, zorder=1))
        if labels:
            ax.annotate(f"{ob.name}\n{ob.center_m[2] + ob.size_m[2] / 2:g} m", ob.center_m[:2], ha="center",
                        va="center", fontsize=7, color="white" if dark else "black", zorder=2)
    lo, hi = sc.area.min_m, sc.area.max_m
    pad = 0.02 * max(hi[0] - lo[0], hi[1] - lo[1])
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")


def scene_legend_handles(sc, altitude_m: float | None = None) -> list:
    """Legend entries of the scene itself (goal, the two kinds of obstacle present)."""
    from matplotlib.patches import Patch

    altitude_m = sc.uav.altitude_m if altitude_m is None else altitude_m
    kinds = {blocks_uav(ob, altitude_m, sc.uav.obstacle_margin_m) for ob in sc.obstacles}
    out = [Patch(facecolor=GOAL_COLOUR, alpha=0.25, edgecolor=GOAL_COLOUR, label="goal region")] if sc.goals else []
    if True in kinds:
        out.append(Patch(facecolor=BLOCKING_COLOUR, edgecolor="0.2", label=f"obstacle above h = {altitude_m:g} m"))
    if False in kinds:
        out.append(Patch(facecolor=OVERFLOWN_COLOUR, edgecolor="0.2", label="obstacle the UAV overflies"))
    return out


def legend_outside(ax, extra_handles=(), fontsize: float = 7, bottom: bool = False):
    """The legend to the right of the axes (at its top, or its ``bottom``), where it covers
    nothing (save with bbox_inches='tight', or leave room with fig.subplots_adjust)."""
    handles, labels = ax.get_legend_handles_labels()
    handles = list(handles) + list(extra_handles)
    labels = list(labels) + [h.get_label() for h in extra_handles]
    return ax.legend(handles, labels, loc="lower left" if bottom else "upper left",
                     bbox_to_anchor=(1.02, 0.0 if bottom else 1.0), borderaxespad=0.0, fontsize=fontsize,
                     frameon=False)
