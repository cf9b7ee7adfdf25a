"""Direction-finder (DF) measurement models for simulation (Sec. II-C and Sec. V of the paper).

Two sensors:

* the UAV's DF (``df_scan``): per target channel and scan, the target's bearing with probability
  p_D plus N(0, sigma^2) noise, and a Poisson(Lambda) number of clutter bearings uniform on
  (-pi, pi], in random order (the filter must not learn which one is the target's);
* the paper's baseline (``fixed_scans``): three fixed DFs on the ground, one bearing per target
  per sensor and scan, same noise, no clutter, p_D = 1.

Bearings are clockwise from north, phi = atan2(x_t - x_s, y_t - y_s), in (-pi, pi] (the
project's ``onboard.core.bearings``). Every random number comes from the Generator passed in.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from onboard.core.bearings import bearing, wrap
from onboard.core.monitor import Scan

#: The paper's three fixed direction finders (ENU, m), Sec. V-B.
FIXED_SENSORS_M = ((150.0, 200.0), (800.0, 200.0), (500.0, 900.0))


@dataclass(frozen=True)
class DirectionFinder:
    """Per channel j, per scan: bearing noise sigma (rad), detection probability, clutter mean."""

    sigma_rad: float
    p_detect: float
    clutter_rate: float

    def __post_init__(self):
        if not (math.isfinite(self.sigma_rad) and self.sigma_rad > 0):
            raise ValueError(f"sigma_rad must be > 0, got {self.sigma_rad}")
        if not 0.0 <= self.p_detect <= 1.0:
            raise ValueError(f"p_detect must be in [0, 1], got {self.p_detect}")
        if not (math.isfinite(self.clutter_rate) and self.clutter_rate >= 0):
            raise ValueError(f"clutter_rate must be >= 0, got {self.clutter_rate}")

    @classmethod
    def from_config(cls, sensor_cfg) -> "DirectionFinder":
        """From ``Scenario.sensor`` (``onboard.config.Sensor``) or anything with the same fields."""
        return cls(float(sensor_cfg.sigma_rad), float(sensor_cfg.p_detect), float(sensor_cfg.clutter_rate))


def _uniform_bearings(rng: np.random.Generator, n: int) -> np.ndarray:
    # rng.uniform is on [0, 2pi): pi - u is on (-pi, pi], the measurement space, both ends right
    return np.pi - rng.uniform(0.0, 2.0 * np.pi, n)


def df_scan(target_positions, sensor_position, df: DirectionFinder,
            rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """One scan of the UAV's DF: per target channel, a 1-D float array of bearings (rad).

    target_positions (M, >=2) ENU m; sensor_position (>=2,) ENU m. The draws per channel are made
    in a fixed order (detection, noise, clutter count, clutter, shuffle), the noise always drawn,
    so a scan consumes the same stream whatever was detected.
    """
    return tuple(b for b, _ in df_scan_labelled(target_positions, sensor_position, df, rng))


def df_scan_labelled(target_positions, sensor_position, df: DirectionFinder,
                     rng: np.random.Generator) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """``df_scan`` with, per channel, which bearing is the target's (a bool mask beside the
    bearings): the same draws from ``rng``, the same bearings in the same order. A simulated
    array DF (sim/stack/kraken.py) draws the direct path's peak and the clutter's differently."""
    targets = np.atleast_2d(np.asarray(target_positions, dtype=float))
    true = bearing(targets[:, :2], np.asarray(sensor_position, dtype=float)[:2])  # (M,)
    out = []
    for phi in np.atleast_1d(true):
        detected = rng.random() < df.p_detect
        noise = rng.normal(0.0, df.sigma_rad)
        clutter = _uniform_bearings(rng, rng.poisson(df.clutter_rate))
        b = np.concatenate([wrap([phi + noise]), clutter]) if detected else clutter
        is_target = np.zeros(len(b), dtype=bool)
        is_target[:1] = detected  # the detection is first, before the shuffle
        order = rng.permutation(len(b))  # the same shuffle as rng.permutation(b)
        out.append((b[order].astype(float), is_target[order]))
    return tuple(out)


def fixed_scans(target_positions, sensor_positions: Sequence, sigma_rad: float,
                rng: np.random.Generator) -> list[Scan]:
    """The paper's fixed-sensor baseline: one noisy bearing per target per sensor, no clutter.

    sensor_positions (K, >=2) ENU m, e.g. ``FIXED_SENSORS_M`` (2-D positions are put on the ground, z = 0). Returns one
    ``Scan`` per sensor; the monitor multiplies their likelihoods in one update. Use it with a
    filter whose SensorModel has p_detect = 1 and clutter_rate = 0.
    """
    targets = np.atleast_2d(np.asarray(target_positions, dtype=float))
    scans = []
    for s in np.atleast_2d(np.asarray(sensor_positions, dtype=float)):
        pos = np.array([s[0], s[1], s[2] if len(s) > 2 else 0.0])
        phi = wrap(bearing(targets[:, :2], pos[:2]) + rng.normal(0.0, sigma_rad, len(targets)))
        scans.append(Scan(pos, tuple(np.array([float(p)]) for p in phi)))
    return scans
