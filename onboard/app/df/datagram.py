"""Direction-finder datagrams (DF -> onboard app): JSON over UDP, version 1. See docs/DATAGRAM.md.

One datagram carries one scan of one channel (= one target's receiver):

    {"v": 1, "t": 12.0, "ch": 0, "bearings_rad": [0.52, -2.9], "seq": 41}

Parsing is total: any input either gives a `Datagram` or raises `DatagramError` whose `reason`
is one of `REASONS` (the key under which the app counts it) and whose message names the field.
Numbers are checked without raising anything else: JSON integers are unbounded in Python, and
``float()`` / ``math.isfinite()`` raise OverflowError on one past ~1e308 (a 400-digit ``t`` or
bearing), so an integer is range-checked as an integer before it becomes a float. Messages show
at most ``SHOW_CHARS`` of a value. Nothing here touches sockets or clocks; the time window is
passed in.
"""
from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass

import numpy as np

VERSION = 1
MAX_BYTES = 4096
MAX_BEARINGS = 64  # per datagram: the DF model's clutter is Poisson(Lambda), Lambda <= ~10
MAX_FUTURE_S = 2.0  # a scan stamped later than the app's clock + this is rejected
MAX_AGE_S = 5.0  # ... and one older than the clock - this
SHOW_CHARS = 24  # of a bad value in a message

FIELDS = {"v", "t", "ch", "bearings_rad", "seq"}
REQUIRED = ("v", "t", "ch", "bearings_rad")

REASONS = (
    "too_large", "not_utf8", "not_json", "not_object", "bad_version", "missing_field",
    "unknown_field", "bad_type", "not_finite", "out_of_range", "unknown_channel",
    "too_many_bearings", "future_time", "stale_time", "duplicate",
)


class DatagramError(ValueError):
    def __init__(self, reason: str, detail: str):
        assert reason in REASONS, reason
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True, eq=False)
class Datagram:
    t: float  # autopilot time of the scan, s since autopilot boot
    ch: int  # channel = target index, 0-based
    bearings: np.ndarray  # rad, clockwise from north, each in (-pi, pi]
    seq: int | None = None


def _show(v) -> str:
    """A value for a message, cut to SHOW_CHARS (a 4000-digit integer must not fill the log)."""
    text = repr(v) if not isinstance(v, int) or abs(v) < 10 ** SHOW_CHARS else f"{str(v)[:8]}...({len(str(v))} digits)"
    return text if len(text) <= SHOW_CHARS else text[:SHOW_CHARS - 3] + "..."


def _real(v, what: str, lo: float, hi: float, lo_open: bool = False) -> float:
    """``v`` as a float in [lo, hi] (or (lo, hi]); DatagramError otherwise, never OverflowError:
    an integer is compared as an integer (exact, any size) before it is converted."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise DatagramError("bad_type", f"{what} must be a number, got {type(v).__name__}")
    if isinstance(v, float) and not math.isfinite(v):
        raise DatagramError("not_finite", f"{what} is not finite")
    if (v <= lo if lo_open else v < lo) or v > hi:
        span = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
        raise DatagramError("out_of_range", f"{what}={_show(v)} not in {span}")
    return float(v)


def _integer(obj: dict, key: str) -> int:
    v = obj[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise DatagramError("bad_type", f"{key} must be an integer, got {type(v).__name__}")
    return v


def _reject_constant(name: str):
    # json accepts NaN/Infinity literals by default; a DF must not send them
    raise DatagramError("not_finite", f"non-standard JSON constant {name}")


def parse(data: bytes, n_channels: int, now_s: float | None = None) -> Datagram:
    """Validate one datagram. ``now_s``: the app's autopilot-clock time (None skips the window)."""
    if len(data) > MAX_BYTES:
        raise DatagramError("too_large", f"{len(data)} bytes > {MAX_BYTES}")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DatagramError("not_utf8", f"byte {exc.start} is not UTF-8") from None
    try:
        obj = json.loads(text, parse_constant=_reject_constant)
    except DatagramError:
        raise
    except (ValueError, RecursionError) as exc:
        raise DatagramError("not_json", str(exc)[:80]) from None
    if not isinstance(obj, dict):
        raise DatagramError("not_object", f"top level is {type(obj).__name__}, want an object")
    for key in REQUIRED:
        if key not in obj:
            raise DatagramError("missing_field", f"{key} is missing")
    unknown = sorted(set(obj) - FIELDS)
    if unknown:
        raise DatagramError("unknown_field", f"unknown field {unknown[0]!r}")
    if _integer(obj, "v") != VERSION:
        raise DatagramError("bad_version", f"v={_show(obj['v'])}, this app reads v={VERSION}")
    t = _real(obj["t"], "t", 0.0, sys.float_info.max)
    ch = _integer(obj, "ch")
    if not 0 <= ch < n_channels:
        raise DatagramError("unknown_channel", f"ch={_show(ch)}, channels are 0..{n_channels - 1}")
    seq = None
    if "seq" in obj:
        seq = _integer(obj, "seq")
        if not 0 <= seq < 2**63:
            raise DatagramError("out_of_range", f"seq={_show(seq)} must be in [0, 2^63)")
    raw = obj["bearings_rad"]
    if not isinstance(raw, list):
        raise DatagramError("bad_type", f"bearings_rad must be a list, got {type(raw).__name__}")
    if len(raw) > MAX_BEARINGS:
        raise DatagramError("too_many_bearings", f"{len(raw)} bearings > {MAX_BEARINGS}")
    bearings = np.empty(len(raw))
    for i, b in enumerate(raw):
        bearings[i] = _real(b, f"bearings_rad[{i}]", -math.pi, math.pi, lo_open=True)
    if now_s is not None:
        if t > now_s + MAX_FUTURE_S:
            raise DatagramError("future_time", f"t={t:.3f} is {t - now_s:.2f} s ahead of the autopilot clock")
        if t < now_s - MAX_AGE_S:
            raise DatagramError("stale_time", f"t={t:.3f} is {now_s - t:.2f} s old")
    bearings.setflags(write=False)
    return Datagram(t, ch, bearings, seq)


def encode(t: float, ch: int, bearings, seq: int | None = None) -> bytes:
    """The datagram a DF (or the sim feed) sends; compact JSON, floats at full precision."""
    obj = {"v": VERSION, "t": round(float(t), 6), "ch": int(ch),
           "bearings_rad": [float(b) for b in bearings]}
    if seq is not None:
        obj["seq"] = int(seq)
    data = json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    if len(data) > MAX_BYTES:
        raise ValueError(f"datagram of {len(data)} bytes exceeds {MAX_BYTES}")
    return data


class ScanBuffer:
    """Datagrams grouped by scan time, waiting for their tick; counts every rejection by reason.

    A scan time is "complete" when every channel has arrived. A second datagram for the same
    (t, ch) is a duplicate: the first is kept (what was received is never replaced).
    Times are rounded to the millisecond to group the channels of one scan.
    """

    def __init__(self, n_channels: int):
        self.n_channels = n_channels
        self.pending: dict[float, dict[int, Datagram]] = {}
        self.accepted = 0
        self.rejected: dict[str, int] = {r: 0 for r in REASONS}
        self.last_error: dict[str, str] = {}  # reason -> last message (logged once per kind)
        self.consumed_until = -math.inf  # scans at or before this time were handed to a tick
        self.last_scan_t = [-math.inf] * n_channels
        self.last_arrival: float | None = None  # arrival of the newest scan take_until returned
        self.arrival: dict[float, float | None] = {}  # scan time -> clock at its newest datagram

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def reject(self, err: DatagramError) -> bool:
        """Count a rejection; True the first time this reason is seen (log it then)."""
        self.rejected[err.reason] += 1
        first = err.reason not in self.last_error
        self.last_error[err.reason] = str(err)
        return first

    def offer(self, data: bytes, now_s: float | None) -> Datagram:
        """Parse and store; raises DatagramError (already counted) when rejected."""
        try:
            d = parse(data, self.n_channels, now_s)
        except DatagramError as err:
            self.reject(err)
            raise
        return self.add(d, now_s)

    def add(self, d: Datagram, now_s: float | None) -> Datagram:
        """Store an already valid scan of one channel (another input's, e.g. KrakenSDR's:
        onboard/app/kraken/source.py); raises DatagramError (counted) for a stale time or a duplicate."""
        try:
            key = round(d.t, 3)
            if key <= self.consumed_until:
                raise DatagramError("stale_time", f"t={d.t:.3f} is at or before the last tick")
            slot = self.pending.setdefault(key, {})
            if d.ch in slot:
                raise DatagramError("duplicate", f"second datagram for t={d.t:.3f} ch={d.ch}")
        except DatagramError as err:
            self.reject(err)
            raise
        slot[d.ch] = d
        self.arrival[key] = now_s
        self.accepted += 1
        self.last_scan_t[d.ch] = max(self.last_scan_t[d.ch], d.t)
        return d

    def drop_pending(self) -> None:
        """Forget the scans waiting for a tick (stamped on a timeline the clock left)."""
        self.pending.clear()
        self.arrival.clear()

    def start_over(self) -> None:
        """The autopilot rebooted: its clock, which stamps the scans, starts again near zero."""
        self.drop_pending()
        self.consumed_until = -math.inf
        self.last_scan_t = [-math.inf] * self.n_channels

    def complete(self, key: float) -> bool:
        return len(self.pending.get(key, ())) == self.n_channels

    def earliest(self) -> float | None:
        return min(self.pending) if self.pending else None

    def take_until(self, t: float) -> list[tuple[float, dict[int, Datagram]]]:
        """Remove and return the scans with time <= t, oldest first."""
        keys = sorted(k for k in self.pending if k <= t)
        self.consumed_until = max(self.consumed_until, t)
        for k in keys:
            self.last_arrival = self.arrival.pop(k, None)
        return [(k, self.pending.pop(k)) for k in keys]
