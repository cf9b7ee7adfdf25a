"""The geofence a setpoint must be inside, checked where the setpoint is planned and again on
the message that carries it out.

Rules (a point breaking any is refused, never clipped): inside the mission area (ENU box),
inside the altitude band PMON_ALT_MIN..MAX, at the planner's altitude h (plan time only: h may
change between ticks, and it is not a safety limit), outside every obstacle inflated by the UAV
margin, and the straight path from where the vehicle is to the point clear of them.

``outgoing_violation`` reads the position from the SET_POSITION_TARGET_LOCAL_NED message itself
(float32, as it goes on the wire, in the frame it goes out in: LOCAL_NED at the autopilot's
origin) and converts it back to ENU with the origin the app fixed, so what is checked is what
the vehicle will be told, whatever happened between the plan and the message: a bug in the
conversion, a wrong origin, a field mixed up. Only the position fields are read, so a velocity
feed-forward added to the message (issue 24) leaves the check as it is. Pure functions of their
arguments; the app calls them under its lock.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from onboard.core.obstacles import Obstacles

MAV_FRAME_LOCAL_NED = 1
POSITION_IGNORE = 0b111  # type_mask bits 0..2: x, y, z ignored
SEND_TOL_M = 0.01  # float32 fields and the geodetic round trip move a point by < 1 mm


@dataclass(frozen=True, eq=False)
class Fence:
    area_min: np.ndarray  # (3,) ENU m
    area_max: np.ndarray
    alt_min_m: float  # PMON_ALT_MIN, ENU up
    alt_max_m: float
    obstacles: Obstacles  # inflated by the UAV margin
    altitude_m: float | None = None  # the mission altitude the planner flies at, ENU up; None: not checked

    @classmethod
    def of(cls, setup, params, at_altitude: bool = True) -> "Fence":
        """The fence of a core ``MonitorSetup`` and the app's parameters; ``at_altitude``: with the
        mission altitude rule (plan time only)."""
        return cls(np.asarray(setup.area_min, float), np.asarray(setup.area_max, float),
                   params.settings.app.fence_min_m, params.settings.app.fence_max_m, setup.uav_obstacles,
                   float(setup.grid.altitude_m) if at_altitude else None)


def violation(fence: Fence, p, centre=None, tol_m: float = 0.0) -> str | None:
    """The rule the ENU point ``p`` breaks (None: inside the fence). ``centre``: where the
    vehicle is (ENU), for the path rule; None skips it. ``tol_m`` widens the box and band
    comparisons (for a point read back from float32 fields)."""
    p = np.asarray(p, dtype=float)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        return "not a finite position"
    if np.any(p < fence.area_min - tol_m) or np.any(p > fence.area_max + tol_m):
        return "outside the area"
    if not fence.alt_min_m - tol_m <= p[2] <= fence.alt_max_m + tol_m:
        return "outside the altitude band"
    if fence.altitude_m is not None and abs(p[2] - fence.altitude_m) > max(tol_m, 1e-6):
        return "not at altitude h"
    if len(fence.obstacles) and fence.obstacles.contains(p).any():
        return "inside an obstacle"
    if centre is not None and len(fence.obstacles):
        c = np.asarray(centre, dtype=float)
        start = np.array([c[0], c[1], p[2]])
        if np.all(np.isfinite(start)) and fence.obstacles.segments_cross(start[None], p[None]).any():
            return "path crosses an obstacle"
    return None


def outgoing_violation(msg, frame, ned_origin, fence: Fence, centre=None,
                       tol_m: float = SEND_TOL_M) -> str | None:
    """The rule a SET_POSITION_TARGET_LOCAL_NED message about to be sent breaks (None: send it).

    ``frame``: the mission frame (``pose.Frame``); ``ned_origin``: the autopilot's local origin
    the app fixed (deg, deg, m AMSL)."""
    if msg.coordinate_frame != MAV_FRAME_LOCAL_NED:
        return f"frame {msg.coordinate_frame} is not LOCAL_NED"
    if msg.type_mask & POSITION_IGNORE:
        return "position fields ignored by type_mask"
    if ned_origin is None:
        return "no fixed NED origin"
    with np.errstate(over="ignore"):  # past float32's range: inf, refused below
        ned = np.array([msg.x, msg.y, msg.z], dtype=np.float32).astype(float)  # what goes on the wire
    if not np.all(np.isfinite(ned)):
        return "not a finite position"
    return violation(fence, frame.enu_from_ned(ned, ned_origin), centre, tol_m)
