"""The app's settings as MAVLink parameters (component 191), and how they map onto a scenario.

All values travel as MAV_PARAM_TYPE_REAL32 (the numeric value itself; integer parameters are
rounded on set). A set outside [min, max], non-finite, or to an unknown name leaves the value
unchanged; the caller answers with the current value and a STATUSTEXT naming the problem.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace


@dataclass(frozen=True)
class ParamSpec:
    name: str  # <= 16 chars
    lo: float
    hi: float
    integer: bool
    doc: str  # unit and meaning


SPECS: tuple[ParamSpec, ...] = (
    ParamSpec("PMON_CLUTTER", 0.0, 50.0, False, "Lambda: expected clutter bearings per scan"),
    ParamSpec("PMON_PD", 0.01, 1.0, False, "p_D: detection probability"),
    ParamSpec("PMON_SIGMA_DEG", 0.05, 30.0, False, "bearing noise, deg (1 sigma)"),
    ParamSpec("PMON_NR", 0, 20, True, "N_r: radial steps of the candidate grid"),
    ParamSpec("PMON_NTH", 1, 72, True, "N_theta: headings of the candidate grid"),
    ParamSpec("PMON_DR", 0.5, 100.0, False, "Delta_r: radial step, m"),
    ParamSpec("PMON_ALT", 2.0, 1000.0, False, "h: flight altitude, m above the mission origin"),
    ParamSpec("PMON_PARTICLES", 100, 20000, True, "particles per target"),
    ParamSpec("PMON_HORIZON", 2, 200, True, "T: guidance horizon, steps"),
    ParamSpec("PMON_REACH", 1.0, 500.0, False,
              "largest move asked per tick, m; farther candidates are excluded"),
    ParamSpec("PMON_SP_HZ", 5.0, 50.0, False, "setpoint re-send rate, Hz of autopilot time"),
    ParamSpec("PMON_SCAN_WAIT", 0.0, 0.9, False,
              "s after a scan's time to wait for missing channels before ticking"),
    ParamSpec("PMON_BUDGET", 0.1, 1.0, False,
              "s after a scan's time by which its setpoint must be sent, else the tick is missed"),
    ParamSpec("PMON_GUID_S", 0.0, 0.9, False,
              "s of autopilot time the targets' guidance may take per tick; then the best plan "
              "found so far, or the fallback (previous plan shifted, then coasting). "
              "0: no solve at all (fallback only; fault drill)"),
    ParamSpec("PMON_ALT_MIN", 0.0, 1000.0, False, "geofence floor, m above the mission origin"),
    ParamSpec("PMON_ALT_MAX", 2.0, 1000.0, False, "geofence ceiling, m above the mission origin"),
)
BY_NAME = {s.name: s for s in SPECS}
assert all(len(s.name) <= 16 for s in SPECS)


def defaults_from_scenario(sc) -> dict[str, float]:
    return {
        "PMON_CLUTTER": sc.sensor.clutter_rate,
        "PMON_PD": sc.sensor.p_detect,
        "PMON_SIGMA_DEG": math.degrees(sc.sensor.sigma_rad),
        "PMON_NR": sc.uav.n_radial,
        "PMON_NTH": sc.uav.n_heading,
        "PMON_DR": sc.uav.step_m,
        "PMON_ALT": sc.uav.altitude_m,
        "PMON_PARTICLES": sc.tracking.particles,
        "PMON_HORIZON": sc.guidance.horizon,
        "PMON_REACH": max(sc.uav.n_radial * sc.uav.step_m, 1.0),
        "PMON_SP_HZ": 10.0,
        "PMON_SCAN_WAIT": 0.3,
        "PMON_BUDGET": 0.9,
        "PMON_GUID_S": 0.3,
        "PMON_ALT_MIN": min(10.0, sc.uav.altitude_m),
        "PMON_ALT_MAX": max(120.0, sc.uav.altitude_m),
    }


# the flight altitude must stay inside the geofence's altitude band: a set that would break
# this is refused (never clipped), naming both parameters
_BAND = ("PMON_ALT_MIN", "PMON_ALT", "PMON_ALT_MAX")


class ParamTable:
    def __init__(self, values: dict[str, float]):
        self._values = {s.name: float(values[s.name]) for s in SPECS}
        self.version = 0  # bumped on every accepted change

    def names(self) -> list[str]:
        return [s.name for s in SPECS]

    def __getitem__(self, name: str) -> float:
        return self._values[name]

    def __contains__(self, name: str) -> bool:
        return name in self._values

    def __len__(self) -> int:
        return len(SPECS)

    def index(self, name: str) -> int:
        return self.names().index(name)

    def set(self, name: str, value: float) -> str | None:
        """Apply a set; None on success, else the reason it was refused (value unchanged)."""
        spec = BY_NAME.get(name)
        if spec is None:
            return f"unknown parameter {name!r}"
        if not math.isfinite(value):
            return f"{name}: value is not finite"
        if spec.integer:
            value = float(round(value))
        if not spec.lo <= value <= spec.hi:
            return f"{name}={value:g} out of range [{spec.lo:g}, {spec.hi:g}]"
        if name in _BAND:
            lo, h, hi = (value if n == name else self._values[n] for n in _BAND)
            if not lo <= h <= hi:
                return f"{name}={value:g} refused: need PMON_ALT_MIN <= PMON_ALT <= PMON_ALT_MAX"
        if value != self._values[name]:
            self._values[name] = value
            self.version += 1
        return None

    def apply(self, sc):
        """The scenario with these settings."""
        v = self._values
        return replace(
            sc,
            sensor=replace(sc.sensor, clutter_rate=v["PMON_CLUTTER"], p_detect=v["PMON_PD"],
                           sigma_rad=math.radians(v["PMON_SIGMA_DEG"])),
            uav=replace(sc.uav, n_radial=int(v["PMON_NR"]), n_heading=int(v["PMON_NTH"]),
                        step_m=v["PMON_DR"], altitude_m=v["PMON_ALT"]),
            tracking=replace(sc.tracking, particles=int(v["PMON_PARTICLES"])),
            guidance=replace(sc.guidance, horizon=int(v["PMON_HORIZON"])),
        )
