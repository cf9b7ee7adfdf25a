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

    @property
    def empty(self) -> bool:
        return not self.uav and not self.tracks


class LogError(Exception):
    pass


def load_tlog(path: str | Path) -> Flight:
    from onboard.app.mavlink_connection import mavlink  # noqa: F401  (MAVLink 2 before mavutil)
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    uav, tracks, nxt = [], {}, None
    seen_tick: set = set()
    while True:
        m = conn.recv_match(type="DEBUG_FLOAT_ARRAY")
        if m is None:
            break
        d = m.data
        if m.name == "PMON_STAT" and all(math.isfinite(v) for v in d[14:16]):
            uav.append((d[14], d[15]))
            if all(math.isfinite(v) for v in d[4:6]):
                nxt = (d[4], d[5])
        elif m.name == "PMON_TGT":
            key = (m.array_id, d[13])
            if key in seen_tick:  # a tlog of both directions may hold a packet twice
                continue
            seen_tick.add(key)
            tracks.setdefault(int(m.array_id), []).append(Estimate(d[13], d[0], d[1], d[6], d[7], d[9]))
    conn.close()
    return Flight(tuple(uav), tracks, {}, nxt, str(path))


def load_runlog(path: str | Path) -> Flight:
    uav, tracks, nxt = [], {}, None
    with open(path) as f:
        for line in f:
            if not line.strip():
                continue
            rec = json.loads(line)
            if "means" not in rec:
                raise LogError(f"{path}: not a pmon run log (no 'means' in a line)")
            if rec.get("uav_enu"):
                uav.append(tuple(rec["uav_enu"][:2]))
            if rec.get("next"):
                nxt = tuple(rec["next"][:2])
            cxy = rec.get("cov_xy") or [0.0] * len(rec["means"])  # older logs: axis-aligned ellipses
            for j, (mean, sig, c) in enumerate(zip(rec["means"], rec["sigmas_xy"], cxy)):
                tracks.setdefault(j, []).append(Estimate(rec["t"], mean[0], mean[1], sig[0], sig[1], c))
    return Flight(tuple(uav), tracks, {}, nxt, str(path))


def load_truth(path: str | Path) -> tuple[dict, list]:
    """The feed's truth JSONL: per target [(x, y)], and the UAV path it used."""
    truth: dict = {}
    uav = []
    with open(path) as f:
        for line in f:
            rec = json.loads(line) if line.strip() else {}
            if "targets" not in rec:
                continue
            for j, s in enumerate(rec["targets"]):
                truth.setdefault(j, []).append((s[0], s[1]))
            uav.append(tuple(rec["uav_enu"][:2]))
    return truth, uav


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
        truth, _ = load_truth(truth_path)
        flight = Flight(flight.uav, flight.tracks, truth, flight.next_wp, flight.source)
    if flight.empty:
        raise LogError(f"{p}: no UAV position and no target estimate in it")
    return flight


def figure(flight: Flight, title: str = "", scenario=None, every: int = 10):
    """(fig, ax): the scenario's scene when given (area, goal, obstacles), true tracks,
    estimated tracks with their 1-sigma ellipse every ``every`` estimates and at the last, the
    UAV path, the next waypoint; the legend beside the map, where it covers nothing."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon

    from groundstation.scene import (UAV_COLOUR, covariance_ellipse, draw_scene, legend_outside,
                                     scene_legend_handles, target_colour)

    fig, ax = plt.subplots(figsize=(9.5, 7))
    if scenario is not None:
        draw_scene(ax, scenario)
    for j, pts in sorted(flight.truth.items()):
        a = np.array(pts)
        ax.plot(a[:, 0], a[:, 1], "-", color=target_colour(j), lw=2, alpha=0.5, label=f"T{j + 1} true", zorder=3)
    for j, est in sorted(flight.tracks.items()):
        c = target_colour(j)
        ax.plot([e.x for e in est], [e.y for e in est], "--", color=c, lw=1, label=f"T{j + 1} estimate", zorder=4)
        for e in est[::every] + est[-1:]:
            pts = covariance_ellipse(e.x, e.y, e.sigma_x, e.sigma_y, e.cov_xy)
            if pts is not None:
                ax.add_patch(Polygon(pts, closed=True, fill=False, edgecolor=c, lw=0.8, alpha=0.7, zorder=4))
        ax.plot(est[-1].x, est[-1].y, "o", color=c, ms=4, zorder=5)
    if flight.uav:
        u = np.array(flight.uav)
        ax.plot(u[:, 0], u[:, 1], "-", color=UAV_COLOUR, lw=1.2, label="UAV", zorder=5)
        ax.plot(u[-1, 0], u[-1, 1], "^", color=UAV_COLOUR, ms=8, zorder=6)
    if flight.next_wp is not None:
        ax.plot(*flight.next_wp, "x", color=UAV_COLOUR, ms=8, label="next waypoint", zorder=6)
    ax.set_aspect("equal")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title or f"{flight.source}: estimates with 1-sigma ellipses", fontsize=9)
    legend_outside(ax, scene_legend_handles(scenario) if scenario is not None else ())
    ax.grid(alpha=0.3)
    return fig, ax


def draw(flight: Flight, png: str | Path, title: str = "", scenario=None, every: int = 10) -> Path:
    """Write ``figure``'s picture (atomically: a live viewer never sees half a file)."""
    import matplotlib.pyplot as plt

    fig, _ = figure(flight, title, scenario, every)
    png = Path(png)
    tmp = png.with_name(png.name + ".tmp.png")
    fig.savefig(tmp, dpi=90, bbox_inches="tight")
    plt.close(fig)
    os.replace(tmp, png)
    return png
