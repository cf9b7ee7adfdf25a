"""``pmon replay RUNLOG``: a flight's run log re-run through the core, to the same decisions.

The run log's ``replay`` fields (onboard/app/replay_record.py) hold each tick's inputs (its scans,
the UAV state it planned from, the generator's state, the setup's parameters when they changed)
and where the clock stopped its guidance, as counts of QP solves. The replay builds the run's
core from the recorded scenario and seed, feeds it those inputs tick by tick with the recorded
counts as the guidance's budget (``clock_stops.SearchClock``: no decision by the clock) and
compares every output with the recorded one, bit for bit: it prints the first tick and stage
that differ (the generator's state as the tick began, the estimates, the guidance, the next UAV
position) and by how much, or that all agree. ``--set KEY=VALUE`` (as ``pmon check-config``'s)
replays with a change, through to the end, and prints per tick how far the estimates and the next
position moved, and a summary.
"""
from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np

from onboard.app.tick.core_side import MonitorCore
from onboard.app.params import SPECS, ParamTable
from onboard.app.replay_record import VERSION, outputs
from onboard.config import ConfigError, override, parse_overrides, parse_scenario
from onboard.core import monitor
from onboard.files import FileRefused, open_regular
from onboard.core.clock_stops import SearchClock
from onboard.core.monitor import Scan, UavState


class RunlogError(ValueError):
    """A run log a replay cannot read: one line naming the file and line."""


@dataclass(frozen=True)
class Runlog:
    seed: int
    scenario: object  # onboard.config.Scenario
    ticks: tuple[dict, ...]  # each tick's record (with its ``replay`` field)
    lines: tuple[int, ...]  # each tick's line number in the file


def read_runlog(path: str) -> Runlog:
    """The run log at ``path``; RunlogError naming the line that is not a replayable tick."""
    ticks, lines = [], []
    try:
        with open_regular(path, text=True) as f:
            for n, line in enumerate(f, 1):
                if not line.strip():
                    continue
                rec = _record(line, f"{path}:{n}")
                why = _not_a_tick(rec, first=not ticks)
                if why:
                    raise RunlogError(f"{path}:{n}: {why}")
                ticks.append(rec)
                lines.append(n)
    except FileRefused as exc:
        raise RunlogError(str(exc)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise RunlogError(f"{path}: cannot read: {exc}") from None
    if not ticks:
        raise RunlogError(f"{path}: no tick records")
    run = ticks[0]["replay"]["run"]
    where = f"{path}:{lines[0]}"
    try:
        return Runlog(int(run["seed"]), parse_scenario(run["scenario"], where), tuple(ticks), tuple(lines))
    except ConfigError as exc:
        raise RunlogError(f"{where}: the recorded scenario: {exc}") from None
    except (KeyError, TypeError, ValueError) as exc:
        raise RunlogError(f"{where}: the run's seed or scenario: {type(exc).__name__}: {exc}") from None


def _record(line: str, where: str):
    try:
        return json.loads(line)
    except json.JSONDecodeError as exc:
        raise RunlogError(f"{where}: not a JSON record ({exc.msg} at column {exc.colno})") from None
    except (ValueError, RecursionError) as exc:  # an integer of too many digits, nesting too deep
        raise RunlogError(f"{where}: not a JSON record ({str(exc)[:80] or type(exc).__name__})") from None


_NEEDED = ("rng", "scans", "plan_from", "n_radial", "guidance_s", "deadlines", "stops", "out")


def _not_a_tick(rec, first: bool) -> str | None:
    if not isinstance(rec, dict) or "t" not in rec:
        return "not a tick record (no 't')"
    rp = rec.get("replay")
    if not isinstance(rp, dict):
        return "no 'replay' field (a run log of an older pmon, or not a run log)"
    missing = [k for k in _NEEDED if k not in rp]
    if first and ("run" not in rp or "setup" not in rp):
        missing += [k for k in ("run", "setup") if k not in rp]
    if missing:
        return f"'replay' lacks {', '.join(missing)} (truncated or edited?)"
    if first and not isinstance(rp["run"], dict):
        return "'replay' 'run' is not a mapping"
    if first and rp["run"].get("version") != VERSION:
        return f"replay version {rp['run'].get('version')!r}, this pmon reads {VERSION}"
    return None


@dataclass(frozen=True)
class Replayed:
    """One tick replayed: its recorded and replayed outputs (``replay_record.outputs``)."""

    index: int
    t: float
    recorded: dict
    replayed: dict
    rng_same: bool


class Replay:
    """The run's core, re-run tick by tick; ``changes``: setting key -> value (``--set``)."""

    def __init__(self, log: Runlog, changes: dict | None = None):
        self.log = log
        self.changes = dict(changes or {})
        scenario = override(log.scenario, self.changes) if self.changes else log.scenario
        self.fixed = {s.name for s in SPECS if s.key in self.changes}  # parameters --set holds
        self.params = ParamTable.from_scenario(scenario)
        self.limits = SimpleNamespace(planner=None)
        self.core = MonitorCore(scenario, self.params, self.limits, np.random.default_rng(log.seed))

    def ticks(self, at: list[int] | None = None):
        """Each tick replayed, in order; ``at[0]``: the index of the one being replayed."""
        for i, rec in enumerate(self.log.ticks):
            if at is not None:
                at[0] = i
            yield self.tick(i, rec)

    def tick(self, i: int, rec: dict) -> Replayed:
        rp = rec["replay"]
        if "setup" in rp:
            self._apply_setup(rp["setup"])
        setup = self.core.tick_setup()
        setup = replace(setup, guidance=replace(setup.guidance, max_solve_time_s=rp["guidance_s"]))
        rng_same = _same(self.core.rng.bit_generator.state, rp["rng"])
        scans = [_scan(s) for s in rp["scans"]]
        pf = rp["plan_from"]
        plan_from = None if pf is None else UavState(np.array(pf["p"]), np.array(pf["v"]),
                                                     None if pf["a"] is None else np.array(pf["a"]))
        clock = SearchClock(time.perf_counter, replay=rp["stops"])
        core = self.core
        core.state, res = monitor.tick(setup, core.state, scans, core.rng, plan_from=plan_from,
                                       workspace=core.workspace, timer=clock)
        core.reseed_collapsed(setup, res)
        return Replayed(i, rec["t"], rp["out"], json.loads(json.dumps(outputs(res))), rng_same)

    def _apply_setup(self, rec: dict) -> None:
        for name, value in rec["params"].items():
            if name in self.params and name not in self.fixed and self.params[name] != value:
                why = self.params.set(name, float(value))
                if why:
                    raise RunlogError(f"recorded parameter refused: {why}")
        self.limits.planner = None if rec["planner"] is None else tuple(rec["planner"])


def _scan(s: dict) -> Scan:
    return Scan(np.array(s["p"]), tuple(np.array(b, float) for b in s["b"]),
                None if s["c"] is None else tuple(s["c"]))


def _same(a, b) -> bool:
    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def first_difference(r: Replayed) -> str | None:
    """The first stage at which a replayed tick differs from its record, and by how much."""
    rec, got = r.recorded, r.replayed
    if not r.rng_same:
        return "rng: the generator's state as the tick began differs"
    for key, stage in (("means", "estimate"), ("covs", "estimate (covariance)")):
        d = _max_abs(rec[key], got[key])
        if d != 0.0:
            return f"{stage}: {key} differ by up to {d:.6g}"
    if rec["plans"] != got["plans"] or rec["qp_solves"] != got["qp_solves"] or rec["margins"] != got["margins"]:
        return (f"guidance: status {rec['plans']} -> {got['plans']}, QP solves {rec['qp_solves']} -> "
                f"{got['qp_solves']}")
    for key, stage in (("next", "setpoint"), ("v_next", "setpoint (velocity)")):
        if (rec[key] is None) != (got[key] is None):
            return f"{stage}: {key} {rec[key]} -> {got[key]}"
        d = 0.0 if rec[key] is None else _max_abs(rec[key], got[key])
        if d != 0.0:
            return f"{stage}: {key} differs by up to {d:.6g} m" + ("/s" if key == "v_next" else "")
    return None


def _max_abs(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape != b.shape:
        return math.inf
    same = (a == b) | (np.isnan(a) & np.isnan(b))
    return 0.0 if same.all() else float(np.max(np.where(same, 0.0, np.abs(a - b))))


def shifts(r: Replayed) -> tuple[float, float]:
    """(largest planar shift of an estimate, planar shift of the next position) in m (NaN: no
    next position in one of them)."""
    m0, m1 = np.asarray(r.recorded["means"])[:, :2], np.asarray(r.replayed["means"])[:, :2]
    est = float(np.max(np.linalg.norm(m1 - m0, axis=1))) if len(m0) else 0.0
    n0, n1 = r.recorded["next"], r.replayed["next"]
    sp = math.nan if n0 is None or n1 is None else float(np.hypot(n1[0] - n0[0], n1[1] - n0[1]))
    return est, sp


def add_arguments(p) -> None:
    p.add_argument("runlog", help="the run log (pmon run --runlog FILE) to replay")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="replay with this scenario value changed (VALUE read as YAML; repeatable), as pmon eval's; "
                        "prints how far estimates and setpoints move")
    p.add_argument("--quiet", action="store_true", help="with --set: the summary only, no line per tick")


def run(args) -> int:
    try:
        changes = parse_overrides(args.set)
        log = read_runlog(args.runlog)
        rp = Replay(log, changes)
    except (RunlogError, ConfigError) as exc:
        print(f"pmon replay: {exc}", file=sys.stderr)
        return 2
    out: list[Replayed] = []
    at = [0]  # the tick being replayed
    try:
        for r in rp.ticks(at):
            if not changes:
                why = first_difference(r)
                if why:
                    print(f"{args.runlog}: diverged at tick {r.index} (t={r.t:.3f} s, line {log.lines[r.index]}): "
                          f"{why}")
                    return 1
            else:
                out.append(r)
                if not args.quiet:
                    est, sp = shifts(r)
                    print(f"tick {r.index:4d} t={r.t:9.3f}: estimate shift {est:8.3f} m, setpoint shift {sp:8.3f} m")
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, RecursionError) as exc:
        # a record whose values do not fit the run (edited, or of another scenario)
        print(f"pmon replay: {args.runlog}:{log.lines[at[0]]}: cannot replay this tick's record "
              f"({type(exc).__name__}: {str(exc)[:120]})", file=sys.stderr)
        return 2
    if not changes:
        stopped = sum(len(t["replay"]["stops"]) for t in log.ticks)
        print(f"{args.runlog}: {len(log.ticks)} ticks replayed bit for bit (estimates, guidance, setpoints; "
              f"{stopped} guidance solves stopped by the clock, replayed at their QP counts)")
        return 0
    print(summary(out, ", ".join(args.set)))
    return 0


def summary(replayed: list[Replayed], what: str) -> str:
    first = next((r for r in replayed if first_difference(r)), None)
    if first is None:
        return f"with {what}: {len(replayed)} ticks, no estimate or setpoint changed"
    est = np.array([shifts(r)[0] for r in replayed])
    sp = np.array([shifts(r)[1] for r in replayed])
    sp = sp[np.isfinite(sp)]
    sp_text = "no setpoints" if not len(sp) else f"setpoint shift mean {sp.mean():.3f} m, max {sp.max():.3f} m"
    return (f"with {what}: first changed at tick {first.index} (t={first.t:.3f} s): {first_difference(first)}; "
            f"over {len(replayed)} ticks: estimate shift mean {est.mean():.3f} m, max {est.max():.3f} m; {sp_text}")
