"""Scenario configuration: YAML in, typed, validated, immutable objects out.

Every error names the key path and the reason, e.g. ``obstacles[2].size_m: must be > 0``.
Degrees exist only in the file; the objects hold radians (``sigma_rad``, ``yaw_rad``).
Only ``yaml.safe_load`` is used: nothing in a config file is ever executed.

Hostile files are refused with one ConfigError, never a traceback or a hang: only a regular
file of at most ``MAX_FILE_BYTES`` is read (checked on the open descriptor before reading:
/dev/zero or a FIFO are refused, not read; onboard/files.py), nesting too deep for the YAML
reader is an error, an integer too large for a float is out of range (``float()`` would raise
OverflowError), values are shown cut to ``SHOW_CHARS`` in messages, and the lists that size the
filters are bounded (``MAX_TARGETS``, ``MAX_PARTICLES_TOTAL``, ...).
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import yaml

from onboard.files import FileRefused, read_regular

BUILTIN_SCENARIOS = ("paper",)
MAX_FILE_BYTES = 1_000_000
SHOW_CHARS = 40  # of a bad value in a message
MAX_TARGETS = 64
MAX_OBSTACLES = 256
MAX_GOALS = 64
MAX_RANGES = 16
MAX_PARTICLES_TOTAL = 2_000_000  # targets x particles per target: ~100 MB of particles


class ConfigError(ValueError):
    """A configuration value is missing or invalid; the message starts with its key path."""


# --------------------------------------------------------------------------- typed objects


@dataclass(frozen=True)
class Area:
    min_m: tuple[float, float, float]
    max_m: tuple[float, float, float]

    def contains(self, points: np.ndarray) -> np.ndarray:
        """True where each point (..., 3) lies inside the closed box."""
        p = np.asarray(points, dtype=float)
        return np.all((p >= np.asarray(self.min_m)) & (p <= np.asarray(self.max_m)), axis=-1)


@dataclass(frozen=True)
class Dynamics:
    dt_s: float
    friction: float
    mass_kg: float
    process_noise_diag: tuple[float, ...]


@dataclass(frozen=True)
class Target:
    name: str
    position_m: tuple[float, float, float]
    velocity_mps: tuple[float, float, float]
    goal: str

    @property
    def mean(self) -> np.ndarray:
        return np.array(self.position_m + self.velocity_mps, dtype=float)


@dataclass(frozen=True)
class Box:
    """A cuboid given by centre, extents (before yaw) and yaw about +z (radians, CCW from +x)."""

    name: str
    center_m: tuple[float, float, float]
    size_m: tuple[float, float, float]
    yaw_rad: float = 0.0


@dataclass(frozen=True)
class Guidance:
    horizon: int
    u_max_n: float
    speed_max_mps: float
    speed_polygon_sides: int
    terminal_weight: float
    stage_weight: float
    smooth_weight: float
    obstacle_margin_m: float
    max_qp_solves: int
    max_solve_time_s: float | None = None  # per target and tick; None: no limit (deterministic)


@dataclass(frozen=True)
class Sensor:
    sigma_rad: float
    p_detect: float
    clutter_rate: float


@dataclass(frozen=True)
class Uav:
    start_m: tuple[float, float, float]
    altitude_m: float
    step_m: float
    n_radial: int
    n_heading: int
    obstacle_margin_m: float


@dataclass(frozen=True)
class Tracking:
    particles: int
    resample_ess_fraction: float
    control_mix: float = 0.1  # fraction of particles predicted with a random control (docs/TRACKING.md)
    regularise_bandwidth: float = 0.0  # h of the regularised resampling (0: plain resampling)
    plan_steering: bool = False  # particles steer by the law of the nearest reference plan (docs/TRACKING.md)
    plan_references: int = 2  # reference plans besides the mean's (even: pairs either side of it)
    plan_spread_sigma: float = 1.5  # the others at +-this many sigma along the cloud's major axis
    plan_steered_share: float = 0.7  # share of the particles a reference plan steers (the rest: its control)
    plan_trust_sigma: float = 2.0  # only particles this close (Mahalanobis) to a reference are steered
    plan_max_qp_solves: int = 80  # QP budget of each reference plan (the mean's: guidance.max_qp_solves)
    plan_sides: bool = False  # a side of each obstacle per particle; the references per side present
    plan_side_temperature: float = 0.05  # relative P1 cost scale of a side's share at its birth


@dataclass(frozen=True)
class Lookahead:
    """The lookahead planner's knobs (onboard.core.planning.LookaheadParams; docs/PLANNING.md)."""

    ranges_m: tuple[float, ...] = (30.0, 80.0, 160.0, 320.0)
    n_headings: int = 16
    loiter_radius_m: float = 40.0
    corner_clearance_m: float = 3.0
    spacing_m: float = 2.0


@dataclass(frozen=True)
class Planning:
    objective: str
    planner: str = "greedy"  # greedy (the paper's one-step rule) | lookahead
    lookahead_steps: int = 10  # ticks scored by the lookahead planner
    motion: str = "jump"  # jump (the paper: anywhere on the polar grid each tick) | vehicle
    speed_max_mps: float = 10.0  # vehicle motion: ArduCopter WPNAV_SPEED default
    accel_max_mps2: float = 2.5  # vehicle motion: ArduCopter WPNAV_ACCEL default
    lookahead: Lookahead = Lookahead()


@dataclass(frozen=True)
class Mission:
    duration_s: float


@dataclass(frozen=True)
class Origin:
    lat_deg: float
    lon_deg: float
    alt_m: float


@dataclass(frozen=True)
class KrakenVfo:
    target: str  # a target's name: the VFO's bearings are that target's channel
    freq_hz: float  # the VFO's frequency, as KrakenSDR writes it in each line


@dataclass(frozen=True)
class Kraken:
    """KrakenSDR's DoA output as the DF (``pmon run --kraken``; onboard/app/kraken.py,
    docs/KRAKENSDR.md has each setting's reason). One section, every setting declared here
    with its default; ``_kraken`` reads it."""

    vfos: tuple[KrakenVfo, ...]
    url: str = "http://127.0.0.1:8081/DOA_value.html"  # its "Kraken App" CSV: http:// or a file path
    status_url: str = "auto"  # its status.json (ADC overdrive, DAQ sync): auto = beside url; "" = none
    freq_tol_hz: float = 2000.0  # a line within this of a VFO's frequency is that VFO's
    mount_offset_rad: float = 0.0  # KrakenSDR's 0 (antenna 0), clockwise from the vehicle's nose
    convention: str = "auto"  # the main DoA's: auto (read off the spectrum) | unit_circle | compass
    measurements: str = "peaks"  # peaks (the spectrum's, the set) | main (the main DoA alone)
    peak_floor_db: float = 6.0  # peaks within this of the highest (docs/KRAKENSDR.md: 6 measured best)
    peak_prominence_db: float = 3.0  # ... standing this far above their valleys
    max_peaks: int = 8
    min_confidence: float = 0.0  # gate: a line below this confidence (dB) is an empty set
    min_power_db: float = -100.0  # gate: ... below this power (KrakenSDR floors it at -100)
    reject_overdrive: bool = True  # gate: frames its status.json flags (ADC overdrive, DAQ not ok)
    clutter: str = "fixed"  # fixed (sensor.clutter_rate: measured best) | adaptive (the rate the peaks show)
    # adaptive rate's bounds (per scan); clutter_min None: the filter's own rate (sensor.clutter_rate,
    # PMON_CLUTTER): the peaks raise it where they show more clutter, never lower it
    clutter_min: float | None = None
    clutter_max: float = 10.0
    clutter_window: int = 20  # scans per channel the adaptive rate is averaged over
    time_source: str = "autopilot"  # its Unix stamps to autopilot time: autopilot (SYSTEM_TIME) | host
    poll_s: float = 0.05  # wall s between reads of url


@dataclass(frozen=True)
class Scenario:
    name: str
    origin: Origin
    area: Area
    dynamics: Dynamics
    initial_cov_diag: tuple[float, ...]
    targets: tuple[Target, ...]
    goals: tuple[Box, ...]
    obstacles: tuple[Box, ...]
    guidance: Guidance
    sensor: Sensor
    uav: Uav
    tracking: Tracking
    planning: Planning
    mission: Mission
    kraken: Kraken | None = None  # KrakenSDR as the DF (optional section)
    source: str = field(default="<memory>", compare=False)
    # the YAML tree as read (before ``overrides``) and the overrides applied, for ``with_overrides``
    tree: Any = field(default=None, compare=False, repr=False)
    overrides: tuple[tuple[str, Any], ...] = field(default=(), compare=False)

    def goal_of(self, target: Target) -> Box:
        return next(g for g in self.goals if g.name == target.goal)

    @property
    def initial_cov(self) -> np.ndarray:
        return np.diag(self.initial_cov_diag)


# --------------------------------------------------------------------------- reading helpers


class _Node:
    """A value in the YAML tree together with its key path, for error messages."""

    def __init__(self, value: Any, path: str):
        self.value = value
        self.path = path

    def fail(self, reason: str) -> ConfigError:
        return ConfigError(f"{self.path or '<root>'}: {reason}")

    def _child_path(self, key: str | int) -> str:
        if isinstance(key, int):
            return f"{self.path}[{key}]"
        return f"{self.path}.{key}" if self.path else key

    def mapping(self, keys: set[str]) -> "_Node":
        if not isinstance(self.value, dict):
            raise self.fail(f"must be a mapping, got {_kind(self.value)}")
        unknown = sorted(str(k) for k in self.value if k not in keys)
        if unknown:
            raise self.fail(f"unknown key {unknown[0]!r} (expected one of: {', '.join(sorted(keys))})")
        return self

    def get(self, key: str, default: Any = ...) -> "_Node":
        if key not in self.value:
            if default is ...:
                raise ConfigError(f"{self._child_path(key)}: missing")
            return _Node(default, self._child_path(key))
        return _Node(self.value[key], self._child_path(key))

    def items(self, min_len: int = 0, max_len: int | None = None) -> list["_Node"]:
        if not isinstance(self.value, list):
            raise self.fail(f"must be a list, got {_kind(self.value)}")
        if len(self.value) < min_len:
            raise self.fail(f"must have at least {min_len} item(s)")
        if max_len is not None and len(self.value) > max_len:
            raise self.fail(f"must have at most {max_len} items, got {len(self.value)}")
        return [_Node(v, self._child_path(i)) for i, v in enumerate(self.value)]

    def number(self, check: Callable[[float], bool] | None = None, why: str = "") -> float:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(f"must be a number, got {_kind(v)}")
        if isinstance(v, int) and abs(v) > sys.float_info.max:  # float() would raise OverflowError
            raise self.fail(f"must be finite, got {_show(v)}")
        v = float(v)
        if not math.isfinite(v):
            raise self.fail("must be finite")
        if check is not None and not check(v):
            raise self.fail(why)
        return v

    def integer(self, lo: int, hi: int) -> int:
        v = self.value
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(f"must be an integer, got {_kind(v)}")
        if not lo <= v <= hi:
            raise self.fail(f"must be in [{lo}, {hi}], got {_show(v)}")
        return v

    def vector(self, n: int, check: Callable[[float], bool] | None = None, why: str = "") -> tuple[float, ...]:
        items = self.items()
        if len(items) != n:
            raise self.fail(f"must have {n} numbers, got {len(items)}")
        return tuple(item.number(check, why) for item in items)

    def boolean(self) -> bool:
        if not isinstance(self.value, bool):
            raise self.fail(f"must be true or false, got {_kind(self.value)}")
        return self.value

    def text(self) -> str:
        if not isinstance(self.value, str) or not self.value:
            raise self.fail(f"must be a non-empty string, got {_kind(self.value)}")
        return self.value

    def choice(self, options: tuple[str, ...]) -> str:
        v = self.text()
        if v not in options:
            raise self.fail(f"must be one of {', '.join(options)}, got {_show(v)}")
        return v


def _even(node: "_Node", lo: int, hi: int) -> int:
    """An even integer in [lo, hi] (reference plans come in pairs, one either side)."""
    v = node.integer(lo, hi)
    if v % 2:
        raise node.fail(f"must be even (pairs either side of the mean), got {v}")
    return v


def _kind(v: Any) -> str:
    return "nothing" if v is None else type(v).__name__


def _show(v: Any) -> str:
    """A value for a message, cut to SHOW_CHARS (a 400-digit integer must not fill the line)."""
    if isinstance(v, int) and not isinstance(v, bool) and abs(v) >= 10 ** SHOW_CHARS:
        digits = len(str(abs(v)))
        return f"{'-' if v < 0 else ''}{str(abs(v))[:6]}... ({digits} digits)"
    text = repr(v)
    return text if len(text) <= SHOW_CHARS else text[:SHOW_CHARS - 3] + "..."


def _positive(v: float) -> bool:
    return v > 0


def _nonneg(v: float) -> bool:
    return v >= 0


# --------------------------------------------------------------------------- sections


def _box(n: _Node, flat_ok: bool) -> Box:
    n.mapping({"name", "center_m", "size_m", "yaw_deg"})
    size_check = _nonneg if flat_ok else _positive
    size = n.get("size_m").vector(3, size_check, "must be >= 0" if flat_ok else "must be > 0")
    yaw = n.get("yaw_deg", 0.0).number(lambda v: -360 <= v <= 360, "must be in [-360, 360] degrees")
    return Box(
        name=n.get("name").text(),
        center_m=n.get("center_m").vector(3),
        size_m=size,
        yaw_rad=math.radians(yaw),
    )


def _parse(root: _Node, source: str) -> Scenario:
    root.mapping({
        "name", "origin", "area", "dynamics", "initial_cov_diag", "targets", "goals", "obstacles",
        "guidance", "sensor", "uav", "tracking", "planning", "mission", "kraken",
    })

    o = root.get("origin").mapping({"lat_deg", "lon_deg", "alt_m"})
    origin = Origin(
        lat_deg=o.get("lat_deg").number(lambda v: -90 <= v <= 90, "must be in [-90, 90]"),
        lon_deg=o.get("lon_deg").number(lambda v: -180 <= v <= 180, "must be in [-180, 180]"),
        alt_m=o.get("alt_m").number(lambda v: -500 <= v <= 9000, "must be in [-500, 9000] m"),
    )

    a = root.get("area").mapping({"min_m", "max_m"})
    lo, hi = a.get("min_m").vector(3), a.get("max_m").vector(3)
    if not all(h > l for l, h in zip(lo, hi)):
        raise a.get("max_m").fail("must be greater than area.min_m in every axis")
    area = Area(lo, hi)

    d = root.get("dynamics").mapping({"dt_s", "friction", "mass_kg", "process_noise_diag"})
    dynamics = Dynamics(
        dt_s=d.get("dt_s").number(_positive, "must be > 0"),
        friction=d.get("friction").number(lambda v: 0 <= v <= 1, "must be in [0, 1]"),
        mass_kg=d.get("mass_kg").number(_positive, "must be > 0"),
        process_noise_diag=d.get("process_noise_diag").vector(6, _nonneg, "must be >= 0"),
    )
    initial_cov_diag = root.get("initial_cov_diag").vector(6, _nonneg, "must be >= 0")

    goals = tuple(_box(g, flat_ok=True) for g in root.get("goals").items(min_len=1, max_len=MAX_GOALS))
    _unique_names(root.get("goals"), goals)
    obstacles = tuple(_box(ob, flat_ok=False) for ob in root.get("obstacles", []).items(max_len=MAX_OBSTACLES))
    _unique_names(root.get("obstacles", []), obstacles)

    targets = []
    for t in root.get("targets").items(min_len=1, max_len=MAX_TARGETS):
        t.mapping({"name", "position_m", "velocity_mps", "goal"})
        goal = t.get("goal").text()
        if goal not in {g.name for g in goals}:
            raise t.get("goal").fail(f"no goal named {goal!r} in goals")
        targets.append(Target(
            name=t.get("name").text(),
            position_m=t.get("position_m").vector(3),
            velocity_mps=t.get("velocity_mps", [0.0, 0.0, 0.0]).vector(3),
            goal=goal,
        ))
    _unique_names(root.get("targets"), targets)

    g = root.get("guidance").mapping({
        "horizon", "u_max_n", "speed_max_mps", "speed_polygon_sides", "terminal_weight",
        "stage_weight", "smooth_weight", "obstacle_margin_m", "max_qp_solves", "max_solve_time_s",
    })
    guidance = Guidance(
        horizon=g.get("horizon").integer(2, 500),
        u_max_n=g.get("u_max_n").number(_positive, "must be > 0"),
        speed_max_mps=g.get("speed_max_mps").number(_positive, "must be > 0"),
        speed_polygon_sides=g.get("speed_polygon_sides", 16).integer(4, 64),
        terminal_weight=g.get("terminal_weight").number(_nonneg, "must be >= 0"),
        stage_weight=g.get("stage_weight").number(_nonneg, "must be >= 0"),
        smooth_weight=g.get("smooth_weight").number(_nonneg, "must be >= 0"),
        obstacle_margin_m=g.get("obstacle_margin_m").number(_nonneg, "must be >= 0"),
        max_qp_solves=g.get("max_qp_solves", 80).integer(1, 1000),
        max_solve_time_s=(None if g.get("max_solve_time_s", None).value is None
                          else g.get("max_solve_time_s").number(_positive, "must be > 0")),
    )
    if guidance.terminal_weight == 0 and guidance.stage_weight == 0:
        raise g.get("stage_weight").fail("stage_weight and terminal_weight cannot both be 0")

    s = root.get("sensor").mapping({"sigma_deg", "p_detect", "clutter_rate"})
    sensor = Sensor(
        sigma_rad=math.radians(s.get("sigma_deg").number(lambda v: 0 < v <= 90, "must be in (0, 90] degrees")),
        p_detect=s.get("p_detect").number(lambda v: 0 <= v <= 1, "must be in [0, 1]"),
        clutter_rate=s.get("clutter_rate").number(lambda v: 0 <= v <= 1000, "must be in [0, 1000]"),
    )

    u = root.get("uav").mapping({"start_m", "altitude_m", "step_m", "n_radial", "n_heading", "obstacle_margin_m"})
    uav = Uav(
        start_m=u.get("start_m").vector(3),
        altitude_m=u.get("altitude_m").number(_positive, "must be > 0"),
        step_m=u.get("step_m").number(_positive, "must be > 0"),
        n_radial=u.get("n_radial").integer(0, 100),
        n_heading=u.get("n_heading").integer(1, 360),
        obstacle_margin_m=u.get("obstacle_margin_m", 10.0).number(_nonneg, "must be >= 0"),
    )

    tr = root.get("tracking").mapping({"particles", "resample_ess_fraction", "control_mix",
                                         "regularise_bandwidth", "plan_steering",
                                         "plan_references", "plan_spread_sigma", "plan_steered_share",
                                         "plan_trust_sigma", "plan_max_qp_solves", "plan_sides",
                                         "plan_side_temperature"})
    tracking = Tracking(
        particles=tr.get("particles").integer(10, 1_000_000),
        resample_ess_fraction=tr.get("resample_ess_fraction", 0.5).number(
            lambda v: 0 <= v <= 1, "must be in [0, 1]"),
        control_mix=tr.get("control_mix", 0.1).number(lambda v: 0 <= v < 1, "must be in [0, 1)"),
        regularise_bandwidth=tr.get("regularise_bandwidth", 0.0).number(lambda v: 0 <= v <= 1, "must be in [0, 1]"),
        plan_steering=tr.get("plan_steering", False).boolean(),
        plan_references=_even(tr.get("plan_references", 2), 0, 8),
        plan_spread_sigma=tr.get("plan_spread_sigma", 1.5).number(lambda v: 0 < v <= 5, "must be in (0, 5]"),
        plan_steered_share=tr.get("plan_steered_share", 0.7).number(lambda v: 0 <= v <= 1, "must be in [0, 1]"),
        plan_trust_sigma=tr.get("plan_trust_sigma", 2.0).number(_positive, "must be > 0"),
        plan_max_qp_solves=tr.get("plan_max_qp_solves", 80).integer(1, 1000),
        plan_sides=tr.get("plan_sides", False).boolean(),
        plan_side_temperature=tr.get("plan_side_temperature", 0.05).number(_positive, "must be > 0"),
    )
    pl = root.get("planning").mapping({"objective", "planner", "lookahead_steps", "motion",
                                       "speed_max_mps", "accel_max_mps2", "lookahead"})
    la = pl.get("lookahead", {}).mapping({"ranges_m", "n_headings", "loiter_radius_m",
                                          "corner_clearance_m", "spacing_m"})
    d_la = Lookahead()
    ranges = la.get("ranges_m", list(d_la.ranges_m))
    lookahead = Lookahead(
        ranges_m=ranges.vector(len(ranges.items(min_len=1, max_len=MAX_RANGES)), _positive, "must be > 0"),
        n_headings=la.get("n_headings", d_la.n_headings).integer(1, 360),
        loiter_radius_m=la.get("loiter_radius_m", d_la.loiter_radius_m).number(_positive, "must be > 0"),
        corner_clearance_m=la.get("corner_clearance_m", d_la.corner_clearance_m).number(_nonneg, "must be >= 0"),
        spacing_m=la.get("spacing_m", d_la.spacing_m).number(lambda v: 0.1 <= v <= 50, "must be in [0.1, 50]"),
    )
    planning = Planning(
        objective=pl.get("objective", "trace").choice(("trace", "position_trace")),
        planner=pl.get("planner", "greedy").choice(("greedy", "lookahead")),
        lookahead_steps=pl.get("lookahead_steps", 10).integer(1, 200),
        motion=pl.get("motion", "jump").choice(("jump", "vehicle")),
        speed_max_mps=pl.get("speed_max_mps", 10.0).number(_positive, "must be > 0"),
        accel_max_mps2=pl.get("accel_max_mps2", 2.5).number(_positive, "must be > 0"),
        lookahead=lookahead,
    )
    if len(targets) * tracking.particles > MAX_PARTICLES_TOTAL:
        raise tr.get("particles").fail(f"{len(targets)} targets x {tracking.particles} particles is more than "
                                       f"{MAX_PARTICLES_TOTAL} in all")
    if tracking.plan_sides and not tracking.plan_steering:
        raise ConfigError("tracking.plan_sides: needs tracking.plan_steering: true (the sides choose "
                          "among its reference plans)")
    if planning.planner == "lookahead" and planning.lookahead_steps > guidance.horizon:
        raise ConfigError("planning.lookahead_steps: must be <= guidance.horizon "
                          f"({guidance.horizon}): the lookahead follows the guidance plans")
    mission = Mission(
        duration_s=root.get("mission").mapping({"duration_s"}).get("duration_s").number(
            _positive, "must be > 0"),
    )

    scenario = Scenario(
        name=root.get("name").text(), origin=origin, area=area, dynamics=dynamics,
        initial_cov_diag=initial_cov_diag, targets=tuple(targets), goals=goals,
        obstacles=obstacles, guidance=guidance, sensor=sensor, uav=uav, tracking=tracking,
        planning=planning, mission=mission, source=source,
        kraken=_kraken(root.get("kraken"), targets) if "kraken" in root.value else None,
    )
    _check_geometry(root, scenario)
    return scenario


def _kraken(k: _Node, targets) -> Kraken:
    d = Kraken(vfos=())
    keys = {f for f in Kraken.__dataclass_fields__ if f != "mount_offset_rad"} | {"mount_offset_deg"}
    k.mapping(keys)
    names = {t.name for t in targets}
    vfos = []
    for v in k.get("vfos").items(min_len=1, max_len=MAX_TARGETS):
        v.mapping({"target", "freq_hz"})
        name = v.get("target").text()
        if name not in names:
            raise v.get("target").fail(f"no target named {name!r} in targets")
        vfos.append(KrakenVfo(name, v.get("freq_hz").number(lambda x: 1e6 <= x <= 1e11, "must be in [1e6, 1e11] Hz")))
    tol = k.get("freq_tol_hz", d.freq_tol_hz).number(lambda x: 0 < x <= 1e6, "must be in (0, 1e6] Hz")
    for i, a in enumerate(vfos):
        for b in vfos[i + 1:]:
            if a.target == b.target or abs(a.freq_hz - b.freq_hz) <= 2 * tol:
                what = "target" if a.target == b.target else f"frequency (within 2 x freq_tol_hz of {a.freq_hz:g})"
                raise k.get("vfos").fail(f"two VFOs with the same {what}")

    def url(key: str, default: str, extra: tuple[str, ...] = ()) -> str:
        node = k.get(key, default)
        if node.value == "" and "" in extra:
            return ""
        v = node.text()
        if len(v) > 512 or not (v.startswith(("http://", "file://", "/")) or v in extra):
            raise node.fail("must be http://HOST:PORT/PATH, file:///PATH or an absolute path"
                            + (f" (or {', '.join(repr(e) for e in extra)})" if extra else ""))
        return v

    lo = k.get("clutter_min", None)
    lo = None if lo.value is None else lo.number(lambda x: 0 <= x <= 1000, "must be in [0, 1000] (or null)")
    hi = k.get("clutter_max", d.clutter_max).number(lambda x: (lo or 0.0) <= x <= 1000,
                                                   f"must be in [clutter_min={lo or 0.0:g}, 1000]")
    return Kraken(
        vfos=tuple(vfos),
        url=url("url", d.url),
        status_url=url("status_url", d.status_url, ("auto", "")),
        freq_tol_hz=tol,
        mount_offset_rad=math.radians(k.get("mount_offset_deg", 0.0).number(lambda x: -360 <= x <= 360,
                                                                             "must be in [-360, 360] degrees")),
        convention=k.get("convention", d.convention).choice(("auto", "unit_circle", "compass")),
        measurements=k.get("measurements", d.measurements).choice(("peaks", "main")),
        peak_floor_db=k.get("peak_floor_db", d.peak_floor_db).number(lambda x: 0 < x <= 100, "must be in (0, 100] dB"),
        peak_prominence_db=k.get("peak_prominence_db", d.peak_prominence_db).number(
            lambda x: 0 <= x <= 100, "must be in [0, 100] dB"),
        max_peaks=k.get("max_peaks", d.max_peaks).integer(1, 64),
        min_confidence=k.get("min_confidence", d.min_confidence).number(lambda x: 0 <= x <= 1000, "must be in [0, 1000]"),
        min_power_db=k.get("min_power_db", d.min_power_db).number(lambda x: -300 <= x <= 100, "must be in [-300, 100] dB"),
        reject_overdrive=k.get("reject_overdrive", d.reject_overdrive).boolean(),
        clutter=k.get("clutter", d.clutter).choice(("adaptive", "fixed")),
        clutter_min=lo,
        clutter_max=hi,
        clutter_window=k.get("clutter_window", d.clutter_window).integer(1, 10_000),
        time_source=k.get("time_source", d.time_source).choice(("autopilot", "host")),
        poll_s=k.get("poll_s", d.poll_s).number(lambda x: 0.005 <= x <= 10, "must be in [0.005, 10] s"),
    )


def _unique_names(node: _Node, things) -> None:
    seen: set[str] = set()
    for i, thing in enumerate(things):
        if thing.name in seen:
            raise ConfigError(f"{node.path}[{i}].name: duplicate name {thing.name!r}")
        seen.add(thing.name)


def _check_geometry(root: _Node, sc: Scenario) -> None:
    """Cross-field checks: things inside the area, not inside obstacles."""
    # imported here: the core imports nothing from this module, keep it that way
    from onboard.core.obstacles import Obstacles

    obstacles = Obstacles.from_boxes(sc.obstacles)
    ground_obstacles = obstacles.inflate(sc.guidance.obstacle_margin_m)

    def inside_area(path: str, p) -> None:
        if not sc.area.contains(np.asarray(p)):
            shown = tuple(float(v) for v in p)
            raise ConfigError(f"{path}: {shown} is outside the area {sc.area.min_m}..{sc.area.max_m}")

    for i, t in enumerate(sc.targets):
        inside_area(f"targets[{i}].position_m", t.position_m)
        hit = ground_obstacles.containing(np.asarray(t.position_m))
        if hit is not None:
            raise ConfigError(f"targets[{i}].position_m: inside obstacle {sc.obstacles[hit].name!r} "
                              f"(inflated by guidance.obstacle_margin_m)")
    for i, g in enumerate(sc.goals):
        inside_area(f"goals[{i}].center_m", g.center_m)
        hit = ground_obstacles.containing(np.asarray(g.center_m))
        if hit is not None:
            raise ConfigError(f"goals[{i}].center_m: inside obstacle {sc.obstacles[hit].name!r} "
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


# --------------------------------------------------------------------------- entry points


def parse_scenario(data: Any, source: str = "<memory>") -> Scenario:
    """Validate an already-parsed YAML tree (a dict) into a Scenario."""
    return _parse(_Node(data, ""), source)


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings (the benches' ``--set``) as ``load_scenario`` overrides; VALUE is read
    as YAML (``true``, ``0.5``, ``[1, 2]``). ConfigError names an item without ``=``."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {_show(item)}: expected KEY=VALUE, e.g. tracking.plan_steering=true")
        try:
            out[key] = yaml.safe_load(value)
        except yaml.YAMLError as exc:  # a tag (!!python/...) is one: safe_load constructs none
            raise ConfigError(f"--set {_show(item)}: VALUE is not plain YAML: "
                              f"{str(getattr(exc, 'problem', None) or exc).splitlines()[0]}") from None
        except RecursionError:
            raise ConfigError(f"--set {_show(key)}=...: VALUE nested too deeply") from None
    return out


def load_scenario(path_or_name: str | Path = "paper", overrides: dict[str, Any] | None = None) -> Scenario:
    """Load a scenario from a YAML file, or a built-in one by name (``paper``).

    overrides: dotted keys set before validation, e.g. ``{"tracking.control_mix": 0.0}``; a key
    whose parent is missing is an error naming it."""
    text, source = _read(path_or_name)
    try:
        tree = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = str(getattr(exc, "problem", None) or exc).splitlines()[0]
        raise ConfigError(f"{source}: not valid YAML{where}: {problem}") from None
    except RecursionError:
        raise ConfigError(f"{source}: nested too deeply for a scenario") from None
    return _with_tree(tree, source, dict(overrides or {}))


def with_overrides(sc: Scenario, overrides: dict[str, Any]) -> Scenario:
    """The scenario re-read from its file with ``overrides`` under the ones it was loaded with
    (those win: a user's ``--set`` over a policy's settings); validated as ``load_scenario`` does.
    A scenario not from ``load_scenario`` (no tree) is an error."""
    if sc.tree is None:
        raise ConfigError(f"{sc.source}: not loaded from a file: cannot apply {', '.join(overrides)}")
    if _with_tree(sc.tree, sc.source, dict(sc.overrides)) != sc:  # a change made after loading would be lost
        raise ConfigError(f"{sc.source}: changed after loading (dataclasses.replace): load it with those "
                          f"changes as overrides to apply {', '.join(overrides)}")
    return _with_tree(sc.tree, sc.source, {**overrides, **dict(sc.overrides)})


def _with_tree(tree: Any, source: str, overrides: dict[str, Any]) -> Scenario:
    import copy

    try:
        data = copy.deepcopy(tree)
    except RecursionError:  # yaml read it; a copy of that depth is not a scenario either
        raise ConfigError(f"{source}: nested too deeply for a scenario") from None
    for key, value in overrides.items():
        node, *parents = data, *key.split(".")[:-1]
        for i, part in enumerate(parents):
            if not isinstance(node, dict) or part not in node:
                raise ConfigError(f"{source}: {'.'.join(parents[:i + 1])}: missing (setting {key})")
            node = node[part]
        if not isinstance(node, dict):
            raise ConfigError(f"{source}: {key}: its parent is not a mapping")
        node[key.split(".")[-1]] = copy.deepcopy(value)
    try:
        sc = parse_scenario(data, source)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    return replace(sc, tree=tree, overrides=tuple(overrides.items()))


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
