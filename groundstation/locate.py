"""``pmon locate``: where the emitters of a recording are, from its bearings and the vehicle's poses.

    pmon locate BEARINGS POSES [--scenario FILE] [--set KEY=VALUE] [--out BASE] [--time-offset S]
                [--seed N] [--format csv,geojson,kml,png] [--json]

BEARINGS: KrakenSDR's recording (``mydata.csv``, "Kraken App" lines) or DF datagrams (JSONL);
POSES: the flight's MAVLink tlog, ArduPilot DataFlash log (.bin) or PX4 ULog (.ulg). The
bearings are put on the log's timeline (groundstation/locate_align.py), the scenario's filter is
run over them one tick per second exactly as the app's tick runs it (``onboard.core.monitor.tick``:
the motion modes, stationary and unknown goal included, with the scenario's priors; no UAV
planning). Each target's final estimate is, for one that stood still (its stationary mode held
the majority), its position fused over the whole recording (groundstation/locate_fuse.py: the
exact posterior of a target that never moved, which the filter, built to follow a target that
may move, is not), else the filter's last tick. The estimates go out with their covariance
ellipses as BASE.csv (every tick, every target, then the final ones), BASE.geojson and BASE.kml
(the ground station's export), BASE.png (its plot).
What could not be aligned is said in one line each; a malformed or misaligned recording is one
line naming the file and the line or the time (exit 2). docs/LOCATE.md.
"""
from __future__ import annotations

import csv
import json
import math
import os
import sys
from dataclasses import dataclass, field

import numpy as np

from onboard.app.autopilot.pose import Frame

FORMATS = ("csv", "geojson", "kml", "png")
CHI2_95_2DOF = 5.991464547107979  # the 95 % ellipse of a 2-D Gaussian: chi-square(2) quantile
CSV_FIELDS = ("t_s", "unix_s", "target", "estimate", "east_m", "north_m", "lat_deg", "lon_deg", "sigma_east_m",
              "sigma_north_m", "cov_en_m2", "ellipse95_major_m", "ellipse95_minor_m", "ellipse95_azimuth_deg",
              "speed_mps", "p_stationary", "bearings")


@dataclass
class Located:
    """What a run found: per tick, the means (M, 6) and covariances (M, 6, 6) of every target; per
    target, its final estimate (``finish``)."""

    times: list[int] = field(default_factory=list)  # autopilot s
    means: list[np.ndarray] = field(default_factory=list)
    covs: list[np.ndarray] = field(default_factory=list)
    p_stationary: list[list[float | None]] = field(default_factory=list)
    counts: list[list[int]] = field(default_factory=list)  # bearings per target at each tick
    uav: list[tuple[float, float]] = field(default_factory=list)  # the vehicle at each tick
    notes: list[str] = field(default_factory=list)
    scans: list[list] = field(default_factory=list)  # per target, [(sensor_xy, bearings, clutter rate)]
    reseeds: list[list[int]] = field(default_factory=list)  # per target, the ticks it was re-seeded at
    final_means: np.ndarray | None = None  # (M, 6)
    final_covs: np.ndarray | None = None  # (M, 6, 6)
    final_kind: list[str] = field(default_factory=list)  # per target: FUSED or LAST_TICK


FUSED = "stationary, fused over the recording"
LAST_TICK = "the filter's last tick"
STATIONARY_MAJORITY = 0.5  # a target whose stationary mode held this much, averaged over the ticks, stood still


def run_filter(sc, aligned, log, seed: int = 1) -> Located:
    """The scenario's filter over the aligned scans, one tick per whole second from the first
    bearing's to the last's (a second without one is a prediction alone, as the app's tick); then
    each target's final estimate (``finish``)."""
    from onboard.app.df.pairing import scans_for_tick
    from onboard.core.monitor import MonitorSetup, initial_state, tick

    setup = MonitorSetup.from_scenario(sc)
    rng = np.random.default_rng(seed)
    state = initial_state(setup, rng)
    poses = log.history()
    out = Located(notes=list(aligned.notes), scans=[[] for _ in range(setup.n_targets)],
                  reseeds=[[] for _ in range(setup.n_targets)])
    first, last = min(aligned.slots), max(aligned.slots)
    unpaired = 0
    for t in range(first, last + 1):
        held = aligned.slots.get(t, {})
        scans, lost = scans_for_tick(held, float(t), setup.n_targets, poses.at)
        unpaired += lost
        state, res = tick(setup, state, scans, rng)
        out.times.append(t)
        out.means.append(res.means.copy())
        out.covs.append(res.covs.copy())
        out.p_stationary.append(_stationary(setup, res))
        out.counts.append([len(held[ch].bearings) if ch in held else 0 for ch in range(setup.n_targets)])
        for j in range(setup.n_targets):
            out.scans[j] += [(np.asarray(s.sensor_position, float)[:2], s.bearings[j],
                              None if s.clutter_rates is None else s.clutter_rates[j])
                             for s in scans if np.asarray(s.bearings[j]).size]
            if res.reseeded is not None and res.reseeded[j]:
                out.reseeds[j].append(t)
        pos = poses.at(float(t))
        if pos is not None:
            out.uav.append((float(pos[0]), float(pos[1])))
    if unpaired:
        out.notes.append(f"{unpaired} scan(s) without a vehicle position at their time: not used")
    finish(out, setup, sc)
    return out


def finish(found: Located, setup, sc) -> None:
    """Each target's final estimate: for one that stood still (its stationary mode held the
    majority over the ticks; without modes, the scenario's ``stationary``), its position fused
    over every scan of the recording (groundstation/locate_fuse.py); else the last tick's."""
    from groundstation.locate_fuse import fuse

    found.final_means, found.final_covs = found.means[-1].copy(), found.covs[-1].copy()
    found.final_kind = []
    for j, target in enumerate(sc.targets):
        ps = stationary_share(found, j)
        still = ps >= STATIONARY_MAJORITY if ps is not None else bool(target.stationary)
        if not still or not found.scans[j]:
            found.final_kind.append(LAST_TICK)
            continue
        f = fuse(found.scans[j], setup.initial_means[j][:2], setup.initial_cov[:2, :2], setup.sensor)
        m, c = np.zeros(6), np.zeros((6, 6))
        m[:2], m[2] = f.mean_m, found.means[-1][j][2]
        c[:2, :2] = f.cov_m2
        found.final_means[j], found.final_covs[j] = m, c
        found.final_kind.append(FUSED)


def _stationary(setup, res) -> list[float | None]:
    if res.mode_probabilities is None or setup.intents is None:
        return [None] * setup.n_targets
    # a target's modes: its goals', then stationary, free, aimed (onboard/core/tracking/intent.py)
    return [float(p[len(it.names)]) for p, it in zip(res.mode_probabilities, setup.intents)]


def ellipse95(cov2: np.ndarray) -> tuple[float, float, float]:
    """(major, minor semi-axis m, azimuth of the major axis deg clockwise from north) of the 95 %
    ellipse of a 2x2 ENU position covariance."""
    vals, vecs = np.linalg.eigh(np.asarray(cov2, float))
    vals = np.clip(vals, 0.0, None)
    k = math.sqrt(CHI2_95_2DOF)
    major = vecs[:, 1]
    return k * math.sqrt(vals[1]), k * math.sqrt(vals[0]), math.degrees(math.atan2(major[0], major[1])) % 180.0


def _row(frame: Frame, when: tuple[int, float | None], name: str, kind: str, m: np.ndarray, c: np.ndarray,
         ps: float | None, n: int) -> dict:
    """One row of the table; ``when``: (autopilot s, Unix s or None)."""
    t, unix = when
    lat, lon, _ = frame.geodetic_from_enu(m[:3])
    a, b, az = ellipse95(c[:2, :2])
    return {"t_s": t, "unix_s": "" if unix is None else f"{unix:.3f}", "target": name, "estimate": kind,
            "east_m": f"{m[0]:.2f}", "north_m": f"{m[1]:.2f}", "lat_deg": f"{lat:.7f}", "lon_deg": f"{lon:.7f}",
            "sigma_east_m": f"{math.sqrt(max(c[0, 0], 0)):.3f}", "sigma_north_m": f"{math.sqrt(max(c[1, 1], 0)):.3f}",
            "cov_en_m2": f"{c[0, 1]:.4f}", "ellipse95_major_m": f"{a:.2f}", "ellipse95_minor_m": f"{b:.2f}",
            "ellipse95_azimuth_deg": f"{az:.1f}", "speed_mps": f"{math.hypot(m[3], m[4]):.2f}",
            "p_stationary": "" if ps is None else f"{ps:.3f}", "bearings": n}


def stationary_share(found: Located, j: int) -> float | None:
    """Target j's stationary-mode probability averaged over the ticks (None without modes)."""
    ps = [p[j] for p in found.p_stationary if p[j] is not None]
    return float(np.mean(ps)) if ps else None


def rows(found: Located, sc, log) -> list[dict]:
    """The table: one row per tick and target (``estimate`` "tick"), then each target's final
    estimate (``estimate`` "final", at the last tick's time; its bearings: the scans it used)."""
    frame = Frame(sc.origin.lat_deg, sc.origin.lon_deg, sc.origin.alt_m)
    out = []
    for t, means, covs, ps, ns in zip(found.times, found.means, found.covs, found.p_stationary, found.counts):
        unix = log.utc.unix_time(float(t))
        out += [_row(frame, (t, unix), target.name, "tick", means[j], covs[j], ps[j], ns[j])
                for j, target in enumerate(sc.targets)]
    t = found.times[-1]
    for j, target in enumerate(sc.targets):
        n = len(found.scans[j]) if found.final_kind[j] == FUSED else found.counts[-1][j]
        out.append(_row(frame, (t, log.utc.unix_time(float(t))), target.name, "final", found.final_means[j],
                        found.final_covs[j], stationary_share(found, j), n))
    return out


def flight(found: Located, source: str):
    """The run as the ground station's ``Flight`` (groundstation/plot.py), for its plot and export:
    each target's track, its last point the final estimate."""
    from groundstation.plot import Estimate, Flight

    def est(t, m, c):
        return Estimate(float(t), float(m[0]), float(m[1]), math.sqrt(max(c[0, 0], 0)), math.sqrt(max(c[1, 1], 0)),
                        float(c[0, 1]))

    tracks = {}
    for t, means, covs in zip(found.times, found.means, found.covs):
        for j in range(len(means)):
            tracks.setdefault(j, []).append(est(t, means[j], covs[j]))
    for j, track in tracks.items():
        track[-1] = est(found.times[-1], found.final_means[j], found.final_covs[j])
    return Flight(tuple(found.uav), tracks, {}, None, source)


def write_outputs(found: Located, sc, log, base: str, formats=FORMATS) -> list[str]:
    """BASE.csv, BASE.geojson, BASE.kml, BASE.png (those of ``formats``); the paths written."""
    written = []
    if "csv" in formats:
        path = base + ".csv"
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, CSV_FIELDS)
            w.writeheader()
            w.writerows(rows(found, sc, log))
        written.append(path)
    fl = flight(found, os.path.basename(base))
    geo = tuple(x for x in ("geojson", "kml") if x in formats)
    if geo:
        from groundstation.export import write
        written += [str(p) for p in write(fl, sc, base, geo, None, 60.0)]
    if "png" in formats:
        from groundstation.plot import draw
        written.append(str(draw(fl, base + ".png", title=f"pmon locate: {os.path.basename(base)}", scenario=sc,
                                every=60)))
    return written


def summary(found: Located, sc) -> list[str]:
    """One line per target: its final estimate, 95 % ellipse, what it is (``finish``), its
    stationary probability averaged over the ticks, and the filter's re-seeds."""
    frame = Frame(sc.origin.lat_deg, sc.origin.lon_deg, sc.origin.alt_m)
    out = []
    for j, target in enumerate(sc.targets):
        m, c = found.final_means[j], found.final_covs[j]
        lat, lon, _ = frame.geodetic_from_enu(m[:3])
        a, b, az = ellipse95(c[:2, :2])
        ps = stationary_share(found, j)
        n = len(found.scans[j])
        seeds = found.reseeds[j]
        apart = float(np.hypot(*(found.means[-1][j][:2] - m[:2])))
        out.append(f"{target.name}: {lat:.6f}, {lon:.6f} (E {m[0]:.1f} m, N {m[1]:.1f} m), 95 % ellipse "
                   f"{a:.1f} x {b:.1f} m at {az:.0f} deg, {found.final_kind[j]}, {n} scans with bearings"
                   + ("" if ps is None else f", stationary {ps:.2f}")
                   + (f"; the filter's last tick {apart:.1f} m from it" if found.final_kind[j] == FUSED else "")
                   + (f"; the filter re-seeded at autopilot t {', '.join(map(str, seeds[-3:]))} s"
                      f"{f' ({len(seeds)} times)' if len(seeds) > 3 else ''}" if seeds else ""))
    return out


# ----------------------------------------------------------------------------- command line
def parser():
    from onboard.argcheck import OneLineParser

    ap = OneLineParser(prog="pmon locate", description=__doc__.splitlines()[0])
    ap.add_argument("bearings", help="KrakenSDR's recording (mydata.csv) or a DF datagram JSONL")
    ap.add_argument("poses", help="the flight's tlog, DataFlash .bin or PX4 .ulg")
    ap.add_argument("--scenario", default="paper", help="YAML file or built-in name: origin, targets and their "
                    "priors, kraken.vfos, the sensor (default: paper)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="change a scenario value (VALUE read as YAML; repeatable), e.g. kraken.mount_offset_deg=90")
    ap.add_argument("--out", metavar="BASE", help="output path without extension (default: the bearings file's)")
    ap.add_argument("--format", default=",".join(FORMATS), help=f"outputs, comma-separated (default {','.join(FORMATS)})")
    ap.add_argument("--time-offset", type=float, default=0.0, metavar="S",
                    help="seconds added to every bearing's time (a DF clock off the autopilot's; default 0)")
    ap.add_argument("--unix-at-boot", type=float, metavar="S",
                    help="Unix time of the autopilot's boot, for a pose log without UTC (PX4's SIH simulator "
                    "writes none) and KrakenSDR's Unix-stamped bearings")
    ap.add_argument("--pose-format", choices=("tlog", "bin", "ulg"), help="the pose log's format (default: from its bytes)")
    ap.add_argument("--seed", type=int, default=1, help="the filter's random seed (default 1)")
    ap.add_argument("--json", action="store_true", help="print the result as one JSON object")
    return ap


@dataclass(frozen=True)
class Request:
    bearings: str
    poses: str
    scenario: object  # onboard.settings.Scenario, its policy applied
    time_offset_s: float = 0.0
    pose_format: str | None = None
    seed: int = 1
    unix_at_boot: float | None = None  # the log holds no UTC: the Unix time of the autopilot's boot


def locate(req: Request) -> tuple[Located, object]:
    """Read, align and track; (what was found, the pose log). Raises PoseError / AlignError."""
    from groundstation import locate_align, poses

    sc = req.scenario
    log = poses.read(req.poses,
                     Frame(sc.origin.lat_deg, sc.origin.lon_deg, sc.origin.alt_m), req.pose_format)
    said = []
    if req.unix_at_boot is not None:
        if log.utc.autopilot_time(0.0) is None:
            log.utc.observe(int(round(req.unix_at_boot * 1e6)), 0)
        else:
            said.append(f"{log.path}: holds its own UTC: --unix-at-boot not used")
    aligned = locate_align.align(req.bearings, sc, log, req.time_offset_s)
    aligned.notes[:0] = said
    return run_filter(sc, aligned, log, req.seed), log


def main(argv=None) -> int:
    """Locate emitters from a recording: bearings and a flight log in, estimates with ellipses out."""
    from groundstation.locate_align import AlignError
    from groundstation.poses import PoseError
    from onboard.config import ConfigError, load_scenario, parse_overrides
    from onboard.policy import DEFAULT, with_policy

    args = parser().parse_args(argv)
    formats = tuple(x.strip() for x in args.format.split(",") if x.strip())
    bad = [x for x in formats if x not in FORMATS]
    if bad or not math.isfinite(args.time_offset) or not math.isfinite(args.unix_at_boot or 0.0):
        why = (f"--format: {bad[0]!r} is none of {', '.join(FORMATS)}" if bad
               else "--time-offset and --unix-at-boot must be finite")
        print(f"pmon locate: {why}", file=sys.stderr)
        return 2
    try:
        sc = with_policy(load_scenario(args.scenario, parse_overrides(args.set)), DEFAULT)
        found, log = locate(Request(args.bearings, args.poses, sc, args.time_offset, args.pose_format, args.seed,
                                        args.unix_at_boot))
        base = args.out or os.path.splitext(args.bearings)[0] + ".locate"
        written = write_outputs(found, sc, log, base, formats)
    except (ConfigError, PoseError, AlignError) as exc:
        print(f"pmon locate: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"pmon locate: cannot write: {exc.strerror or exc}: {exc.filename or ''}", file=sys.stderr)
        return 1
    lines = summary(found, sc)
    if args.json:
        print(json.dumps({"targets": [{"name": t.name, "east_m": float(found.final_means[j][0]),
                                       "north_m": float(found.final_means[j][1]),
                                       "cov_en_m2": found.final_covs[j][:2, :2].tolist(),
                                       "final": found.final_kind[j], "reseeded_at_s": found.reseeds[j]}
                                      for j, t in enumerate(sc.targets)],
                          "ticks": len(found.times), "notes": found.notes, "files": written}))
        return 0
    print(f"pmon locate: {len(found.times)} ticks, autopilot t {found.times[0]}..{found.times[-1]} s, "
          f"poses from {log.kind} {log.path}")
    for note in found.notes:
        print(f"not aligned: {note}")
    for line in lines + [f"wrote {p}" for p in written]:
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
