"""The declaration's machinery: how one setting is read, checked and shown (``Setting``), the field
makers a section declares its settings with (``number``, ``integer``, ``flag``, ``choice``, ...,
``section``, ``records``), and walking a declaration (``walk``) and writing its values as the tables
do (``value_text``). The sections themselves are onboard/settings/sections.py.

Pure Python (no YAML, no numpy): the ground station imports it for the parameters' ranges.
"""
from __future__ import annotations

from dataclasses import MISSING, dataclass, field, fields
from typing import Any


class ConfigError(ValueError):
    """A configuration value is missing or invalid; the message starts with its key path."""


@dataclass(frozen=True)
class Setting:
    """How one setting is read, checked and shown.

    kind: ``number`` (a float), ``integer``, ``even`` (an even integer), ``flag`` (true/false),
    ``choice`` (one of ``choices``), ``text`` (a name), ``names`` (a list of up to ``max_items``
    names), ``location`` (where to read from: an
    ``http://`` or ``file://`` URL or an absolute path, or one of the words in ``choices``),
    ``vector`` (``size`` numbers, or 1 to ``max_items`` when ``size`` is None). ``lo``/``hi`` bound a number or each number of a
    vector (``lo_open``/``hi_open``: the bound itself excluded). ``nullable``: ``null`` is a
    value (its meaning in ``doc``). ``param``: the PMON_* parameter that sets it in flight.
    ``paper``: the value is the paper's (Sec. V-A), not ours. ``experimental``: a research knob
    an operator or integrator never needs (a filter's or planner's internals): its default is the
    configuration that flies, it has no PMON_* parameter, docs/SETTINGS.md lists it apart and
    ``pmon check-config`` names it when a file or ``--set`` changes it.
    """

    kind: str
    doc: str
    unit: str = ""
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple[str, ...] = ()
    size: int | None = None
    max_items: int | None = None
    nullable: bool = False
    param: str | None = None
    paper: bool = False
    experimental: bool = False

    def range_text(self) -> str:
        """The range as a reader writes it: ``[0.05, 30] deg``, ``(0, 5]``, ``one of a | b``."""
        if self.kind == "choice":
            return " or ".join(self.choices)
        if self.kind == "flag":
            return "true or false"
        if self.kind == "text":
            return f"1 to {TEXT_CHARS} characters"
        if self.kind == "names":
            return f"a list of up to {self.max_items} names"
        if self.kind == "location":
            return " or ".join((LOCATION_FORMS,) + self.choices)
        if self.lo is None:
            return ""
        text = f"{'(' if self.lo_open else '['}{show_number(self.lo)}, {show_number(self.hi)}{')' if self.hi_open else ']'}"
        if self.kind == "even":
            text += ", even"
        return f"{text} {self.unit}".strip()

    def contains(self, v: float) -> bool:
        lo_ok = v > self.lo if self.lo_open else v >= self.lo
        hi_ok = v < self.hi if self.hi_open else v <= self.hi
        return lo_ok and hi_ok


TEXT_CHARS = 64  # a name: shown in tables, logs and messages
LOCATION_CHARS = 512  # a location setting
LOCATION_STARTS = ("http://", "file://", "/")  # what a location setting may start with
LOCATION_FORMS = "http://HOST:PORT/PATH, file:///PATH or an absolute path"


def show_number(x: float) -> str:
    """1e6 rather than 1e+06."""
    return f"{x:g}".replace("e+0", "e").replace("e+", "e").replace("e-0", "e-")


def _setting(default: Any, kind: str, doc: str, **kw) -> Any:
    """A dataclass field declaring a setting; ``default`` MISSING: the file must state it."""
    meta = {"setting": Setting(kind, doc, **kw)}
    if isinstance(default, (list, tuple)):
        return field(default=tuple(default), metadata=meta)
    return field(default=default, metadata=meta)


def number(default, lo, hi, unit, doc, *, lo_open=False, hi_open=False, nullable=False, param=None,
           paper=False, experimental=False) -> Any:
    return _setting(default, "number", doc, unit=unit, lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open,
                    nullable=nullable, param=param, paper=paper, experimental=experimental)


def integer(default, lo, hi, unit, doc, *, param=None, paper=False, even=False, experimental=False) -> Any:
    return _setting(default, "even" if even else "integer", doc, unit=unit, lo=lo, hi=hi, param=param,
                    paper=paper, experimental=experimental)


def flag(default, doc, *, experimental=False) -> Any:
    return _setting(default, "flag", doc, experimental=experimental)


def choice(default, choices, doc, *, paper=False, experimental=False) -> Any:
    return _setting(default, "choice", doc, choices=tuple(choices), paper=paper, experimental=experimental)


def text(default, doc, *, nullable=False, experimental=False) -> Any:
    return _setting(default, "text", doc, nullable=nullable, experimental=experimental)


def names(default, max_items, doc, *, experimental=False) -> Any:
    return _setting(default, "names", doc, max_items=max_items, experimental=experimental)


def location(default, doc, *, words=(), nullable=False, experimental=False) -> Any:
    """Where to read from; ``words``: plain words it may also be (``auto``)."""
    return _setting(default, "location", doc, choices=tuple(words), nullable=nullable, experimental=experimental)


def vector(default, size, lo, hi, unit, doc, *, max_items=None, lo_open=False, paper=False,
           experimental=False) -> Any:
    return _setting(default, "vector", doc, unit=unit, lo=lo, hi=hi, size=size, max_items=max_items,
                    lo_open=lo_open, paper=paper, experimental=experimental)


def section(cls, doc: str, required: bool = False) -> Any:
    """A nested mapping of settings; left out of a file, its defaults (unless ``required``)."""
    meta = {"section": cls, "doc": doc}
    return field(metadata=meta) if required else field(default_factory=cls, metadata=meta)


def records(cls, min_items: int, max_items: int, doc: str, required: bool = True) -> Any:
    """A list of mappings of ``cls`` (targets, goals, obstacles, kraken.vfos)."""
    meta = {"records": cls, "min_items": min_items, "max_items": max_items, "doc": doc}
    return field(metadata=meta) if required else field(default=(), metadata=meta)


def walk(cls, prefix: str = ""):
    """Every setting under ``cls``: (dotted key, dataclass field, Setting); records as ``key[].field``."""
    for f in fields(cls):
        if not f.init or f.name in ("source", "overrides"):  # a Scenario's bookkeeping, not settings
            continue
        key = f"{prefix}{f.name}"
        if "section" in f.metadata:
            yield from walk(f.metadata["section"], key + ".")
        elif "records" in f.metadata:
            yield from walk(f.metadata["records"], key + "[].")
        else:
            yield key, f, f.metadata["setting"]


def default_text(f) -> str:
    return "required" if f.default is MISSING else value_text(f.default)


def value_text(v: Any) -> str:
    """A setting's value as the table writes it: null, true, [1, 2], 0.05."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, tuple):
        return "[" + ", ".join(show_number(x) for x in v) + "]"
    if isinstance(v, float):
        return show_number(v)
    return str(v)
