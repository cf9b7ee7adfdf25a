"""The app's target estimates (PMON_TGT) checked and made geodetic, for the outputs that draw
them on other tools' maps (groundstation/adsb.py, groundstation/tak.py).

Whatever arrives is assumed hostile: a PMON_TGT becomes an ``OutputEstimate`` only when it
comes from the onboard app's component, names a target the outputs can address, and every
number it carries is finite and within what a ground target of one mission can be. Anything
else is refused with a reason (counted by the caller); an output is never made from it, so
no ADSB_VEHICLE or CoT event ever carries an invalid coordinate.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from groundstation import protocol as P
from groundstation.scene import covariance_ellipse

MAX_TARGETS = 16  # the ADSB address block holds 16 targets per vehicle (groundstation/adsb.py)
MAX_RANGE_M = 100_000.0  # farther from the mission origin than this is no target of the mission
MAX_SIGMA_M = 100_000.0
MAX_SPEED_MPS = 300.0  # a ground target faster than this is a broken estimate
MAX_AGE_S = 1e6


@dataclass(frozen=True)
class OutputEstimate:
    """One target estimate as the outputs draw it: WGS 84 position, 1-sigma circle, course."""

    index: int
    name: str  # T1, T2, ... as every other view names them
    x_m: float  # mission ENU, m
    y_m: float
    lat_deg: float
    lon_deg: float
    alt_m: float  # AMSL: the mission origin's altitude plus the estimate's height (ground targets)
    vx_mps: float
    vy_mps: float
    sigma_x_m: float
    sigma_y_m: float
    cov_xy_m2: float
    radius_1sigma_m: float  # radius of the circle around the 1-sigma ellipse the live view draws
    age_s: float  # since the last DF scan of this target's channel (the data the estimate rests on)
    tick_time_s: float  # autopilot s
    degenerate: bool
    doing: str = "-"  # what it most likely does (``TargetEstimate.mode_text``)

    @property
    def speed_mps(self) -> float:
        return math.hypot(self.vx_mps, self.vy_mps)

    @property
    def course_deg(self) -> float:
        """Course over ground, degrees clockwise from true north, [0, 360)."""
        return math.degrees(math.atan2(self.vx_mps, self.vy_mps)) % 360.0


def radius_1sigma_m(sigma_x: float, sigma_y: float, cov_xy: float) -> float | None:
    """Radius of the smallest circle about the estimate that holds the 1-sigma ellipse the live
    view draws: the farthest of ``covariance_ellipse``'s points (the same function and points
    as groundstation/static/view.js), i.e. the ellipse's semi-major axis within 0.04 %."""
    pts = covariance_ellipse(0.0, 0.0, sigma_x, sigma_y, cov_xy, 1.0)
    if pts is None:
        return None
    return float(np.max(np.hypot(pts[:, 0], pts[:, 1])))


def check(msg, frame) -> tuple[OutputEstimate | None, str | None]:
    """(estimate, None) or (None, reason) for one PMON_TGT DEBUG_FLOAT_ARRAY; ``frame`` is the
    mission's ``onboard.app.autopilot.pose.Frame`` (its geodetic origin). ``reason`` "not yet detected"
    is not a fault: the estimate is the prior until its channel's first scan."""
    if msg.get_srcComponent() != P.APP_COMPID:
        return None, "not from the onboard app's component"
    j = int(msg.array_id)
    if not 0 <= j < MAX_TARGETS:
        return None, f"target index outside 0..{MAX_TARGETS - 1}"
    d = [float(v) for v in msg.data[:14]]
    if len(d) < 14 or not all(math.isfinite(v) for v in d):
        return None, "not finite"
    x, y, z, vx, vy = d[0], d[1], d[2], d[3], d[4]
    sx, sy, since, cxy, t = d[6], d[7], d[8], d[9], d[13]
    if math.hypot(x, y) > MAX_RANGE_M or abs(z) > 10_000.0:
        return None, "position out of range"
    if not (0.0 <= sx <= MAX_SIGMA_M and 0.0 <= sy <= MAX_SIGMA_M) or abs(cxy) > sx * sy * (1 + 1e-3) + 1e-6:
        return None, "covariance out of range"
    if math.hypot(vx, vy) > MAX_SPEED_MPS:
        return None, "velocity out of range"
    if not 0.0 <= t <= MAX_AGE_S:
        return None, "tick time out of range"
    if since == -1.0:
        return None, "not yet detected"
    if not 0.0 <= since <= MAX_AGE_S:
        return None, "age out of range"
    r = radius_1sigma_m(sx, sy, cxy)
    lat, lon, alt = frame.geodetic_from_enu((x, y, z))
    if r is None or not (abs(lat) <= 90.0 and abs(lon) <= 180.0 and math.isfinite(alt)):
        return None, "position out of range"
    return OutputEstimate(j, f"T{j + 1}", x, y, lat, lon, alt, vx, vy, sx, sy, cxy, r, since, t,
                          bool(d[12]), P.TargetEstimate.from_msg(msg).mode_text()), None
