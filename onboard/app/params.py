"""The app's settings as MAVLink parameters (component 191), and how they map onto a scenario.

Each PMON_* parameter is a scenario setting declared in onboard/settings/sections.py (``param=``): its
range, integer-ness and meaning come from there, its value at start from the scenario
(``defaults_from_scenario``), and a set is checked as a file is: the range first (one line
naming the parameter and the range), then the whole scenario with the new value
(``onboard.config.override``: cross-field checks included, e.g. PMON_HORIZON below
``planning.lookahead_steps`` with the lookahead planner). All values travel as
MAV_PARAM_TYPE_REAL32 (the numeric value itself; integer parameters are rounded on set). A
refused set, a non-finite value or an unknown name leaves the value unchanged; the caller
answers with the current value and a STATUSTEXT naming the problem.

Light to import (no YAML, no numpy): the ground station reads SPECS and BY_NAME for its
``params list``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from onboard.settings.sections import PARAMS, SETTINGS, value_of


@dataclass(frozen=True)
class ParamSpec:
    name: str  # <= 16 chars
    lo: float
    hi: float
    integer: bool
    doc: str  # meaning and unit
    key: str  # the scenario setting it sets (onboard/settings/sections.py)


def _spec(name: str, key: str) -> ParamSpec:
    s = SETTINGS[key]
    return ParamSpec(name, s.lo, s.hi, s.kind in ("integer", "even"), f"{s.doc}{', ' + s.unit if s.unit else ''}",
                     key)


SPECS: tuple[ParamSpec, ...] = tuple(_spec(name, key) for name, key in PARAMS.items())
BY_NAME = {s.name: s for s in SPECS}
assert all(len(s.name) <= 16 for s in SPECS)


def defaults_from_scenario(sc) -> dict[str, float]:
    """Each parameter's value in the scenario (a null setting's derived value: settings.DERIVED)."""
    return {s.name: float(value_of(sc, s.key)) for s in SPECS}


class ParamTable:
    """The parameters' current values, checked against the scenario they apply to."""

    def __init__(self, values: dict[str, float], scenario):
        self._values = {s.name: float(values[s.name]) for s in SPECS}
        self._scenario = scenario
        self.version = 0  # bumped on every accepted change
        self._settings = self.apply(scenario)

    @property
    def settings(self):
        """The scenario with the parameters' current values: what the app reads them as, by their
        typed settings (``params.settings.app.tick_budget_s``), never by their PMON names. Replaced
        whole on an accepted set, so a reader on another thread sees the old or the new one."""
        return self._settings

    @classmethod
    def from_scenario(cls, sc) -> "ParamTable":
        """The parameters of scenario ``sc`` (the one ``apply`` and the checks of ``set`` use)."""
        return cls(defaults_from_scenario(sc), sc)

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
        from onboard.config import ConfigError, override

        spec = BY_NAME.get(name)
        if spec is None:
            return f"unknown parameter {name!r}"
        if not math.isfinite(value):
            return f"{name}: value is not finite"
        if spec.integer:
            value = float(round(value))
        if not spec.lo <= value <= spec.hi:
            return f"{name}={value:g} out of range [{spec.lo:g}, {spec.hi:g}]"
        if value == self._values[name]:
            return None
        values = {**self._values, name: value}
        try:  # the scenario with every parameter: each setting's range, then the cross-field checks
            settings = override(self._scenario, _changes(values))
        except ConfigError as exc:
            return f"{name}={value:g} refused: {exc}"
        self._values = values
        self._settings = settings
        self.version += 1
        return None

    def apply(self, sc):
        """The scenario with these settings (checked as a file is)."""
        from onboard.config import override

        return override(sc, _changes(self._values))


def _changes(values: dict[str, float]) -> dict[str, float | int]:
    """Parameter values as scenario settings."""
    return {s.key: int(values[s.name]) if s.integer else values[s.name] for s in SPECS}
