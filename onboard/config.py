"""Scenario configuration: YAML in, typed, validated, immutable objects out.

What a scenario holds, with each setting's default, unit, range and doc, is declared once in
onboard/settings/sections.py; this module reads a file or a tree against that declaration, checks what
involves several settings (``CHECKS``), and applies ``KEY=VALUE`` changes (``override``: the one
way a scenario is changed, used by ``--set``, the flight policies, the evaluation's methods and
the PMON_* parameters, so a change gets the same checks as a file).

Every error is one line that starts with the key path, e.g. ``obstacles[2].size_m[1]: must be >
0``, ``sensor.sigma_deg: must be in [0.05, 30] deg, got 0.01745``. Only the YAML safe loader is
used: nothing in a config file is ever executed.

Hostile files are refused with one ConfigError, never a traceback or a hang: only a regular
file of at most ``MAX_FILE_BYTES`` is read (checked on the open descriptor before reading:
/dev/zero or a FIFO are refused, not read; onboard/files.py), nesting too deep for the YAML
reader is an error, a key given twice in a mapping is an error (YAML readers keep the last),
an integer literal longer than ``MAX_INT_CHARS`` is never converted (Python refuses to convert
more than 4300 digits; every range is far below 10^30) and is shown cut in its error, values
are shown cut to ``SHOW_CHARS``, and every list is bounded by its declaration.
"""
from __future__ import annotations

import math
import re
from dataclasses import MISSING, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any, Mapping, Sequence
from urllib.parse import quote, urlsplit

import numpy as np
import yaml

from onboard.files import FileRefused, read_regular
from onboard.settings import ConfigError
from onboard.settings.declare import LOCATION_CHARS, LOCATION_STARTS, TEXT_CHARS, Setting
from onboard.settings.sections import Scenario, value_of

BUILTIN_SCENARIOS = ("paper",)
MAX_FILE_BYTES = 1_000_000
SHOW_CHARS = 40  # of a bad value in a message
MAX_INT_CHARS = 30  # an integer literal longer than this is out of every setting's range


# --------------------------------------------------------------------------- YAML


class _Huge:
    """An integer literal too long to convert (``MAX_INT_CHARS``): its setting's check refuses it."""

    def __init__(self, text: str):
        self.text = text

    def __repr__(self) -> str:
        digits = self.text.lstrip("+-")
        return f"{self.text[:7]}... ({len(digits)} digits)"


class _Loader(yaml.SafeLoader):
    pass


def _construct_int(loader: _Loader, node: yaml.ScalarNode):
    text = loader.construct_scalar(node)
    if len(text) > MAX_INT_CHARS:
        return _Huge(text)
    return yaml.SafeLoader.construct_yaml_int(loader, node)


_Loader.add_constructor("tag:yaml.org,2002:int", _construct_int)
# YAML 1.1 (PyYAML) reads 1e-9 as a string: its floats need a dot. YAML 1.2 and every user read a number.
_Loader.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+$"),
                              list("-+0123456789"))


def read_yaml(text: str, where: str = "", invalid: str = "not valid YAML") -> Any:
    """A YAML document as plain data, with the safe loader. ConfigError for a syntax error or a
    tag (``invalid``, with line and column), nesting too deep, or a key given twice in a mapping
    (its key path, under ``where``, and both lines)."""
    head = f"{where}: " if where else ""
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _no_duplicate_keys(node, where, set())
        return loader.construct_document(node)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = str(getattr(exc, "problem", None) or exc).splitlines()[0]
        raise ConfigError(f"{head}{invalid}{at}: {problem}") from None
    except RecursionError:
        raise ConfigError(f"{head}nested too deeply") from None
    finally:
        loader.dispose()


def _no_duplicate_keys(node: yaml.Node, path: str, seen: set[int]) -> None:
    if id(node) in seen:  # an alias: checked where it was anchored (and no exponential walk)
        return
    seen.add(id(node))
    if isinstance(node, yaml.MappingNode):
        lines: dict[str, int] = {}
        for key, value in node.value:
            name = key.value if isinstance(key, yaml.ScalarNode) else "?"
            child = f"{path}.{name}" if path else name
            if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                if name in lines:
                    raise ConfigError(f"{_cut(child)}: key given twice (lines {lines[name]} and "
                                      f"{key.start_mark.line + 1})")
                lines[name] = key.start_mark.line + 1
            _no_duplicate_keys(value, child, seen)
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _no_duplicate_keys(item, f"{path}[{i}]", seen)


# --------------------------------------------------------------------------- reading against the declaration


def _kind(v: Any) -> str:
    if isinstance(v, _Huge):
        return f"an integer of {len(v.text.lstrip('+-'))} digits"
    return "nothing" if v is None else type(v).__name__


def _show(v: Any) -> str:
    """A value for a message, cut to SHOW_CHARS (a 400-digit integer must not fill the line)."""
    if isinstance(v, int) and not isinstance(v, bool) and v.bit_length() > 3.33 * SHOW_CHARS:
        return f"an integer of about {int(v.bit_length() * math.log10(2)) + 1} digits"  # str() of it may raise
    return _cut(repr(v))


def _cut(text: str) -> str:
    return text if len(text) <= SHOW_CHARS else text[:SHOW_CHARS - 3] + "..."


class _Node:
    """A value in the tree together with its key path, for error messages."""

    def __init__(self, value: Any, path: str):
        self.value = value
        self.path = path

    def fail(self, reason: str) -> ConfigError:
        return ConfigError(f"{self.path or '<root>'}: {reason}")

    def child(self, key: str | int) -> "_Node":
        path = f"{self.path}[{key}]" if isinstance(key, int) else (f"{self.path}.{key}" if self.path else key)
        return _Node(self.value[key], path)

    def mapping(self, keys: list[str]) -> None:
        if not isinstance(self.value, dict):
            raise self.fail(f"must be a mapping, got {_kind(self.value)}")
        for k in self.value:
            if k not in keys:
                name = _cut(str(k))
                raise ConfigError(f"{self.path + '.' if self.path else ''}{name}: unknown key "
                                  f"(expected one of: {', '.join(keys)})")

    def items(self, min_items: int, max_items: int) -> list["_Node"]:
        if not isinstance(self.value, list):
            raise self.fail(f"must be a list, got {_kind(self.value)}")
        if len(self.value) < min_items:
            raise self.fail(f"must have at least {min_items} item(s)")
        if len(self.value) > max_items:
            raise self.fail(f"must have at most {max_items} items, got {len(self.value)}")
        return [self.child(i) for i in range(len(self.value))]

    def number(self, s: Setting) -> float:
        v = self.value
        if isinstance(v, _Huge):
            raise self.fail(f"must be in {s.range_text()}, got {v!r}")
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(f"must be a number, got {_kind(v)}")
        if isinstance(v, int) and v.bit_length() > 1024:  # float() would raise OverflowError
            raise self.fail(f"must be in {s.range_text()}, got {_show(v)}")
        v = float(v)
        if not math.isfinite(v):
            raise self.fail("must be finite")
        if not s.contains(v):
            raise self.fail(f"must be in {s.range_text()}, got {_show(v)}")
        return v

    def integer(self, s: Setting) -> int:
        v = self.value
        if isinstance(v, _Huge):
            raise self.fail(f"must be in {s.range_text()}, got {v!r}")
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(f"must be an integer, got {_kind(v)}")
        if not s.contains(v):
            raise self.fail(f"must be in {s.range_text()}, got {_show(v)}")
        if s.kind == "even" and v % 2:
            raise self.fail(f"must be even (pairs either side of the mean), got {v}")
        return v

    def read(self, s: Setting) -> Any:
        """The value of setting ``s`` here, checked."""
        v = self.value
        if v is None and s.nullable:
            return None
        if s.kind == "number":
            return self.number(s)
        if s.kind in ("integer", "even"):
            return self.integer(s)
        if s.kind == "flag":
            if not isinstance(v, bool):
                raise self.fail(f"must be true or false, got {_kind(v)}")
            return v
        if s.kind in ("text", "choice"):
            if not isinstance(v, str) or not v:
                raise self.fail(f"must be a non-empty string, got {_kind(v)}")
            if s.kind == "choice" and v not in s.choices:
                raise self.fail(f"must be one of {', '.join(s.choices)}, got {_show(v)}")
            if len(v) > TEXT_CHARS:
                raise self.fail(f"must be at most {TEXT_CHARS} characters, got {len(v)}")
            return v
        if s.kind == "names":
            if isinstance(self.value, tuple):
                self.value = list(self.value)
            return tuple(item.read(Setting("text", s.doc)) for item in self.items(0, s.max_items))
        if s.kind == "location":
            if not isinstance(v, str) or not v:
                raise self.fail(f"must be a non-empty string, got {_kind(v)}")
            if v in s.choices:
                return v
            if not v.startswith(LOCATION_STARTS):
                raise self.fail(f"must be {s.range_text()}, got {_show(v)}")
            if len(v) > LOCATION_CHARS:
                raise self.fail(f"must be at most {LOCATION_CHARS} characters, got {len(v)}")
            if any(c.isspace() or not c.isprintable() for c in v):
                raise self.fail(f"must have no spaces or control characters, got {_show(v)}")
            if v.startswith("http://"):
                try:
                    u = urlsplit(v)
                    u.port  # noqa: B018  (raises for a port out of range)
                except ValueError as exc:
                    raise self.fail(f"{exc}, got {_show(v)}") from None
                if not u.hostname:
                    raise self.fail(f"must name a host (http://HOST:PORT/PATH), got {_show(v)}")
                if not v.isascii():  # an HTTP request line is ASCII: refused here, not at the first read
                    if not u.netloc.isascii():
                        raise self.fail(f"its host must be ASCII (an IDN in its xn-- form), got {_show(v)}")
                    i, c = next((i, c) for i, c in enumerate(v) if not c.isascii())
                    raise self.fail(f"must be ASCII: percent-encode its path and query ({c!r}, character "
                                    f"{i + 1}, is {quote(c)}), got {_show(v)}")
            return v
        if s.kind == "vector":
            if isinstance(self.value, tuple):
                self.value = list(self.value)
            if s.size is not None and isinstance(self.value, list) and len(self.value) != s.size:
                raise self.fail(f"must have {s.size} numbers, got {len(self.value)}")
            return tuple(item.number(s) for item in self.items(s.size or 1, s.size or s.max_items))
        raise AssertionError(f"unknown kind {s.kind!r}")


def _build(cls, node: _Node):
    """An object of the declared dataclass ``cls`` from the mapping at ``node``."""
    decl = [f for f in fields(cls) if f.init and f.name not in ("source", "overrides")]
    node.mapping([f.name for f in decl])
    values = {}
    for f in decl:
        if f.name not in node.value:
            if f.default is MISSING and f.default_factory is MISSING:
                raise ConfigError(f"{node.path + '.' if node.path else ''}{f.name}: missing")
            continue  # the declared default
        child = node.child(f.name)
        if "section" in f.metadata:
            values[f.name] = _build(f.metadata["section"], child)
        elif "records" in f.metadata:
            items = child.items(f.metadata["min_items"], f.metadata["max_items"])
            values[f.name] = tuple(_build(f.metadata["records"], item) for item in items)
        else:
            values[f.name] = child.read(f.metadata["setting"])
    return cls(**values)


# --------------------------------------------------------------------------- checks across settings


def _unique_names(sc: Scenario) -> None:
    for key in ("targets", "goals", "obstacles"):
        seen: set[str] = set()
        for i, thing in enumerate(getattr(sc, key)):
            if thing.name in seen:
                raise ConfigError(f"{key}[{i}].name: duplicate name {thing.name!r}")
            seen.add(thing.name)


def _references(sc: Scenario) -> None:
    names = {g.name for g in sc.goals}
    for i, t in enumerate(sc.targets):
        if t.goal is not None and t.goal not in names:
            raise ConfigError(f"targets[{i}].goal: no goal named {t.goal!r} in goals")
        for j, g in enumerate(t.goals):
            if g not in names:
                raise ConfigError(f"targets[{i}].goals[{j}]: no goal named {g!r} in goals")
    for i, ob in enumerate(sc.obstacles):
        for j, size in enumerate(ob.size_m):
            if size <= 0:
                raise ConfigError(f"obstacles[{i}].size_m[{j}]: must be > 0 (an obstacle has a volume)")


def _area(sc: Scenario) -> None:
    if not all(h > lo for lo, h in zip(sc.area.min_m, sc.area.max_m)):
        raise ConfigError("area.max_m: must be greater than area.min_m in every axis")


def _settings(sc: Scenario) -> None:
    g, pl = sc.guidance, sc.planning
    if g.terminal_weight == 0 and g.stage_weight == 0:
        raise ConfigError("guidance.stage_weight: stage_weight and terminal_weight cannot both be 0")
    if pl.planner == "lookahead" and pl.lookahead_steps > g.horizon:
        raise ConfigError(f"planning.lookahead_steps: must be <= guidance.horizon ({g.horizon}) with the "
                          f"lookahead planner, got {pl.lookahead_steps}: it follows the guidance plans")
    lo, altitude_m, hi = (value_of(sc, k) for k in ("app.fence_min_m", "uav.altitude_m", "app.fence_max_m"))
    if not lo <= altitude_m <= hi:
        raise ConfigError(f"uav.altitude_m: must be within the geofence band app.fence_min_m.."
                          f"app.fence_max_m = {lo:g}..{hi:g} m, got {altitude_m:g}")


def _kraken(sc: Scenario) -> None:
    """Each VFO a target's, one VFO per target, their frequencies told apart; the adaptive
    clutter's bounds in order."""
    k = sc.kraken
    names = {t.name for t in sc.targets}
    for i, v in enumerate(k.vfos):
        if v.target not in names:
            raise ConfigError(f"kraken.vfos[{i}].target: no target named {v.target!r} in targets")
        for w in k.vfos[:i]:
            if w.target == v.target:
                raise ConfigError(f"kraken.vfos[{i}].target: two VFOs with the same target {v.target!r}")
            if abs(w.freq_hz - v.freq_hz) <= 2 * k.freq_tol_hz:
                raise ConfigError(f"kraken.vfos[{i}].freq_hz: two VFOs with the same frequency (within "
                                  f"2 x kraken.freq_tol_hz of {w.freq_hz:g} Hz)")
    if k.clutter_min is not None and k.clutter_max < k.clutter_min:
        raise ConfigError(f"kraken.clutter_max: must be >= kraken.clutter_min ({k.clutter_min:g}), "
                          f"got {k.clutter_max:g}")


def _geometry(sc: Scenario) -> None:
    """Things inside the area, not inside obstacles."""
    # imported here: the core imports nothing from this module, keep it that way
    from onboard.core.obstacles import Obstacles

    obstacles = Obstacles.from_boxes(sc.obstacles)
    ground_obstacles = obstacles.inflate(sc.guidance.obstacle_margin_m)

    def inside_area(path: str, p) -> None:
        if not sc.area.contains(np.asarray(p)):
            shown = tuple(float(v) for v in p)
            raise ConfigError(f"{path}: {shown} is outside the area {sc.area.min_m}..{sc.area.max_m}")

    for key, points in (("targets", [(i, t.position_m, "position_m") for i, t in enumerate(sc.targets)]),
                        ("goals", [(i, g.center_m, "center_m") for i, g in enumerate(sc.goals)])):
        for i, p, name in points:
            inside_area(f"{key}[{i}].{name}", p)
            hit = ground_obstacles.containing(np.asarray(p))
            if hit is not None:
                raise ConfigError(f"{key}[{i}].{name}: inside obstacle {sc.obstacles[hit].name!r} "
                                  f"(inflated by guidance.obstacle_margin_m)")
    start = np.array(sc.uav.start_m)
    inside_area("uav.start_m", start)
    if not sc.area.min_m[2] <= sc.uav.altitude_m <= sc.area.max_m[2]:
        raise ConfigError(f"uav.altitude_m: {sc.uav.altitude_m} is outside the area's altitude range")
    hit = obstacles.inflate(sc.uav.obstacle_margin_m).containing(
        np.array([start[0], start[1], sc.uav.altitude_m]))
    if hit is not None:
        raise ConfigError(f"uav.start_m: at altitude uav.altitude_m it is inside obstacle "
                          f"{sc.obstacles[hit].name!r} (inflated by uav.obstacle_margin_m)")


CHECKS = (_unique_names, _references, _area, _settings, _kraken, _geometry)  # in this order, after each setting's own


# --------------------------------------------------------------------------- entry points


def parse_scenario(data: Any, source: str = "<memory>") -> Scenario:
    """Validate an already-read tree (a dict, as the YAML file holds it) into a Scenario."""
    sc = replace(_build(Scenario, _Node(data, "")), source=source)
    for check in CHECKS:
        check(sc)
    return sc


def scenario_tree(sc: Scenario) -> dict:
    """The scenario as a file holds it (every setting, defaults included): read back by
    ``parse_scenario`` it is the same scenario."""
    def tree(obj):
        out = {}
        for f in fields(obj):
            if f.name in ("source", "overrides"):
                continue
            v = getattr(obj, f.name)
            if "section" in f.metadata:
                out[f.name] = tree(v)
            elif "records" in f.metadata:
                out[f.name] = [tree(item) for item in v]
            else:
                out[f.name] = list(v) if isinstance(v, tuple) else v
        return out
    return tree(sc)


def _apply(tree: Any, changes: Mapping[str, Any]) -> Any:
    """``tree`` (changed in place) with each dotted KEY set to VALUE."""
    for key, value in changes.items():
        parts = str(key).split(".")
        node = tree
        for i, part in enumerate(parts[:-1]):
            if not isinstance(node, dict):
                raise ConfigError(f"{_cut(key)}: {'.'.join(parts[:i]) or '<root>'} is not a mapping")
            node = node.setdefault(part, {})  # a key that is no section: refused by the parse, named
        if not isinstance(node, dict):
            raise ConfigError(f"{_cut(key)}: {'.'.join(parts[:-1]) or '<root>'} is not a mapping")
        node[parts[-1]] = list(value) if isinstance(value, tuple) else value
    return tree


def override(sc: Scenario, changes: Mapping[str, Any], *, beneath: bool = False) -> Scenario:
    """The scenario with the settings ``changes`` ({dotted key: value as a file states it}),
    checked as a file is (each setting's range, then ``CHECKS``): the one way to change a
    scenario. ``beneath``: the scenario's own earlier changes win over these (a flight policy
    under a user's ``--set``). ConfigError names the key path."""
    merged = {**dict(changes), **dict(sc.overrides)} if beneath else dict(changes)
    if not merged:
        return sc
    new = parse_scenario(_apply(scenario_tree(sc), merged), sc.source)
    return replace(new, overrides=tuple({**dict(sc.overrides), **merged}.items()))


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings (``--set``) as ``override`` changes; VALUE is read as YAML
    (``true``, ``0.5``, ``[1, 2]``). ConfigError names an item without ``=``."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {_cut(repr(item))}: expected KEY=VALUE, e.g. tracking.plan_steering=true")
        try:  # a tag (!!python/...) is not plain YAML: the safe loader constructs none
            out[key] = read_yaml(value, _cut(key), invalid="VALUE is not plain YAML")
        except ConfigError as exc:
            raise ConfigError(f"--set {exc}") from None
    return out


def load_scenario(path_or_name: str | Path = "paper", overrides: Mapping[str, Any] | None = None) -> Scenario:
    """A scenario from a YAML file, or a built-in one by name (``paper``), with ``overrides``
    ({dotted key: value}, e.g. ``{"tracking.control_mix": 0.0}``) set before it is checked."""
    text, source = _read(path_or_name)
    try:
        tree = read_yaml(text)
        sc = parse_scenario(_apply(tree, dict(overrides or {})) if overrides else tree, source)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    return replace(sc, overrides=tuple(dict(overrides or {}).items()))


def _read(path_or_name: str | Path) -> tuple[str, str]:
    if isinstance(path_or_name, str) and path_or_name in BUILTIN_SCENARIOS:
        res = resources.files("onboard") / "data" / f"{path_or_name}.yaml"
        return res.read_text(encoding="utf-8"), f"<builtin {path_or_name}>"
    path = Path(path_or_name)
    try:
        raw = read_regular(path, MAX_FILE_BYTES)
    except FileRefused as exc:
        raise ConfigError(f"{exc}; not a scenario file") from None
    try:
        return raw.decode("utf-8"), str(path)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from None
