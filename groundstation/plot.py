"""Top-down pictures of a flight: UAV path, estimated tracks with 1-sigma ellipses, true tracks
when known. From a tlog (the app's PMON_TGT / PMON_STAT), from the app's JSONL run log, and live
(``watch --png``). Mission ENU frame, metres."""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class Estimate:
    t: float
    x: float
    y: float
    sigma_x: float
    sigma_y: float
    cov_xy: float = 0.0


@dataclass(frozen=True)
class Flight:
    uav: tuple[tuple[float, float], ...] = ()
    tracks: dict = field(default_factory=dict)  # target index -> [Estimate]
    truth: dict = field(default_factory=dict)  # target index -> [(x, y)]
    next_wp: tuple[float, float] | None = None
    source: str = ""
    uav_t: tuple[float, ...] = ()  # autopilot s of each UAV position (empty: not known)
    truth_t: tuple[float, ...] = ()  # autopilot s of each truth point (the feed's scans)

    @property
    def empty(self) -> bool:
        return not self.uav and not self.tracks


class LogError(Exception):
    pass


def load_tlog(path: str | Path) -> Flight:
    from onboard.app.mavlink2 import mavutil

    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    uav, uav_t, tracks, nxt = [], [], {}, None
    seen_tick: set = set()
    while True:
        m = conn.recv_match(type="DEBUG_FLOAT_ARRAY")
        if m is None:
            break
        d = m.data
        if m.name == "PMON_STAT" and all(math.isfinite(v) for v in d[14:16]):
            uav.append((d[14], d[15]))
            uav_t.append(d[2])  # the last tick's time
            if all(math.isfinite(v) for v in d[4:6]):
                nxt = (d[4], d[5])
        elif m.name == "PMON_TGT":
            key = (m.array_id, d[13])
            if key in seen_tick:  # a tlog of both directions may hold a packet twice
                continue
            seen_tick.add(key)
            tracks.setdefault(int(m.array_id), []).append(Estimate(d[13], d[0], d[1], d[6], d[7], d[9]))
    conn.close()
    times = tuple(uav_t) if all(math.isfinite(t) for t in uav_t) else ()
    return Flight(tuple(uav), tracks, {}, nxt, str(path), uav_t=times)


def load_runlog(path: str | Path) -> Flight:
    uav, uav_t, tracks, nxt = [], [], {}, None
    with open(path) as f:
        for line in f:
            if not line.strip():
                continue
            rec = json.loads(line)
            if "means" not in rec:
                raise LogError(f"{path}: not a pmon run log (no 'means' in a line)")
            if rec.get("uav_enu"):
                uav.append(tuple(rec["uav_enu"][:2]))
                uav_t.append(rec["t"])
            if rec.get("next"):
                nxt = tuple(rec["next"][:2])
            cxy = rec.get("cov_xy") or [0.0] * len(rec["means"])  # older logs: axis-aligned ellipses
            for j, (mean, sig, c) in enumerate(zip(rec["means"], rec["sigmas_xy"], cxy)):
                tracks.setdefault(j, []).append(Estimate(rec["t"], mean[0], mean[1], sig[0], sig[1], c))
    return Flight(tuple(uav), tracks, {}, nxt, str(path), uav_t=tuple(uav_t))


def load_truth(path: str | Path) -> tuple[dict, list, list]:
    """The feed's truth JSONL: per target [(x, y)], the UAV path it used, the scans' times (s)."""
    truth: dict = {}
    uav, times = [], []
    with open(path) as f:
        for line in f:
            rec = json.loads(line) if line.strip() else {}
            if "targets" not in rec:
                continue
            for j, s in enumerate(rec["targets"]):
                truth.setdefault(j, []).append((s[0], s[1]))
            uav.append(tuple(rec["uav_enu"][:2]))
            times.append(rec["t"])
    return truth, uav, times


def load(path: str | Path, truth_path: str | Path | None = None) -> Flight:
    p = Path(path)
    if not p.exists():
        raise LogError(f"{p}: no such file")
    with open(p, "rb") as f:
        head = f.read(1)
    flight = load_runlog(p) if head == b"{" else load_tlog(p)
    if truth_path is None and (p.parent / "truth.jsonl").exists():  # as pmon demo writes them
        truth_path = p.parent / "truth.jsonl"
    if truth_path is not None:
        truth, _, times = load_truth(truth_path)
        flight = Flight(flight.uav, flight.tracks, truth, flight.next_wp, flight.source, flight.uav_t, tuple(times))
    if flight.empty:
        raise LogError(f"{p}: no UAV position and no target estimate in it")
    return flight


MARK_EVERY_S = 20.0  # time marks along the paths, s since the first scan (or the first tick)


def figure(flight: Flight, title: str = "", scenario=None, every: int = 10):
    """(fig, ax): the scenario's scene when given (area, goal, obstacles), true tracks,
    estimated tracks with their 1-sigma ellipse every ``every`` estimates and at the last, the
    UAV path, the next waypoint; where each path starts and ends, and time marks along the true
    tracks and the UAV path every MARK_EVERY_S; the legend beside the map, where it covers
    nothing. With a scenario's goal regions, a second panel enlarges them: the targets end there
    and their tracks and ellipses crowd the map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from groundstation.scene import draw_scene, legend_outside, scene_legend_handles

    zoom = _goal_box(scenario)
    if zoom is None:
        fig, ax = plt.subplots(figsize=(9.5, 7))
    else:
        fig = plt.figure(figsize=(14, 8.5))
        ax = fig.add_axes((0.05, 0.07, 0.58, 0.86))
    if scenario is not None:
        draw_scene(ax, scenario)
    t0 = next((ts[0] for ts in (flight.truth_t, flight.uav_t) if ts), None)
    _draw_flight(ax, flight, every, t0)
    ax.set_aspect("equal")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title or f"{flight.source}: estimates with 1-sigma ellipses", fontsize=10)
    # right of the map, below the enlarged goal region when there is one
    legend_outside(ax, _mark_handles(t0) + (scene_legend_handles(scenario) if scenario is not None else []),
                   fontsize=8, bottom=zoom is not None)
    ax.grid(alpha=0.3)
    if zoom is not None:
        zax = fig.add_axes((0.67, 0.52, 0.31, 0.41))
        draw_scene(zax, scenario, labels=False)
        _draw_flight(zax, flight, every, t0, labels=False)
        (x0, y0), (x1, y1) = zoom
        zax.set_xlim(x0, x1)
        zax.set_ylim(y0, y1)
        zax.set_aspect("equal")
        zax.set_xlabel("")
        zax.set_ylabel("")
        zax.tick_params(labelsize=7)
        zax.set_title("the goal region, enlarged", fontsize=9)
        zax.grid(alpha=0.3)
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="0.4", lw=1.0, ls=":",
                               zorder=2))
    return fig, ax


def _goal_box(scenario, margin: float = 0.6):
    """((x0, y0), (x1, y1)): the goal regions' bounding box widened by ``margin`` of its size on
    each side, m; None without a scenario or goals."""
    if scenario is None or not scenario.goals:
        return None
    from groundstation.scene import footprint

    pts = np.vstack([footprint(g) for g in scenario.goals])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = margin * (hi - lo).max()
    return tuple(lo - pad), tuple(hi + pad)


def _draw_flight(ax, flight: Flight, every: int, t0: float | None, labels: bool = True) -> None:
    from matplotlib.patches import Polygon

    from groundstation.scene import UAV_COLOUR, covariance_ellipse, target_colour

    def label(text):
        return text if labels else "_nolegend_"
    for j, pts in sorted(flight.truth.items()):
        a = np.array(pts)
        c = target_colour(j)
        ax.plot(a[:, 0], a[:, 1], "-", color=c, lw=2, alpha=0.5, label=label(f"T{j + 1} true"), zorder=3)
        _ends(ax, a, c)
        _time_marks(ax, a, flight.truth_t, t0, c, labels)
    for j, est in sorted(flight.tracks.items()):
        c = target_colour(j)
        ax.plot([e.x for e in est], [e.y for e in est], "--", color=c, lw=1, label=label(f"T{j + 1} estimate"),
                zorder=4)
        for e in est[::every] + est[-1:]:
            pts = covariance_ellipse(e.x, e.y, e.sigma_x, e.sigma_y, e.cov_xy)
            if pts is not None:
                ax.add_patch(Polygon(pts, closed=True, fill=False, edgecolor=c, lw=0.8, alpha=0.7, zorder=4))
        ax.plot(est[-1].x, est[-1].y, "o", color=c, ms=4, zorder=5)
    if flight.uav:
        u = np.array(flight.uav)
        ax.plot(u[:, 0], u[:, 1], "-", color=UAV_COLOUR, lw=1.2, label=label("UAV"), zorder=5)
        _ends(ax, u, UAV_COLOUR, end="^")
        _time_marks(ax, u, flight.uav_t, t0, UAV_COLOUR, labels)
    if flight.next_wp is not None:
        ax.plot(*flight.next_wp, "x", color=UAV_COLOUR, ms=8, label=label("next waypoint"), zorder=6)


def _ends(ax, a: np.ndarray, colour: str, end: str = "s") -> None:
    """A path's start (hollow circle) and end (filled ``end`` marker)."""
    ax.plot(a[0, 0], a[0, 1], "o", mfc="white", mec=colour, mew=1.5, ms=7, zorder=6)
    ax.plot(a[-1, 0], a[-1, 1], end, color=colour, ms=7, zorder=6)


def _time_marks(ax, a: np.ndarray, times, t0: float | None, colour: str, labels: bool) -> None:
    """A dot and 's since t0' on the path at each MARK_EVERY_S (the positions nearest in time)."""
    if t0 is None or len(times) != len(a) or not len(a):
        return
    t = np.asarray(times, float) - t0
    for mark in np.arange(MARK_EVERY_S, t[-1] + 1e-9, MARK_EVERY_S):
        i = int(np.argmin(np.abs(t - mark)))
        if abs(t[i] - mark) > 1.0:
            continue
        ax.plot(a[i, 0], a[i, 1], ".", color=colour, ms=6, zorder=6)
        if labels:
            ax.annotate(f"{mark:g} s", (a[i, 0], a[i, 1]), xytext=(4, 3), textcoords="offset points",
                        fontsize=7, color=colour, zorder=7)


def _mark_handles(t0: float | None) -> list:
    from matplotlib.lines import Line2D

    out = [Line2D([], [], ls="", marker="o", mfc="white", mec="0.3", mew=1.5, ms=7, label="start"),
           Line2D([], [], ls="", marker="s", color="0.3", ms=7, label="end (UAV: triangle)")]
    if t0 is not None:
        out.append(Line2D([], [], ls="", marker=".", color="0.3", ms=6,
                          label=f"every {MARK_EVERY_S:g} s from the first scan"))
    return out


def draw(flight: Flight, png: str | Path, title: str = "", scenario=None, every: int = 10,
         dpi: int = 110) -> Path:
    """Write ``figure``'s picture (atomically: a live viewer never sees half a file)."""
    import matplotlib.pyplot as plt

    fig, _ = figure(flight, title, scenario, every)
    png = Path(png)
    tmp = png.with_name(png.name + ".tmp.png")
    fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    os.replace(tmp, png)
    return png
