"""Generated missions: a scenario drawn from a *family* and a seed (``pmon worlds``, ``pmon eval --worlds``).

Every choice in the flight default was measured on one scenario; these families are the other
1 km missions it must also fly (issue 47). A world is a scenario tree as a file holds it (the
geometry only: every other setting at its declared default, as config/paper.yaml leaves them),
checked by the project's own validator (``onboard.config.parse_scenario``) and by a reachability
check of its own (each target's start and goal in one free region of the ground, the obstacles
inflated by ``guidance.obstacle_margin_m``). The same (family, seed, index) gives the same world
on every machine: its draws come from ``numpy.random.SeedSequence`` keyed by all three.

Families (the 1 km cube of the paper's; h = ``uav.altitude_m``'s default, 40 m; "low" buildings
are at most ``LOW_M[1]`` tall and the UAV flies over them, "tall" ones at least ``TALL_M[0]``
block it; the targets go round both):

* ``town``: 3-5 targets crossing a town of 6-8 buildings of mixed height (at least 2 low, 2 tall),
  half of them on the targets' straight paths to one of 3 exits;
* ``open``: 3 targets, 3 exits, at most one (low) obstacle;
* ``crowd``: 6 targets from all sides converging on one square, 3-4 obstacles (at least one low
  and one tall) on their ways in; two more exits nobody names;
* ``corridor``: 3-6 targets along a road between two rows of buildings, each heading for the
  road's far end; a third exit off the road;
* ``mixed``: 1-10 targets, 0-10 obstacles of any height and yaw, 3-4 exits anywhere; half the
  targets also declare every exit as a candidate goal (``goals``: docs/SCENARIO.md).

Each target's ``goal`` is its true exit (what the nominal truth steers it to); the worlds
declare at least 3 goal regions, so ``--truth candidate_goal`` runs on every one. Town, open and
corridor worlds are drawn in a frame where the targets start north and then turned by a random
multiple of 90 degrees about the area's centre.
"""
from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

FAMILIES = ("town", "open", "crowd", "corridor", "mixed")
AREA_M = 1000.0
CENTRE_M = AREA_M / 2
ALTITUDE_M = 40.0  # uav.altitude_m's default: what "low" and "tall" are measured against
LOW_M = (12.0, 30.0)  # a low building's height: the UAV (10 m margin) flies over it
TALL_M = (50.0, 90.0)  # a tall one's: it blocks the UAV
GOAL_M = 100.0  # a goal region's side (the paper's G)
EDGE_M = 60.0  # obstacles keep this from the area's edge
GAP_M = 40.0  # ... and from each other and every goal region: the ground between them stays free
CLEAR_M = 25.0  # a target's start from any obstacle
FROM_GOAL_M = 300.0  # a target's start from its goal's centre, at least
ORIGIN = {"lat_deg": 35.1450, "lon_deg": 33.4110, "alt_m": 160.0}  # the paper's
CELL_M = 5.0  # the reachability check's grid
TRIES = 2000  # draws per placed thing before the world is redrawn
ATTEMPTS = 50  # redraws of a world


class _Redraw(Exception):
    """This draw of the world failed a rule: draw it again from the next attempt's stream."""


@dataclass(frozen=True)
class Rect:
    """A footprint on the ground: centre, x and y extents before yaw, yaw (deg)."""

    x: float
    y: float
    sx: float
    sy: float
    yaw_deg: float = 0.0

    def gap(self, o: "Rect") -> float:
        """A lower bound of the ground distance between the two (exact for unyawed ones)."""
        if self.yaw_deg == 0.0 and o.yaw_deg == 0.0:
            return max(abs(self.x - o.x) - (self.sx + o.sx) / 2, abs(self.y - o.y) - (self.sy + o.sy) / 2)
        return math.hypot(self.x - o.x, self.y - o.y) - self.radius - o.radius

    @property
    def radius(self) -> float:
        return math.hypot(self.sx, self.sy) / 2

    def distance(self, x: float, y: float) -> float:
        """From the point (x, y) to the footprint (0 inside)."""
        c, s = math.cos(math.radians(self.yaw_deg)), math.sin(math.radians(self.yaw_deg))
        dx, dy = x - self.x, y - self.y
        u, v = abs(c * dx + s * dy) - self.sx / 2, abs(-s * dx + c * dy) - self.sy / 2
        return math.hypot(max(u, 0.0), max(v, 0.0))

    def edge_gap(self) -> float:
        r = self.radius if self.yaw_deg else 0.0
        hx, hy = (r, r) if self.yaw_deg else (self.sx / 2, self.sy / 2)
        return min(self.x - hx, AREA_M - self.x - hx, self.y - hy, AREA_M - self.y - hy)


@dataclass
class _World:
    """A world being drawn: obstacles (footprint, height), goal regions, targets."""

    goals: dict  # name -> (x, y)
    targets: list  # (x, y, goal name, candidates: tuple of names)
    obstacles: list  # (Rect, height)

    def goal_rect(self, name: str) -> Rect:
        x, y = self.goals[name]
        return Rect(x, y, GOAL_M, GOAL_M)

    def fits(self, r: Rect) -> bool:
        """An obstacle there keeps its gaps to the edge, the others, the goals and the targets."""
        return (r.edge_gap() >= EDGE_M and all(r.gap(o) >= GAP_M for o, _ in self.obstacles)
                and all(r.gap(self.goal_rect(g)) >= GAP_M for g in self.goals)
                and all(r.distance(t[0], t[1]) >= CLEAR_M for t in self.targets))

    def place(self, rng, draw, height: float) -> bool:
        """An obstacle drawn by ``draw(rng) -> Rect`` where it fits; False when none did."""
        for _ in range(TRIES):
            r = draw(rng)
            if self.fits(r):
                self.obstacles.append((r, height))
                return True
        return False


def _r(v: float) -> float:
    return round(float(v), 1)


def _low(rng) -> float:
    return _r(rng.uniform(*LOW_M))


def _tall(rng) -> float:
    return _r(rng.uniform(*TALL_M))


def _heights(rng, n: int, low: int, tall: int) -> list[float]:
    """n heights, at least ``low`` low and ``tall`` tall ones, the rest either, shuffled."""
    kinds = ["low"] * low + ["tall"] * tall + [("low" if rng.random() < 0.5 else "tall") for _ in range(n - low - tall)]
    rng.shuffle(kinds)
    return [_low(rng) if k == "low" else _tall(rng) for k in kinds]


def _exits_south(rng, n: int = 3) -> dict:
    """n exits spread along the south edge (the canonical frame's)."""
    width = (AREA_M - 2 * 80.0) / n
    return {f"G{i + 1}": (_r(80.0 + width * (i + 0.5) + rng.uniform(-0.2, 0.2) * width), _r(rng.uniform(80.0, 200.0)))
            for i in range(n)}


def _targets_north(rng, w: _World, n: int, y=(760.0, 950.0)) -> None:
    """n targets starting in the north band, 60 m apart, each heading for an exit drawn at random."""
    names = list(w.goals)
    for _ in range(TRIES):
        if len(w.targets) == n:
            return
        x, yy = _r(rng.uniform(80.0, AREA_M - 80.0)), _r(rng.uniform(*y))
        g = names[int(rng.integers(len(names)))]
        if all(math.hypot(x - t[0], yy - t[1]) >= 60.0 for t in w.targets) and \
                math.hypot(x - w.goals[g][0], yy - w.goals[g][1]) >= FROM_GOAL_M:
            w.targets.append((x, yy, g, ()))
    raise _Redraw


def _on_path(w: _World, rng, size=(50.0, 140.0), jitter_m: float = 40.0):
    """A footprint drawn on a random target's straight line to its goal (the paper's Fig. 1)."""
    def draw(rng):
        x0, y0, g, _ = w.targets[int(rng.integers(len(w.targets)))]
        gx, gy = w.goals[g]
        u = rng.uniform(0.3, 0.7)
        return Rect(_r(x0 + u * (gx - x0) + rng.uniform(-jitter_m, jitter_m)),
                    _r(y0 + u * (gy - y0) + rng.uniform(-jitter_m, jitter_m)),
                    _r(rng.uniform(*size)), _r(rng.uniform(*size)))
    return draw


def _anywhere(lo: float, hi: float, size=(50.0, 140.0), yaw: bool = False):
    def draw(rng):
        return Rect(_r(rng.uniform(lo, hi)), _r(rng.uniform(lo, hi)), _r(rng.uniform(*size)), _r(rng.uniform(*size)),
                    _r(rng.uniform(-45.0, 45.0)) if yaw else 0.0)
    return draw


def _town(rng) -> _World:
    w = _World(_exits_south(rng), [], [])
    _targets_north(rng, w, int(rng.integers(3, 6)))
    heights = _heights(rng, int(rng.integers(6, 9)), low=2, tall=2)
    for i, h in enumerate(heights):
        draw = _on_path(w, rng) if i % 2 == 0 else _anywhere(150.0, 850.0)
        if not w.place(rng, draw, h):
            raise _Redraw
    return w


def _open(rng) -> _World:
    w = _World(_exits_south(rng), [], [])
    _targets_north(rng, w, 3, y=(650.0, 950.0))
    if rng.random() < 0.5 and not w.place(rng, _on_path(w, rng), _low(rng)):
        raise _Redraw
    return w


def _crowd(rng) -> _World:
    """Six targets on a ring, every one heading for the square at the centre."""
    sq = (_r(CENTRE_M + rng.uniform(-50, 50)), _r(CENTRE_M + rng.uniform(-50, 50)))
    corners = [(120.0, 120.0), (880.0, 120.0), (880.0, 880.0), (120.0, 880.0)]
    k = int(rng.integers(4))  # two opposite corners are the exits nobody names
    w = _World({"SQ": sq, "X1": corners[k], "X2": corners[(k + 2) % 4]}, [], [])
    phase = rng.uniform(0, 2 * math.pi)
    for j in range(6):
        a = phase + 2 * math.pi * j / 6 + math.radians(rng.uniform(-15, 15))
        r = rng.uniform(380.0, 450.0)
        x = float(np.clip(sq[0] + r * math.cos(a), 40.0, AREA_M - 40.0))
        y = float(np.clip(sq[1] + r * math.sin(a), 40.0, AREA_M - 40.0))
        w.targets.append((_r(x), _r(y), "SQ", ()))
    n = int(rng.integers(3, 5))
    for h in _heights(rng, n, low=1, tall=1):
        def draw(rng):
            x0, y0, _, _ = w.targets[int(rng.integers(6))]
            u = rng.uniform(0.35, 0.65)
            s = rng.uniform(60.0, 120.0, 2)
            return Rect(_r(x0 + u * (sq[0] - x0)), _r(y0 + u * (sq[1] - y0)), _r(s[0]), _r(s[1]))
        if not w.place(rng, draw, h):
            raise _Redraw
    return w


def _corridor(rng) -> _World:
    """A road along x between two rows of buildings; targets on it head for its far end."""
    y0 = _r(CENTRE_M + rng.uniform(-100, 100))
    half = rng.uniform(35.0, 50.0)  # the road's half width
    w = _World({"R1": (80.0, y0), "R2": (920.0, y0),  # the road's ends, and an exit off it
                "X": (_r(rng.uniform(300, 700)), 900.0 if y0 < CENTRE_M else 100.0)}, [], [])
    rows = []
    for side in (1, -1):
        x = 180.0 + rng.uniform(0, 30)
        while True:
            length, depth = rng.uniform(60.0, 140.0), rng.uniform(60.0, 120.0)
            if x + length > 820.0:
                break
            rows.append(Rect(_r(x + length / 2), _r(y0 + side * (half + depth / 2)), _r(length), _r(depth)))
            x += length + rng.uniform(GAP_M + 1, 80.0)
    if len(rows) < 2:
        raise _Redraw
    for r, h in zip(rows, _heights(rng, len(rows), low=1, tall=1)):
        if not w.fits(r):
            raise _Redraw
        w.obstacles.append((r, h))
    n = int(rng.integers(3, 7))
    for _ in range(TRIES):
        if len(w.targets) == n:
            break
        x, y = _r(rng.uniform(60.0, 940.0)), _r(y0 + rng.uniform(-1, 1) * (half - CLEAR_M - 1))
        g = "R2" if x < CENTRE_M else "R1"
        if all(abs(x - t[0]) >= 40.0 for t in w.targets) and abs(x - w.goals[g][0]) >= FROM_GOAL_M \
                and all(r.distance(x, y) >= CLEAR_M for r, _ in w.obstacles):
            w.targets.append((x, y, g, ()))
    if len(w.targets) < n:
        raise _Redraw
    return w


def _mixed(rng) -> _World:
    n_goals = int(rng.integers(3, 5))
    w = _World({}, [], [])
    for _ in range(TRIES):
        if len(w.goals) == n_goals:
            break
        x, y = _r(rng.uniform(80, 920)), _r(rng.uniform(80, 920))
        if all(math.hypot(x - gx, y - gy) >= 250.0 for gx, gy in w.goals.values()):
            w.goals[f"G{len(w.goals) + 1}"] = (x, y)
    names = tuple(w.goals)
    n = int(rng.integers(1, 11))
    for _ in range(TRIES):
        if len(w.targets) == n:
            break
        x, y = _r(rng.uniform(40, 960)), _r(rng.uniform(40, 960))
        g = names[int(rng.integers(len(names)))]
        if all(math.hypot(x - t[0], y - t[1]) >= 40.0 for t in w.targets) and \
                math.hypot(x - w.goals[g][0], y - w.goals[g][1]) >= FROM_GOAL_M and \
                all(Rect(gx, gy, GOAL_M, GOAL_M).distance(x, y) > 0 for gx, gy in w.goals.values()):
            w.targets.append((x, y, g, tuple(o for o in names if o != g) if rng.random() < 0.5 else ()))
    if len(w.targets) < n or len(w.goals) < 3:
        raise _Redraw
    for _ in range(int(rng.integers(0, 11))):
        h = _r(rng.uniform(LOW_M[0], TALL_M[1]))
        w.place(rng, _anywhere(120.0, 880.0, (40.0, 160.0), yaw=True), h)  # fewer where none fits
    return w


BUILDERS = {"town": _town, "open": _open, "crowd": _crowd, "corridor": _corridor, "mixed": _mixed}
TURNED = ("town", "open", "corridor")  # drawn with the targets north, then turned


def _turn(x: float, y: float, k: int) -> tuple[float, float]:
    """(x, y) turned by k * 90 deg about the area's centre (exact on the 0.1 m grid)."""
    dx, dy = x - CENTRE_M, y - CENTRE_M
    for _ in range(k % 4):
        dx, dy = -dy, dx
    return _r(CENTRE_M + dx), _r(CENTRE_M + dy)


def _uav_start(rng, w: _World) -> tuple[float, float]:
    """The UAV's start: anywhere 50 m in from the edge, 30 m clear of the buildings it cannot overfly
    (``pmon eval`` draws its own start per trial; this is the file's, for ``pmon run``)."""
    for _ in range(TRIES):
        x, y = _r(rng.uniform(50, 950)), _r(rng.uniform(50, 950))
        if all(r.distance(x, y) >= 30.0 for r, h in w.obstacles if h > ALTITUDE_M):
            return x, y
    raise _Redraw


def _tree(name: str, w: _World, start: tuple[float, float], k: int) -> dict:
    """The world as a scenario file holds it, turned by k * 90 deg."""
    goals = [{"name": g, "center_m": [*_turn(x, y, k), 0.0], "size_m": [GOAL_M, GOAL_M, 0.0]}
             for g, (x, y) in w.goals.items()]
    targets = []
    for j, (x, y, g, cand) in enumerate(w.targets):
        t = {"name": f"T{j + 1}", "position_m": [*_turn(x, y, k), 0.0], "goal": g}
        if cand:
            t["goals"] = list(cand)
        targets.append(t)
    obstacles = []
    for i, (r, h) in enumerate(w.obstacles):
        sx, sy = (r.sy, r.sx) if k % 2 else (r.sx, r.sy)
        obstacles.append({"name": f"B{i + 1}", "center_m": [*_turn(r.x, r.y, k), h / 2], "size_m": [sx, sy, h],
                          "yaw_deg": r.yaw_deg})
    return {"name": name, "origin": dict(ORIGIN),
            "area": {"min_m": [0.0, 0.0, 0.0], "max_m": [AREA_M, AREA_M, AREA_M]},
            "targets": targets, "goals": goals, "obstacles": obstacles,
            "uav": {"start_m": [*_turn(*start, k), ALTITUDE_M]}}


def unreachable(sc) -> str | None:
    """Why some target cannot reach its goal on the ground, or None: its start and every goal it may
    head for must lie in one connected free region of a ``CELL_M`` grid, the obstacles inflated by
    ``guidance.obstacle_margin_m`` (what the targets' guidance keeps from them)."""
    from scipy import ndimage

    from onboard.core.obstacles import Obstacles

    lo, hi = np.asarray(sc.area.min_m[:2]), np.asarray(sc.area.max_m[:2])
    nx, ny = (int(v) for v in np.ceil((hi - lo) / CELL_M))
    xs, ys = lo[0] + CELL_M * (np.arange(nx) + 0.5), lo[1] + CELL_M * (np.arange(ny) + 0.5)
    free = np.ones((nx, ny), bool)
    if sc.obstacles:
        ob = Obstacles.from_boxes(sc.obstacles).inflate(sc.guidance.obstacle_margin_m).extruded(0.0)
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        pts = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
        free = ~ob.contains(pts).any(axis=1).reshape(nx, ny)
    labels, _ = ndimage.label(free)

    def region(p) -> int:
        i, j = (min(int((p[0] - lo[0]) // CELL_M), nx - 1), min(int((p[1] - lo[1]) // CELL_M), ny - 1))
        return int(labels[i, j])

    for t in sc.targets:
        here = region(t.position_m)
        for g in t.candidates:
            there = region(sc.goal_named(g).center_m)
            if here == 0 or there != here:
                return f"target {t.name} cannot reach goal {g}"
    return None


def _stream(family: str, seed: int, index: int, attempt: int) -> np.random.Generator:
    key = zlib.crc32(family.encode("utf-8"))  # stable across processes (unlike hash())
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(key, int(index), int(attempt))))


def world_name(family: str, seed: int, index: int) -> str:
    return f"{family}-s{seed}-{index:03d}"


def world_tree(family: str, seed: int, index: int) -> dict:
    """World ``index`` of ``family`` for ``seed``, as a scenario file holds it (checked: it parses
    with the project's validator and every target reaches its goals). ValueError for an unknown
    family or a negative seed or index."""
    from onboard.config import ConfigError, parse_scenario

    if family not in BUILDERS:
        raise ValueError(f"unknown world family {family!r} (one of {', '.join(FAMILIES)})")
    if seed < 0 or index < 0:
        raise ValueError(f"a world's seed and index must be >= 0, got {seed}, {index}")
    last = "?"
    for attempt in range(ATTEMPTS):
        rng = _stream(family, seed, index, attempt)
        try:
            w = BUILDERS[family](rng)
            start = _uav_start(rng, w)
        except _Redraw:
            last = "a draw's rule failed"
            continue
        k = int(rng.integers(4)) if family in TURNED else 0
        tree = _tree(world_name(family, seed, index), w, start, k)
        try:
            sc = parse_scenario(tree)
        except ConfigError as exc:
            last = str(exc)
            continue
        why = unreachable(sc)
        if why is None:
            return tree
        last = why
    raise RuntimeError(f"no valid {family} world for seed {seed}, index {index} in {ATTEMPTS} draws ({last})")


def draw_world(family: str, seed: int, index: int):
    """World ``index`` of ``family`` for ``seed`` as a Scenario (``world_tree``, parsed)."""
    from onboard.config import parse_scenario

    return parse_scenario(world_tree(family, seed, index), f"<world {world_name(family, seed, index)}>")


def world_yaml(family: str, seed: int, index: int) -> str:
    """The world as a scenario file a user can open, check and run (``pmon check-config FILE``,
    ``pmon eval FILE``): its geometry; every other setting left at its declared default."""
    import yaml

    tree = world_tree(family, seed, index)
    head = (f"# A generated world (sim/truth/worlds.py): family {family}, seed {seed}, world {index}.\n"
            f"# Drawn again by: pmon worlds {family} --n {index + 1} --seed {seed}\n"
            "# Mission frame: local ENU in metres; every setting not stated here is at its default\n"
            "# (docs/SETTINGS.md), as in config/paper.yaml. Obstacles lower than uav.altitude_m are overflown.\n")
    body = yaml.safe_dump(tree, sort_keys=False, default_flow_style=None, width=110)
    return head + body


def write_worlds(family: str, n: int, seed: int, out_dir) -> list[Path]:
    """Worlds 0..n-1 of ``family`` for ``seed`` as files ``out_dir/NAME.yaml``; their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(n):
        p = out / f"{world_name(family, seed, i)}.yaml"
        p.write_text(world_yaml(family, seed, i), encoding="utf-8")
        paths.append(p)
    return paths


def parse_spec(text: str) -> list[tuple[str, int]]:
    """``FAMILY:N[,FAMILY:N...]`` (``pmon eval --worlds``) as [(family, n)]; ValueError, one line."""
    out = []
    for part in (p.strip() for p in text.split(",")):
        fam, sep, n = part.partition(":")
        if fam not in BUILDERS or not sep or not n.isdigit() or int(n) < 1:
            raise ValueError(f"--worlds {part!r}: expected FAMILY:N with N >= 1 and FAMILY one of "
                             f"{', '.join(FAMILIES)}")
        if fam in dict(out):
            raise ValueError(f"--worlds names {fam} twice")
        out.append((fam, int(n)))
    return out

