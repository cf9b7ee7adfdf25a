"""KrakenSDR's "Kraken App" DoA line: parsing, total and strict. See docs/KRAKENSDR.md.

KrakenSDR's DSP software (krakenrf/krakensdr_doa, ``_sdr/_signal_processing/
kraken_sdr_signal_processor.py``, ``SignalProcessor.run``) writes, for every VFO above its
squelch and every processed frame, one line

    EPOCH_MS, DOA, CONF, POWER_DB, FREQ_HZ, ARRAY, LATENCY_MS, STATION, LAT, LON, HEADING,
    HEADING, GPS, R, R, R, R, S0, S1, ..., S359 \\n

(17 fields, then the 360-bin DoA spectrum: ``DOA_plot_util`` of the estimator's output, i.e.
10 log10 of it normalised to its maximum, floored at -100 dB, shifted up by its minimum,
``{:.2f}``; bin i is the unit-circle angle i degrees). Every line of a frame has the frame's
time stamp: the DAQ's end-of-frame time, Unix ms; LATENCY_MS is the frame's acquisition time
(``daq_cpi``), so the DoA is of the frame's middle, ``EPOCH_MS - LATENCY_MS / 2``. The file
(``_share/DOA_value.html``, served on port 8081) is rewritten in place each frame.

``parse_line`` turns one line (without its newline) into a ``KrakenLine`` or raises
``LineError`` whose ``reason`` is one of ``REASONS`` and whose message names the field and
shows at most ``SHOW_CHARS`` of the bad value. Numbers are matched by pattern before they are
converted: Python's ``float()`` reads "nan", "inf", "1_0" and " 1", none of which KrakenSDR
writes. Nothing here touches sockets, clocks or the vehicle.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from onboard.core.doa import SPECTRUM_BINS

HEADER_FIELDS = 17
MAX_LINE_BYTES = 8192  # a line KrakenSDR writes is ~3 kB (360 values of at most 6 characters)
MAX_LINES = 16  # KrakenSDR's max_vfos: a document has at most one line per VFO
MAX_DOC_BYTES = MAX_LINES * (MAX_LINE_BYTES + 1)
SHOW_CHARS = 24

REASONS = (
    "too_long", "not_utf8", "truncated", "field_count", "spectrum_length", "bad_number",
    "not_finite", "out_of_range", "format_version", "too_many_lines",
)

_NUMBER = re.compile(r"[+-]?(?:\d{1,24}(?:\.\d{0,24})?|\.\d{1,24})(?:[eE][+-]?\d{1,4})?")
_INTEGER = re.compile(r"[+-]?\d{1,19}")
_SPECTRUM_CHARS = re.compile(r"[0-9eE+\-., ]*")
_NONFINITE = re.compile(r"nan|inf", re.IGNORECASE)
_ARRAY_WORDS = ("UCA", "ULA", "Custom", "VULA")


class LineError(ValueError):
    def __init__(self, reason: str, detail: str):
        assert reason in REASONS, reason
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True, eq=False)
class KrakenLine:
    epoch_ms: int  # Unix ms, end of the frame (the DAQ's time stamp)
    doa_deg: float  # main DoA as written: unit-circle or compass, by software version
    confidence: float  # peak-to-average of the DoA spectrum, dB (``calculate_doa_papr``)
    power_db: float  # the VFO channel's power, dB (its maximum in the FFT, floored at -100)
    freq_hz: int  # the VFO's frequency
    array: str  # UCA, ULA, Custom
    latency_ms: int  # acquisition time of the frame
    station: str
    lat_deg: float  # KrakenSDR's own GPS (0 without one); not used: the autopilot's pose is
    lon_deg: float
    heading_deg: float  # its GPS course or fixed heading; not used: the array turns with the vehicle
    spectrum: np.ndarray | None  # (360,) dB, unit-circle bins; None when the line has none

    @property
    def measured_unix_s(self) -> float:
        """The middle of the frame's acquisition, Unix s."""
        return self.epoch_ms / 1000.0 - self.latency_ms / 2000.0


def _show(text: str) -> str:
    return repr(text) if len(text) <= SHOW_CHARS - 2 else repr(text[:SHOW_CHARS - 5]) + "..."


def _number(tok: str, what: str, lo: float, hi: float) -> float:
    if not _NUMBER.fullmatch(tok):
        if _NONFINITE.search(tok):
            raise LineError("not_finite", f"{what}={_show(tok)}")
        raise LineError("bad_number", f"{what}={_show(tok)} is not a number")
    v = float(tok)  # at most 24+24 digits and a 4-digit exponent: inf at worst, never an error
    if not np.isfinite(v):
        raise LineError("not_finite", f"{what}={_show(tok)}")
    if not lo <= v <= hi:
        raise LineError("out_of_range", f"{what}={_show(tok)} not in [{lo:g}, {hi:g}]")
    return v


def _integer(tok: str, what: str, lo: int, hi: int) -> int:
    if not _INTEGER.fullmatch(tok):
        if _NONFINITE.search(tok):
            raise LineError("not_finite", f"{what}={_show(tok)}")
        if _NUMBER.fullmatch(tok):
            raise LineError("bad_number", f"{what}={_show(tok)} is not an integer")
        raise LineError("bad_number", f"{what}={_show(tok)} is not a number")
    v = int(tok)  # at most 19 digits
    if not lo <= v <= hi:
        raise LineError("out_of_range", f"{what}={_show(tok)} not in [{lo}, {hi}]")
    return v


def _text(tok: str, what: str, max_len: int = 64) -> str:
    if len(tok) > max_len:
        raise LineError("out_of_range", f"{what} of {len(tok)} characters > {max_len}")
    return tok


def _spectrum(fields: list[str]) -> np.ndarray:
    text = ",".join(fields)
    if not _SPECTRUM_CHARS.fullmatch(text):
        if _NONFINITE.search(text):
            raise LineError("not_finite", "spectrum holds a NaN or inf")
        raise LineError("bad_number", "spectrum holds a value that is not a number")
    for i, tok in enumerate(fields):  # the characters are right; each value must be a number
        if not _NUMBER.fullmatch(tok):
            raise LineError("bad_number", f"spectrum[{i}]={_show(tok)} is not a number")
    s = np.array([float(t) for t in fields])
    if not np.isfinite(s).all():
        raise LineError("not_finite", "spectrum holds a value too large for a float")
    if np.abs(s).max() > 1e4:
        raise LineError("out_of_range", "spectrum value beyond +-1e4 dB")
    s.setflags(write=False)
    return s


def format_of(doc: bytes) -> str | None:
    """A one-line name of another of KrakenSDR's output formats when ``doc`` is one (its XML for
    df-aggregator or the Kerberos app, JSON), else None."""
    head = doc.lstrip()[:1]
    if head == b"<":
        return ("XML (KrakenSDR's 'DF Aggregator' or 'Kerberos App' output): set its DoA Data Format "
                "to 'Kraken App'")
    if head in (b"{", b"["):
        return "JSON (KrakenSDR's 'Kraken Pro' output): set its DoA Data Format to 'Kraken App'"
    return None


def split_document(doc: bytes) -> tuple[list[bytes], bytes | None]:
    """The complete lines of a document (each ended by a newline, which is removed) and its
    unterminated tail (None if it ends with a newline). Blank lines are dropped."""
    parts = doc.split(b"\n")
    tail = parts.pop()
    lines = [p for p in parts if p.strip()]
    return lines, (tail if tail.strip() else None)


def parse_line(raw: bytes) -> KrakenLine:
    """One "Kraken App" line (bytes, without its newline)."""
    if len(raw) > MAX_LINE_BYTES:
        raise LineError("too_long", f"{len(raw)} bytes > {MAX_LINE_BYTES}")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise LineError("not_utf8", f"byte {exc.start} is not UTF-8") from None
    fields = [f.strip() for f in text.split(",")]
    n = len(fields)
    if n == 7 + SPECTRUM_BINS and fields[5] in _ARRAY_WORDS:
        raise LineError("format_version", "7 fields before the spectrum: an older KrakenSDR line; this app "
                                          "reads the 17-field 'Kraken App' line")
    if n < HEADER_FIELDS:
        raise LineError("field_count", f"{n} fields, a 'Kraken App' line has {HEADER_FIELDS} "
                                       f"(+ {SPECTRUM_BINS} spectrum values)")
    bins = n - HEADER_FIELDS
    if bins not in (0, SPECTRUM_BINS):
        raise LineError("spectrum_length", f"spectrum of {bins} values, want {SPECTRUM_BINS}")
    epoch = _integer(fields[0], "epoch_ms", 10**12, 10**14 - 1)
    doa = _number(fields[1], "doa", 0.0, 360.0)
    conf = _number(fields[2], "confidence", 0.0, 1e3)
    power = _number(fields[3], "power_db", -300.0, 100.0)
    freq = _number(fields[4], "freq_hz", 1e6, 1e11)
    array = _text(fields[5], "array")
    latency = _integer(fields[6], "latency_ms", 0, 60_000)
    station = _text(fields[7], "station")
    lat = _number(fields[8], "latitude", -90.0, 90.0)
    lon = _number(fields[9], "longitude", -180.0, 180.0)
    heading = _number(fields[10], "heading", -360.0, 720.0)
    _number(fields[11], "compass heading", -360.0, 720.0)
    for i in range(12, HEADER_FIELDS):  # heading source and reserved fields: words
        _text(fields[i], f"field {i + 1}", 16)
    spectrum = _spectrum(fields[HEADER_FIELDS:]) if bins else None
    return KrakenLine(epoch, doa, conf, power, int(round(freq)), array, latency, station, lat, lon, heading,
                      spectrum)



@dataclass(frozen=True, eq=False)
class RecordedLine:
    number: int  # the line's number in its recording, from 1
    raw: bytes  # as written, without its newline
    line: KrakenLine


class RecordingError(ValueError):
    """A recording's bad line: its ``number`` and the ``LineError``."""

    def __init__(self, number: int, error: LineError):
        super().__init__(f"{number}: {error}")
        self.number = number
        self.error = error


def recording_frames(raws: Iterable[bytes]) -> list[tuple[int, list[RecordedLine]]]:
    """The frames of a KrakenSDR recording (its data recording ``mydata.csv``, or ``DOA_value.html``
    documents one after another), given its lines (bytes, newline or not): [(time stamp ms,
    [RecordedLine, ...])] in file order, consecutive lines of one stamp one frame; blank lines
    skipped. Every line is checked by ``parse_line``; the first bad one raises ``RecordingError``."""
    frames: list[tuple[int, list[RecordedLine]]] = []
    for n, raw in enumerate(raws, 1):
        raw = raw.rstrip(b"\r\n")
        if not raw.strip():
            continue
        try:
            line = parse_line(raw)
        except LineError as exc:
            raise RecordingError(n, exc) from None
        rec = RecordedLine(n, raw, line)
        if frames and frames[-1][0] == line.epoch_ms:
            frames[-1][1].append(rec)
        else:
            frames.append((line.epoch_ms, [rec]))
    return frames


@dataclass(frozen=True, eq=False)
class ParsedDocument:
    """A document's good lines and, for each bad one, (reason, detail, count)."""

    lines: tuple[KrakenLine, ...] = ()
    errors: tuple[tuple[str, str, int], ...] = field(default_factory=tuple)


def parse_document(doc: bytes, max_lines: int = MAX_LINES * 4) -> ParsedDocument:
    """Every line of a document (KrakenSDR writes one per VFO; at most ``max_lines`` are parsed,
    the rest counted ``too_many_lines``), an unterminated tail is ``truncated``, another of
    KrakenSDR's output formats is ``format_version``. Pure: the poller's thread runs it, so a
    hostile document costs the io thread nothing but its result."""
    other = format_of(doc)
    if other is not None:
        return ParsedDocument((), (("format_version", other, 1),))
    raws, tail = split_document(doc)
    errors = []
    if tail is not None:
        errors.append(("truncated", f"a line of {len(tail)} bytes without its end (newline)", 1))
    if len(raws) > max_lines:
        errors.append(("too_many_lines", f"{len(raws)} lines in one document; read the first {max_lines}",
                       len(raws) - max_lines))
        raws = raws[:max_lines]
    lines = []
    for raw in raws:
        try:
            lines.append(parse_line(raw))
        except LineError as err:
            errors.append((err.reason, err.detail, 1))
    return ParsedDocument(tuple(lines), tuple(errors))
