"""The vehicle's pose from MAVLink telemetry, in the ENU mission frame, and the frame edge.

Only this module and `link` know about NED and degE7: the mission frame is ENU (m) at the
scenario's geodetic origin. GLOBAL_POSITION_INT gives an absolute position, so the app does
not depend on where the autopilot's local (EKF) origin is; setpoints in LOCAL_NED are made
relative to that origin (GPS_GLOBAL_ORIGIN, or HOME_POSITION's origin-relative fields).
"""
from __future__ import annotations

import bisect
import math
import threading
from dataclasses import dataclass

import numpy as np
import pymap3d

from onboard.core.bearings import wrap


@dataclass(frozen=True)
class PoseSample:
    t: float  # autopilot s
    pos: np.ndarray  # (3,) ENU m
    vel: np.ndarray  # (3,) ENU m/s
    yaw: float | None = None  # rad, clockwise from north (the vehicle's heading); None: unknown


class Frame:
    """ENU mission frame at a geodetic origin (deg, deg, m AMSL)."""

    def __init__(self, lat: float, lon: float, alt: float):
        self.origin = (float(lat), float(lon), float(alt))

    def enu_from_geodetic(self, lat: float, lon: float, alt: float) -> np.ndarray:
        return np.array(pymap3d.geodetic2enu(lat, lon, alt, *self.origin), dtype=float)

    def geodetic_from_enu(self, enu) -> tuple[float, float, float]:
        lat, lon, alt = pymap3d.enu2geodetic(float(enu[0]), float(enu[1]), float(enu[2]), *self.origin)
        return float(lat), float(lon), float(alt)

    def ned_from_enu(self, enu, ned_origin: tuple[float, float, float]) -> np.ndarray:
        """Mission ENU -> the autopilot's local NED (origin ``ned_origin``, deg, deg, m AMSL)."""
        lat, lon, alt = self.geodetic_from_enu(enu)
        return np.array(pymap3d.geodetic2ned(lat, lon, alt, *ned_origin), dtype=float)

    def enu_from_ned(self, ned, ned_origin: tuple[float, float, float]) -> np.ndarray:
        lat, lon, alt = pymap3d.ned2geodetic(float(ned[0]), float(ned[1]), float(ned[2]), *ned_origin)
        return self.enu_from_geodetic(lat, lon, alt)

    def pose_from_global_position_int(self, msg) -> PoseSample:
        pos = self.enu_from_geodetic(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
        vel = np.array([msg.vy, msg.vx, -msg.vz], dtype=float) / 100.0  # NED cm/s -> ENU m/s
        hdg = heading_from_global_position_int(msg.hdg)
        yaw = None if hdg is None else float(wrap(math.radians(hdg)))
        return PoseSample(msg.time_boot_ms / 1000.0, pos, vel, yaw)


ORIGIN_TOL_M = 0.5  # a GPS_GLOBAL_ORIGIN within this of the fixed one is the same origin


def origin_of(msg) -> tuple[float, float, float] | None:
    """(lat deg, lon deg, alt m AMSL) of a GPS_GLOBAL_ORIGIN, None if out of range."""
    lat, lon, alt = msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3
    if not (abs(lat) <= 90.0 and abs(lon) <= 180.0 and -1000.0 <= alt <= 10000.0):
        return None
    if msg.latitude == 0 and msg.longitude == 0:
        return None  # "not set"
    return lat, lon, alt


def origin_offset_m(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
    """Distance between two local origins, m."""
    return float(np.linalg.norm(pymap3d.geodetic2enu(*b, *a)))


class FixedOrigin:
    """The autopilot's local NED origin, fixed by the first valid GPS_GLOBAL_ORIGIN heard.

    Setpoints go out in LOCAL_NED relative to it. The autopilot sets its EKF origin once (at the
    first GPS fix, or when a ground station sets it before flight) and does not move it in flight;
    a different origin arriving later is taken for what it most likely is on an unsigned link, a
    forged message, and is never adopted: ``offer`` reports it (the app stops commanding and says
    so, since it cannot tell which origin the vehicle flies by). ``clear()`` (an autopilot
    reboot) lets the next one be fixed.
    """

    def __init__(self):
        self.value: tuple[float, float, float] | None = None
        self.refused = 0  # different origins heard after the first

    def offer(self, origin: tuple[float, float, float]) -> float | None:
        """Fix ``origin`` if none is yet; returns None when it is (now) the fixed origin, else
        its distance in m from the fixed one (refused, counted)."""
        if self.value is None:
            self.value = origin
            return None
        off = origin_offset_m(self.value, origin)
        if off <= ORIGIN_TOL_M:
            return None
        self.refused += 1
        return off

    def clear(self) -> None:
        self.value = None


def heading_from_global_position_int(hdg_cdeg: int) -> float | None:
    """GLOBAL_POSITION_INT.hdg in degrees, None when the autopilot does not know it (65535) or
    it is out of its range (0..35999 cdeg; 36000 read as north)."""
    return None if hdg_cdeg > 36000 else hdg_cdeg / 100.0


def valid_global_position_int(msg) -> bool:
    """A fix worth using: lat/lon in range and not the all-zero 'no fix' message."""
    if msg.lat == 0 and msg.lon == 0:
        return False
    return abs(msg.lat) <= 900_000_000 and abs(msg.lon) <= 1_800_000_000


class PoseHistory:
    """Telemetry history; position at any autopilot time by interpolation.

    Beyond the newest sample the position is extrapolated with its velocity for at most
    ``max_extrapolation_s``; earlier than the oldest kept sample it is unknown (None).
    """

    def __init__(self, keep_s: float = 30.0, max_extrapolation_s: float = 1.0):
        self.keep_s = keep_s
        self.max_extrapolation_s = max_extrapolation_s
        self._t: list[float] = []
        self._s: list[PoseSample] = []
        self._lock = threading.Lock()

    def add(self, sample: PoseSample) -> None:
        with self._lock:
            if self._t and sample.t <= self._t[-1]:
                if sample.t < self._t[-1] - 5.0:  # autopilot rebooted: start over
                    self._t.clear()
                    self._s.clear()
                else:
                    return
            self._t.append(sample.t)
            self._s.append(sample)
            cut = bisect.bisect_left(self._t, sample.t - self.keep_s)
            if cut > 0:
                del self._t[:cut]
                del self._s[:cut]

    def latest(self) -> PoseSample | None:
        with self._lock:
            return self._s[-1] if self._s else None

    def at(self, t: float) -> np.ndarray | None:
        """ENU position (3,) at autopilot time t, or None if not covered."""
        return self._interpolate(t, "pos")

    def velocity_at(self, t: float) -> np.ndarray | None:
        """ENU velocity (3,) at autopilot time t, interpolated as ``at`` interpolates the position
        (after the newest sample its velocity, for at most ``max_extrapolation_s``), or None."""
        return self._interpolate(t, "vel")

    def _interpolate(self, t: float, field: str) -> np.ndarray | None:
        """``field`` ("pos" or "vel") at t: linear between the samples around it; after the newest,
        for at most ``max_extrapolation_s``, the position carried on at the newest velocity and
        the velocity held."""
        with self._lock:
            i = self._index(t)
            if i is None:
                return None
            if i == len(self._t):
                last = self._s[-1]
                dt = t - last.t
                if dt > self.max_extrapolation_s:
                    return None
                return last.pos + last.vel * dt if field == "pos" else last.vel.copy()
            if i == 0 or self._t[i] == t:
                return getattr(self._s[i], field).copy()
            a, b = getattr(self._s[i - 1], field), getattr(self._s[i], field)
            w = (t - self._t[i - 1]) / (self._t[i] - self._t[i - 1])
            return a + w * (b - a)

    def _index(self, t: float) -> int | None:
        """(under the lock) the first sample at or after t (len: after the newest); None if t is
        before the oldest (50 ms of slack) or nothing is held."""
        if not self._t or t < self._t[0] - 0.05:
            return None
        return bisect.bisect_left(self._t, t)

    def yaw_at(self, t: float) -> float | None:
        """Heading (rad, clockwise from north, (-pi, pi]) at autopilot time t, interpolated the
        short way round between the samples around it; after the newest the newest, for at most
        ``max_extrapolation_s`` (no yaw rate is known); None if not covered or unknown."""
        with self._lock:
            i = self._index(t)
            if i is None:
                return None
            if i == len(self._t):
                last = self._s[-1]
                return last.yaw if t - last.t <= self.max_extrapolation_s and last.yaw is not None \
                    else None
            if i == 0 or self._t[i] == t:
                return self._s[i].yaw
            a, b = self._s[i - 1], self._s[i]
        if a.yaw is None or b.yaw is None:
            return None
        w = (t - a.t) / (b.t - a.t)
        d = math.remainder(b.yaw - a.yaw, math.tau)
        return float(wrap(a.yaw + w * d))


def is_finite(v) -> bool:
    return all(math.isfinite(float(x)) for x in v)
