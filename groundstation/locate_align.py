"""Recorded bearings read and put on a pose log's timeline, for ``pmon locate`` (docs/LOCATE.md).

Two recordings are read, each line checked as the app checks it live:

* **KrakenSDR's** "Kraken App" lines (its data recording ``mydata.csv``, or ``DOA_value.html``
  documents one after another; onboard/app/kraken/line.py): consecutive lines of one time stamp
  are one frame. The frames go through the app's own ``KrakenSource`` (onboard/app/kraken/source.py):
  each VFO's line is its target's, the frame dated at the middle of its acquisition (``epoch -
  latency / 2``, KrakenSDR's own latency field) and put on the autopilot's timeline through the
  UTC the pose log holds, its spectrum's peaks turned into bearings with the vehicle's heading at
  that time and the array's ``kraken.mount_offset_deg``, each frame in the slot of its nearest
  whole second.
* **DF datagrams** (docs/DATAGRAM.md) one JSON object per line, as ``pmon feed replay`` takes
  them, or the feed's truth JSONL (sim/stack/feed.py: ``bearings`` per channel): already bearings, on
  the autopilot's timeline (``t``).

``time_offset_s`` is added to every bearing's time (a DF clock that is off the autopilot's).
What cannot be aligned is counted, not fatal: bearings before the pose record starts or after it
ends, bearings inside a gap of the record (``poses.GAP_S``), and what the KrakenSDR input refuses
(its reasons, docs/KRAKENSDR.md). A malformed line, or a recording none of whose bearings falls
on the pose record, is an ``AlignError``: one line naming the file and the line or the times.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field

import numpy as np

from onboard.app.df import datagram as dg
from onboard.app.kraken import line as kl
from onboard.app.autopilot.clock import ManualClock
from onboard.app.kraken.source import KrakenScan, KrakenSource
from onboard.files import open_regular

MAX_BYTES = 2 * 1024 ** 3  # a day of KrakenSDR lines at one per second and VFO, four VFOs: ~1 GB
BEARING_GAP_S = 5.0  # seconds without a bearing inside the recording: said


class AlignError(ValueError):
    """A recording that cannot be used; the message names the file and the line or time."""


@dataclass
class Aligned:
    """Per whole autopilot second, per channel, its scan (``KrakenScan``: ``t`` the slot,
    ``t_measured`` its own time), and one line for each thing that could not be aligned."""

    slots: dict[int, dict[int, KrakenScan]] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    frames: int = 0  # frames (KrakenSDR) or scan times (datagrams) read
    used: int = 0  # ... of them aligned

    def add(self, scan: KrakenScan, now=None) -> None:
        self.slots.setdefault(int(scan.t), {}).setdefault(scan.ch, scan)


@dataclass
class _Misses:
    """Frames that fell outside the pose record or into a gap: count, first and last line, time."""

    what: str
    n: int = 0
    lines: list = field(default_factory=list)
    times: list = field(default_factory=list)

    def add(self, line: int, t: float) -> None:
        self.n += 1
        self.lines.append(line)
        self.times.append(t)

    def note(self, path: str) -> str | None:
        if not self.n:
            return None
        return (f"{path}: {self.n} frame(s) {self.what}, lines {min(self.lines)}-{max(self.lines)} "
                f"(autopilot t {min(self.times):.1f}..{max(self.times):.1f} s): not aligned")


def kind_of(path: str) -> str:
    """``datagram`` when the recording's first line is a JSON object, else ``kraken``."""
    with open_regular(path, MAX_BYTES) as f:
        for raw in f:
            if raw.strip():
                return "datagram" if raw.lstrip().startswith(b"{") else "kraken"
    raise AlignError(f"{path}: empty: no bearings")


def kraken_frames(path: str) -> list[tuple[int, list[kl.RecordedLine]]]:
    """The recording's frames (``onboard.app.kraken.line.recording_frames``), in time order."""
    with open_regular(path, MAX_BYTES) as f:
        try:
            frames = kl.recording_frames(f)
        except kl.RecordingError as exc:
            raise AlignError(f"{path}:{exc.number}: {exc.error}") from None
    for (before, _), (epoch, lines) in zip(frames, frames[1:]):
        if epoch < before:
            raise AlignError(f"{path}:{lines[0].number}: time goes back {(before - epoch) / 1000:.3f} s "
                             "(a recording is in time order)")
    if not frames:
        raise AlignError(f"{path}: no KrakenSDR line in it")
    return frames


def _where(t: float, log, gaps) -> str | None:
    if t < log.start:
        return "before"
    if t > log.end:
        return "after"
    if any(a < t < b for a, b in gaps):
        return "gap"
    return None


class _TimeMap:
    def __init__(self, utc, offset_s: float):
        self.utc, self.offset_s = utc, offset_s

    def autopilot_time(self, unix_s: float) -> float | None:
        t = self.utc.autopilot_time(unix_s)
        return None if t is None else t + self.offset_s


def align_kraken(path: str, sc, log, time_offset_s: float = 0.0) -> Aligned:
    """KrakenSDR's recording at ``path`` on the pose log ``log`` (groundstation/poses.py), with the
    scenario ``sc``'s ``kraken`` section and targets."""
    if not sc.kraken.vfos:
        raise AlignError(f"{sc.source}: kraken.vfos: none: which VFO frequency is which target? (docs/KRAKENSDR.md)")
    frames = kraken_frames(path)
    if log.utc.autopilot_time(0.0) is None:
        raise AlignError(f"{log.path}: no UTC in this {log.kind} (SYSTEM_TIME, GPS week/ms, time_utc_usec): "
                         "KrakenSDR's Unix stamps cannot be put on its timeline (--unix-at-boot)")
    out, clock, said = Aligned(), ManualClock(None), {}
    time_map = _TimeMap(log.utc, time_offset_s)
    source = KrakenSource(sc.kraken, tuple(t.name for t in sc.targets), clock, log.history(), time_map, out.add,
                          lambda: sc.sensor.p_detect, lambda r, m: said.setdefault(r, m),
                          lambda: sc.sensor.clutter_rate)
    misses = {k: _Misses(w) for k, w in (("before", "before the pose record starts"),
                                         ("after", "after the pose record ends"), ("gap", "in a gap of the pose record"))}
    gaps = log.gaps()
    for _epoch, lines in frames:
        out.frames += 1
        t = time_map.autopilot_time(lines[0].line.measured_unix_s)
        where = _where(t, log, gaps)
        if where is not None:
            misses[where].add(lines[0].number, t)
            continue
        clock.t = t
        source.offer("doa", kl.ParsedDocument(tuple(r.line for r in lines)))
        source.tick(t)
        out.used += 1
    source.tick(math.inf)
    _finish(out, path, log, misses, [m for r, m in said.items() if r not in ("silent", "back", "late", "missed")])
    return out


def _finish(out: Aligned, path: str, log, misses: dict, refused: list[str]) -> None:
    """The notes, and the error when nothing aligned."""
    if not out.slots:
        first = min((m.times[0] for m in misses.values() if m.n), default=None)
        last = max((m.times[-1] for m in misses.values() if m.n), default=None)
        span = "" if first is None else f" (bearings at autopilot t {first:.1f}..{last:.1f} s)"
        raise AlignError(f"{path}: no bearing falls on the pose record of {log.path} "
                         f"(t {log.start:.1f}..{log.end:.1f} s){span}: another flight's log, or a clock "
                         "offset (--time-offset)?")
    out.notes += [n for m in misses.values() if (n := m.note(path))]
    out.notes += [f"{path}: {m}" for m in refused]
    for a, b in log.gaps():
        out.notes.append(f"{log.path}: no pose between autopilot t {a:.1f} and {b:.1f} s ({b - a:.1f} s)")
    ts = sorted(out.slots)
    for a, b in zip(ts, ts[1:]):
        if b - a > BEARING_GAP_S:
            out.notes.append(f"{path}: no bearing between autopilot t {a} and {b} s ({b - a} s): the filter "
                             "predicted across it")


def _datagrams(path: str, n_channels: int):
    """(line number, Datagram) of every datagram in a datagram or truth JSONL, each checked by
    the app's parser (onboard/app/df/datagram.py)."""
    with open_regular(path, MAX_BYTES) as f:
        for n, raw in enumerate(f, 1):
            if not raw.strip():
                continue
            try:
                obj = json.loads(raw)
            except (ValueError, RecursionError) as exc:
                raise AlignError(f"{path}:{n}: not JSON: {str(exc)[:80]}") from None
            if isinstance(obj, dict) and "header" in obj:
                continue
            if isinstance(obj, dict) and isinstance(obj.get("bearings"), list) and "t" in obj:  # a truth record
                raws = [dg.encode(obj["t"], ch, b) if _numbers(obj["t"], b) else json.dumps(obj).encode()
                        for ch, b in enumerate(obj["bearings"])]
            else:
                raws = [raw.strip()]
            for r in raws:
                try:
                    yield n, dg.parse(r, n_channels)
                except dg.DatagramError as exc:
                    raise AlignError(f"{path}:{n}: {exc}") from None


def _numbers(t, bearings) -> bool:
    ok = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool)  # noqa: E731
    return ok(t) and isinstance(bearings, list) and all(ok(b) for b in bearings)


def align_datagrams(path: str, sc, log, time_offset_s: float = 0.0) -> Aligned:
    """A datagram (or truth) JSONL at ``path`` on the pose log ``log``: each datagram's bearings
    in the slot of its nearest whole second, measured at its own ``t``."""
    out = Aligned()
    misses = {k: _Misses(w) for k, w in (("before", "before the pose record starts"),
                                         ("after", "after the pose record ends"), ("gap", "in a gap of the pose record"))}
    gaps, seen, dup = log.gaps(), set(), 0
    for n, d in _datagrams(path, len(sc.targets)):
        t = d.t + time_offset_s
        where = _where(t, log, gaps)
        if (t, "time") not in seen:
            seen.add((t, "time"))
            out.frames += 1
            if where is not None:
                misses[where].add(n, t)
        if where is not None:
            continue
        slot = int(round(t))
        if d.ch in out.slots.get(slot, {}):
            dup += 1
            continue
        out.add(KrakenScan(float(slot), d.ch, np.asarray(d.bearings), None, t))
    out.used = out.frames - sum(m.n for m in misses.values())
    refused = [f"{dup} datagram(s) for a second and channel already held (duplicate): not used"] if dup else []
    _finish(out, path, log, misses, refused)
    return out


def align(path: str | os.PathLike, sc, log, time_offset_s: float = 0.0) -> Aligned:
    """The recording at ``path`` (KrakenSDR's or datagrams, found from its first line) aligned."""
    path = os.fspath(path)
    try:
        kind = kind_of(path)
        fn = align_datagrams if kind == "datagram" else align_kraken
        return fn(path, sc, log, time_offset_s)
    except AlignError:
        raise
    except ValueError as exc:  # onboard.files.FileRefused
        raise AlignError(str(exc)) from None
