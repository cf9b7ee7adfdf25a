"""Direction-of-arrival maths for an array direction finder (KrakenSDR): plain arrays in and out.

Conventions (docs/KRAKENSDR.md has the sources):

* An array reports angles in its own frame. KrakenSDR's 360-bin DoA spectrum is indexed by the
  *unit-circle* angle theta in degrees (bin i = theta of i degrees), counterclockwise seen from
  above, 0 at the array's reference direction (antenna 0 of a UCA). Its "compass" angle, the
  one its own mapping code adds to the vehicle heading, is ``360 - theta``: clockwise from the
  same reference.
* The filter's bearing is radians clockwise from north on (-pi, pi] (onboard.core.bearings).

So a unit-circle angle theta seen by an array whose reference points ``mount`` clockwise from
the vehicle's nose, on a vehicle heading ``heading`` (clockwise from north), is the bearing
``wrap(heading + mount - theta)``.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import find_peaks

from onboard.core.bearings import wrap

SPECTRUM_BINS = 360  # KrakenSDR's DoA grid: 0..359 degrees, one bin per degree
CONVENTIONS = ("unit_circle", "compass")


def unit_circle_deg(doa_deg, convention: str) -> np.ndarray:
    """An array angle (degrees) as written in ``convention``, as the unit-circle angle."""
    a = np.asarray(doa_deg, dtype=float)
    if convention == "unit_circle":
        return a
    if convention == "compass":
        return 360.0 - a
    raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")


def bearing_from_array(theta_deg, heading_rad, mount_rad: float = 0.0) -> np.ndarray:
    """Bearing(s) (rad, clockwise from north, (-pi, pi]) of unit-circle array angle(s)
    ``theta_deg`` seen with the vehicle heading ``heading_rad`` (clockwise from north) and the
    array's reference ``mount_rad`` clockwise from the vehicle's nose."""
    return wrap(np.asarray(heading_rad, float) + mount_rad - np.radians(np.asarray(theta_deg, float)))


def array_from_bearing(bearing_rad, heading_rad, mount_rad: float = 0.0) -> np.ndarray:
    """The inverse of ``bearing_from_array``: unit-circle array angle(s) in [0, 360) degrees."""
    theta = np.degrees(np.asarray(heading_rad, float) + mount_rad - np.asarray(bearing_rad, float))
    return np.mod(theta, 360.0)


def circular_distance_deg(a, b) -> np.ndarray:
    """|a - b| on the circle, degrees in [0, 180]."""
    d = np.mod(np.asarray(a, float) - np.asarray(b, float), 360.0)
    return np.minimum(d, 360.0 - d)


def detect_convention(doa_deg: float, spectrum: np.ndarray, tol_deg: float = 2.0) -> str | None:
    """Which convention a line's main DoA is written in, from its spectrum (always unit-circle):
    KrakenSDR's main DoA is the spectrum's argmax, written as theta (``unit_circle``) or as
    ``360 - theta`` (``compass``) depending on the software version. The nearer of the two
    within ``tol_deg`` (the spectrum is rounded to 0.01 dB, so neighbouring bins can tie); None
    when neither is, or both are equally near (near 0 and 180 degrees the two agree to within
    twice the distance: nothing is learnt there)."""
    k = float(np.argmax(spectrum))
    du = float(circular_distance_deg(doa_deg, k))
    dc = float(circular_distance_deg(doa_deg, 360.0 - k))
    if min(du, dc) > tol_deg or du == dc:
        return None
    return "unit_circle" if du < dc else "compass"


def spectrum_peaks(spectrum_db: np.ndarray, floor_db: float, prominence_db: float,
                   max_peaks: int) -> tuple[np.ndarray, np.ndarray]:
    """Peaks of a circular DoA spectrum (dB, one bin per degree): unit-circle angles (degrees in
    [0, 360), refined between bins by a parabola through the peak bin and its neighbours) and
    heights in dB relative to the highest bin (<= 0), strongest first.

    A peak counts if it is within ``floor_db`` of the highest bin and stands at least
    ``prominence_db`` above the higher of the two valleys that separate it from higher ground
    (topographic prominence, on the circle): ripple of the noise floor and shoulders of a lobe
    are not peaks. At most ``max_peaks`` are returned. A flat spectrum has none."""
    s = np.asarray(spectrum_db, dtype=float).reshape(-1)
    n = len(s)
    if n < 3 or max_peaks < 1 or not np.isfinite(s).all():
        return np.empty(0), np.empty(0)
    top = float(s.max())
    # three copies: the middle one's peaks see their neighbours across 0/360 and the valleys
    # beyond them, so prominence is measured on the circle (the highest peak's is its height
    # above the spectrum's minimum)
    ext = np.concatenate([s, s, s])
    idx, props = find_peaks(ext, height=top - floor_db, prominence=prominence_db)
    keep = (idx >= n) & (idx < 2 * n)
    idx = idx[keep] - n
    if not len(idx):
        return np.empty(0), np.empty(0)
    heights = s[idx]
    order = np.argsort(-heights, kind="stable")[:max_peaks]
    idx, heights = idx[order], heights[order]
    a, b, c = s[(idx - 1) % n], s[idx], s[(idx + 1) % n]
    den = a - 2.0 * b + c
    with np.errstate(divide="ignore", invalid="ignore"):
        delta = np.where(den < 0, 0.5 * (a - c) / den, 0.0)
    angles = np.mod(idx + np.clip(delta, -0.5, 0.5), float(n)) * (360.0 / n)
    return angles, heights - top


def clutter_rate(counts, p_detect: float, lo: float, hi: float) -> float:
    """The clutter rate Lambda the measurement counts show: a scan of the RFS model holds the
    target's bearing with probability p_D and Poisson(Lambda) clutter, E[n] = p_D + Lambda, so
    Lambda = mean(n) - p_D, clipped to [lo, hi] (``lo`` with no counts yet)."""
    c = np.asarray(counts, dtype=float)
    if not c.size:
        return float(lo)
    return float(np.clip(c.mean() - p_detect, lo, hi))
