"""A simulated recording for ``pmon locate`` (docs/LOCATE.md): a hand-flown lawnmower over
stationary emitters, written as a KrakenSDR would have recorded it and as the flight's logs hold
the vehicle's poses.

* **The flight** (``lawnmower``): legs east and west across the survey box, ``spacing_m`` apart,
  at ``speed_mps``, the nose along the track with a pilot's slow yaw wander (``yaw_wander_deg``);
  or any poses given (a firmware's own log, read by groundstation/poses.py).
* **The bearings**: each whole autopilot second, the DF model's scan of every emitter from where
  the vehicle was (sim/truth/sensors.py ``df_scan_labelled``: p_D, sigma, Poisson clutter), rendered
  by the simulated KrakenSDR (sim/stack/kraken.py ``frame_lines``: the lobes seen from the array on the
  vehicle's heading and ``mount_offset``, multipath, its latency) and appended to ``mydata.csv``
  as KrakenSDR's data recording does; and the same bearings as DF datagrams (``bearings.jsonl``).
* **The poses** as a MAVLink tlog (``flight.tlog``: GLOBAL_POSITION_INT at 10 Hz, SYSTEM_TIME at
  1 Hz with the UTC the KrakenSDR stamps use).
* **The scenario** (``scenario.yaml``): the emitters as stationary targets without a goal, their
  prior means drawn from N(truth, ``prior_sigma_m``^2) (so the prior is honest: the estimate's
  NEES can be checked), the KrakenSDR's VFOs.
"""
from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from onboard.app.df import datagram as dg
from onboard.app.autopilot.pose import Frame, PoseSample
from onboard.core.bearings import wrap

ORIGIN = (35.1450, 33.4110, 160.0)
UNIX_AT_BOOT = 1_790_000_000.0  # the simulated autopilot's UTC at its boot
FREQS_HZ = (433_100_000, 433_200_000)


@dataclass(frozen=True)
class RecordingConfig:
    # the legs 300-605 m from each emitter
    emitters_m: tuple[tuple[float, float], ...] = ((300.0, 500.0), (560.0, 500.0))
    box_m: tuple[float, float, float, float] = (220.0, 0.0, 640.0, 200.0)  # x0, y0, x1, y1 of the legs
    spacing_m: float = 50.0
    speed_mps: float = 6.0
    altitude_m: float = 40.0
    start_s: float = 60.0  # autopilot s of the first pose (after boot, arming, take-off)
    yaw_wander_deg: float = 15.0
    prior_sigma_m: float = 100.0
    sigma_deg: float = 1.0
    p_detect: float = 0.95
    clutter_rate: float = 1.0
    mount_offset_deg: float = 0.0


def lawnmower(cfg: RecordingConfig, rng: np.random.Generator, rate_hz: float = 10.0) -> list[PoseSample]:
    """The hand-flown lawnmower's poses (autopilot s, ENU), ``rate_hz`` of them per second."""
    x0, y0, x1, y1 = cfg.box_m
    legs = np.arange(y0, y1 + 1e-9, cfg.spacing_m)
    corners = []
    for k, y in enumerate(legs):
        corners += [(x0, y), (x1, y)] if k % 2 == 0 else [(x1, y), (x0, y)]
    pts = np.array(corners, float)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s_at = np.r_[0.0, np.cumsum(seg)]
    t = np.arange(0.0, s_at[-1] / cfg.speed_mps, 1.0 / rate_hz)
    s = t * cfg.speed_mps
    xy = np.stack([np.interp(s, s_at, pts[:, 0]), np.interp(s, s_at, pts[:, 1])], axis=1)
    vel = np.gradient(xy, t, axis=0)
    track = np.arctan2(vel[:, 0], vel[:, 1])
    # a pilot's yaw wander: a smooth random walk of a few tens of seconds
    k = max(1, int(20 * rate_hz))
    walk = np.convolve(rng.normal(0, 1, len(t) + k), np.ones(k) / math.sqrt(k), "same")[:len(t)]
    yaw = wrap(track + math.radians(cfg.yaw_wander_deg) * walk / max(np.abs(walk).max(), 1e-9))
    out = []
    for ti, p, v, y in zip(t, xy, vel, yaw):
        out.append(PoseSample(cfg.start_s + float(ti), np.array([p[0], p[1], cfg.altitude_m]),
                              np.array([v[0], v[1], 0.0]), float(y)))
    return out


def write_tlog(path: Path, poses: list[PoseSample], frame: Frame, unix_at_boot: float = UNIX_AT_BOOT) -> None:
    """GLOBAL_POSITION_INT for every pose and SYSTEM_TIME each second, as a tlog (each packet after
    its 8-byte big-endian Unix microseconds)."""
    from onboard.app.mavlink2 import mavlink

    with open(path, "wb") as f:
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        last_sys = -math.inf
        for p in poses:
            usec = int((unix_at_boot + p.t) * 1e6)
            boot_ms = int(round(p.t * 1000))
            if p.t - last_sys >= 1.0:
                last_sys = p.t
                f.write(struct.pack(">Q", usec) + mav.system_time_encode(usec, boot_ms).pack(mav))
            lat, lon, alt = frame.geodetic_from_enu(p.pos)
            hdg = int(round(math.degrees(p.yaw) % 360.0 * 100)) % 36000
            msg = mav.global_position_int_encode(boot_ms, int(round(lat * 1e7)), int(round(lon * 1e7)),
                                                 int(round(alt * 1000)), int(round(p.pos[2] * 1000)),
                                                 int(round(p.vel[1] * 100)), int(round(p.vel[0] * 100)),
                                                 int(round(-p.vel[2] * 100)), hdg)
            f.write(struct.pack(">Q", usec) + msg.pack(mav))


def _interp_pose(poses: list[PoseSample], t: float) -> tuple[np.ndarray, float] | None:
    ts = np.array([p.t for p in poses])
    if not ts[0] <= t <= ts[-1]:
        return None
    i = int(np.clip(np.searchsorted(ts, t), 1, len(ts) - 1))
    a, b = poses[i - 1], poses[i]
    w = (t - a.t) / (b.t - a.t)
    return a.pos + w * (b.pos - a.pos), float(wrap(a.yaw + w * math.remainder(b.yaw - a.yaw, math.tau)))


def write_bearings(folder: Path, poses: list[PoseSample], cfg: RecordingConfig, unix_of, rng: np.random.Generator
                   ) -> int:
    """``mydata.csv`` and ``bearings.jsonl`` over the poses' span (``unix_of``: autopilot s to Unix
    s); the number of frames written."""
    from sim.stack.kraken import KrakenModel, frame_lines
    from sim.truth.sensors import DirectionFinder, df_scan_labelled

    df = DirectionFinder(math.radians(cfg.sigma_deg), cfg.p_detect, cfg.clutter_rate)
    model = KrakenModel(mount_offset_rad=math.radians(cfg.mount_offset_deg))
    freqs = dict(enumerate(FREQS_HZ[:len(cfg.emitters_m)]))
    emitters = np.array(cfg.emitters_m, float)
    n = 0
    with open(folder / "mydata.csv", "w") as kraken, open(folder / "bearings.jsonl", "w") as grams:
        for T in range(int(math.ceil(poses[0].t)), int(math.floor(poses[-1].t)) + 1):
            at = _interp_pose(poses, float(T))
            if at is None:
                continue
            pos, yaw = at
            labelled = df_scan_labelled(emitters, pos[:2], df, rng)
            epoch = int(round(unix_of(T) * 1000.0 + model.latency_ms / 2.0))
            doc = frame_lines(epoch, labelled, freqs, yaw, model, rng)
            kraken.write(doc)
            n += bool(doc)
            for ch, (b, is_target) in enumerate(labelled):
                shown = b[is_target | model.multipath]
                grams.write(dg.encode(float(T), ch, shown).decode() + "\n")
    return n


def scenario_tree(cfg: RecordingConfig, prior_m: np.ndarray) -> dict:
    """The locate scenario: the emitters as stationary targets with priors ``prior_m`` (M, 2)."""
    s = cfg.prior_sigma_m
    return {
        "name": "locate_sim", "origin": dict(zip(("lat_deg", "lon_deg", "alt_m"), ORIGIN)),
        "area": {"min_m": [-200.0, -200.0, 0.0], "max_m": [1000.0, 900.0, 1000.0]},
        "initial_cov_diag": [s * s, s * s, 1e-10, 1.0, 1.0, 1e-10],
        "targets": [{"name": f"T{j + 1}", "position_m": [float(p[0]), float(p[1]), 0.0], "stationary": True}
                    for j, p in enumerate(prior_m)],
        "goals": [{"name": "G", "center_m": [900.0, -100.0, 0.0], "size_m": [100.0, 100.0, 0.0]}],
        "sensor": {"sigma_deg": cfg.sigma_deg, "p_detect": cfg.p_detect, "clutter_rate": cfg.clutter_rate},
        "uav": {"start_m": [cfg.box_m[0], cfg.box_m[1], cfg.altitude_m], "altitude_m": cfg.altitude_m},
        "kraken": {"vfos": [{"target": f"T{j + 1}", "freq_hz": f} for j, f in enumerate(FREQS_HZ[:len(prior_m)])],
                   "mount_offset_deg": cfg.mount_offset_deg},
    }


def write_recording(folder, seed: int, cfg: RecordingConfig = RecordingConfig(), poses=None, unix_of=None) -> dict:
    """Everything in ``folder``: mydata.csv, bearings.jsonl, scenario.yaml, truth.json, and
    flight.tlog unless ``poses`` are given (a firmware's log: then ``unix_of``, its autopilot s
    to Unix s, too). Returns {"truth_m": (M, 2), "frames": n, paths...}."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    frame = Frame(*ORIGIN)
    if poses is None:
        poses = lawnmower(cfg, rng)
        write_tlog(folder / "flight.tlog", poses, frame)
        unix_of = lambda t: UNIX_AT_BOOT + t  # noqa: E731
    truth = np.array(cfg.emitters_m, float)
    prior = truth + rng.normal(0.0, cfg.prior_sigma_m, truth.shape)
    frames = write_bearings(folder, poses, cfg, unix_of, rng)
    (folder / "scenario.yaml").write_text(yaml.safe_dump(scenario_tree(cfg, prior), sort_keys=False))
    (folder / "truth.json").write_text(json.dumps({"emitters_m": truth.tolist(), "prior_m": prior.tolist(),
                                                   "seed": seed, "frames": frames}))
    return {"truth_m": truth, "prior_m": prior, "frames": frames, "mydata": folder / "mydata.csv",
            "datagrams": folder / "bearings.jsonl", "tlog": folder / "flight.tlog",
            "scenario": folder / "scenario.yaml"}
