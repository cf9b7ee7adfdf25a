"""KrakenSDR's DoA output as the app's DF input: documents in, one scan per target and second out.

Read by ``DocumentPoller`` (onboard/app/kraken/fetch.py), parsed here on the io thread:

1. **Lines** (onboard/app/kraken/line.py): a bad line is dropped, counted by reason, the first
   of each reason reported (STATUSTEXT and log). The other lines of its document are used.
2. **Frames.** The lines of one document with one time stamp are a frame (KrakenSDR writes one
   frame per document). A VFO's line is a target's by its frequency (``kraken.vfos``,
   ``freq_tol_hz``); another frequency is ``unknown_vfo``. Its time: the middle of the frame's
   acquisition (``epoch - latency / 2``, Unix s) in autopilot s, through the autopilot's own
   UTC (SYSTEM_TIME: ``UtcMap``, onboard/app/autopilot/clock.py) or this computer's clock (``time_source: host``); a frame more
   than ``MAX_FUTURE_S`` ahead of the autopilot clock or ``MAX_AGE_S`` behind it is refused.
3. **Slots.** The filter steps dt = 1 s per tick, KrakenSDR frames come at its own rate (a
   frame per ~0.4-1 s). Each frame falls in the slot of the nearest whole autopilot second; a
   slot is filled by its frame nearest that second (others are ``decimated``), and is ticked at
   that second (``t``) with the vehicle's pose at the frame's own time (``t_measured``,
   onboard/app/df/pairing.py).
4. **Measurements** (onboard/core/doa.py): per target, the spectrum's peaks above the floor as
   the measurement set (``measurements: peaks``; the main DoA alone without a spectrum or with
   ``main``), empty when the line is gated (confidence, power, or the frame's status.json
   flags ADC overdrive or DAQ not in sync), turned into bearings with the vehicle's heading at
   the frame's time (the pose history), the array's ``mount_offset``; and the clutter rate the
   peaks show over the last ``clutter_window`` scans (``clutter: adaptive``).
"""
from __future__ import annotations

import json
import math
import statistics
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from onboard.app.kraken import line as kl
from onboard.app.autopilot.clock import HostTime
from onboard.app.context import AppContext
from onboard.app.df.datagram import MAX_AGE_S, MAX_FUTURE_S, Datagram, DatagramError, ScanBuffer
from onboard.app.kraken.fetch import DocumentPoller, status_url_for
from onboard.app.mavlink_connection import mavlink
from onboard.app.part import Job, Part
from onboard.core import doa
from onboard.settings import ConfigError

SLOT_EARLY_S = 0.05  # a frame this close before its slot's second closes the slot at once
SLOT_HOLD_S = 0.3  # a slot without such a frame waits this long after its half-second end
LATE_S = 1.0  # a frame arriving this long (autopilot s) after its time is reported as late
SILENT_S = 3.0  # autopilot s without a new frame: reported (KrakenSDR writes nothing below squelch)
SEEN_FRAMES = 64  # frame time stamps remembered (a re-read of the same frame is not used twice)
STATUS_FRAMES = 64  # status.json entries remembered (frame time stamp -> flags)
MAIN_TOL_DEG = 2.0  # the main DoA and its spectrum's peak (1-degree grid, 0.01 dB rounding)
DOCS_PER_CALL = 4  # documents (parsed by the poller) handled per io-loop iteration

REASONS = kl.REASONS + (
    "unknown_vfo", "duplicate_vfo", "future_time", "stale_time", "no_time_reference", "no_heading",
    "convention_unknown", "doa_spectrum_mismatch", "status_invalid", "late_for_tick",
)
GATES = ("confidence", "power", "overdrive")


@dataclass(frozen=True, eq=False)
class KrakenScan(Datagram):
    """One target's measurement set from a KrakenSDR frame, ticked in the slot ``t``."""

    t_measured: float | None = None  # autopilot s of the frame (its pose is the vehicle's then)
    clutter_rate: float | None = None  # the clutter rate of this scan's likelihood (None: the filter's)


class KrakenSource:
    """Documents to scans (io thread). ``sink(scan, now)`` stores a scan (ScanBuffer.add);
    ``report(reason, message)`` is called the first time each reason is seen."""

    def __init__(self, cfg, target_names: tuple[str, ...], clock, poses, time_map,
                 sink: Callable[[Datagram, float | None], None], p_detect: Callable[[], float],
                 report: Callable[[str, str], None], clutter_floor: Callable[[], float] = lambda: 0.0):
        self.cfg = cfg
        self.clock, self.poses, self.time_map = clock, poses, time_map
        self.sink, self.p_detect, self.report = sink, p_detect, report
        self.clutter_floor = clutter_floor  # the filter's own clutter rate (clutter_min: null)
        self.vfo_freqs = np.array([v.freq_hz for v in cfg.vfos], float)
        self.vfo_channels = [target_names.index(v.target) for v in cfg.vfos]
        self.lines = 0  # lines parsed
        self.rejected = {r: 0 for r in REASONS}
        self.gated = {g: 0 for g in GATES}
        self.last_error: dict[str, str] = {}
        self.frames = self.decimated = self.repeated = self.scans = self.late_frames = 0
        self.convention: str | None = None if cfg.convention == "auto" else cfg.convention
        self._seen: OrderedDict[int, None] = OrderedDict()
        self._status: OrderedDict[int, tuple[bool, bool]] = OrderedDict()  # epoch -> (overdrive, daq_ok)
        self._pending: dict[int, tuple[float, list]] = {}  # slot -> (frame time, [(ch, line)])
        self._last_slot = -math.inf
        self._mapped = sorted(set(self.vfo_channels))  # channels with a VFO
        self._counts = {ch: deque(maxlen=cfg.clutter_window) for ch in self._mapped}
        self.last_frame_t: float | None = None  # autopilot s when the newest frame arrived
        self.missed = 0  # frames estimated lost between reads (_count_gap)
        self._last_epoch: int | None = None
        self._gaps: deque[int] = deque(maxlen=20)
        self._missed_said = False
        self.silent = False

    # ----------------------------------------------------------------- errors
    def reject(self, reason: str, detail: str, n: int = 1) -> None:
        self.rejected[reason] += n
        first = reason not in self.last_error
        self.last_error[reason] = detail
        if first:
            self.report(reason, f"bad KrakenSDR data: {reason}: {detail}")

    # ----------------------------------------------------------------- documents
    def offer(self, kind: str, doc) -> None:
        if kind == "status":
            self._on_status(doc)
        else:
            self._on_doa(doc)

    def _on_status(self, doc: bytes) -> None:
        """status.json: {"timestamp_ms": frame stamp, "daq_ok": bool, "daq_status":
        {"adc_overdrive": bool, ...}, ...} (krakensdr_doa's ``save_processing_status``)."""
        try:
            obj = json.loads(doc.decode("utf-8"))
            ts = obj["timestamp_ms"]
            daq = obj.get("daq_status", {})
            over, ok = daq.get("adc_overdrive", False), obj.get("daq_ok", True)
            if isinstance(ts, bool) or not isinstance(ts, int) or not isinstance(over, bool) \
                    or not isinstance(ok, bool):
                raise ValueError("timestamp_ms, daq_ok or adc_overdrive of the wrong type")
        except (ValueError, KeyError, TypeError, AttributeError, RecursionError) as exc:
            self.reject("status_invalid", f"status.json: {str(exc)[:60]}")
            return
        self._status[ts] = (over, ok)
        while len(self._status) > STATUS_FRAMES:
            self._status.popitem(last=False)

    def _on_doa(self, doc) -> None:
        """A document: its bytes, or already parsed (``line.parse_document``, which the
        poller's thread runs)."""
        parsed = doc if isinstance(doc, kl.ParsedDocument) else kl.parse_document(doc)
        for reason, detail, n in parsed.errors:
            self.reject(reason, detail, n)
        self.lines += len(parsed.lines)
        frames: dict[int, list] = {}
        for line in parsed.lines:
            frames.setdefault(line.epoch_ms, []).append(line)
        for epoch, lines in frames.items():
            self._on_frame(epoch, lines)

    # ----------------------------------------------------------------- frames and slots
    def _channel(self, freq_hz: float) -> int | None:
        d = np.abs(self.vfo_freqs - freq_hz)
        i = int(np.argmin(d))
        return self.vfo_channels[i] if d[i] <= self.cfg.freq_tol_hz else None

    def _on_frame(self, epoch: int, lines: list) -> None:
        if epoch in self._seen:  # the same frame read again (a rewritten but unchanged frame)
            self.repeated += 1
            return
        chans: list = []
        for line in lines:
            ch = self._channel(line.freq_hz)
            if ch is None:
                self.reject("unknown_vfo", f"{line.freq_hz} Hz is no target's VFO (kraken.vfos)")
            elif any(c == ch for c, _ in chans):
                self.reject("duplicate_vfo", f"two lines for target {ch + 1} in one frame")
            else:
                chans.append((ch, line))
        if not chans:
            return
        t = self.time_map.autopilot_time(lines[0].measured_unix_s)
        now = self.clock.now()
        if t is None or now is None:
            self.reject("no_time_reference", "no autopilot UTC yet (SYSTEM_TIME.time_unix_usec) or clock",
                        len(chans))
            return
        if t > now + MAX_FUTURE_S:
            self.reject("future_time", f"frame {t - now:.2f} s ahead of the autopilot clock", len(chans))
            return
        if t < now - MAX_AGE_S:
            self.reject("stale_time", f"frame {now - t:.2f} s old", len(chans))
            return
        # remembered once used, not before: a refused frame (a forgery stamped ahead) must not
        # shut out the genuine frame of the same stamp
        self._seen[epoch] = None
        while len(self._seen) > SEEN_FRAMES:
            self._seen.popitem(last=False)
        self.frames += 1
        self._count_gap(epoch)
        self.last_frame_t = now
        if self.silent:
            self.silent = False
            self.report("back", "KrakenSDR frames again")
        if now - t > LATE_S:
            self.late_frames += 1
            if self.late_frames == 1:
                self.report("late", f"KrakenSDR frames arrive {now - t:.1f} s after they were measured")
        slot = int(round(t))
        if slot < self._last_slot - MAX_AGE_S:  # within the clock's window yet far behind: the
            self._last_slot = -math.inf  # autopilot's clock went back (a reboot): a new timeline
            self._pending.clear()
        if slot <= self._last_slot:
            self.decimated += 1  # its second was ticked with a nearer frame
            return
        held = self._pending.get(slot)
        if held is not None:
            if abs(held[0] - slot) <= abs(t - slot):
                self.decimated += 1
                return
            self.decimated += 1
        self._pending[slot] = (t, chans, epoch)
        for s in sorted(k for k in self._pending if k < slot):
            self._emit(s)
        if t >= slot - SLOT_EARLY_S:  # no later frame can be nearer its second
            self._emit(slot)

    def _count_gap(self, epoch: int) -> None:
        """Frames KrakenSDR wrote that were never read: its document holds the newest frame only,
        so a reader that falls behind (a poll period too long, a starved computer) loses frames.
        Estimated from the gaps between frame stamps against their median (``missed``)."""
        if self._last_epoch is not None and epoch > self._last_epoch:
            gap = epoch - self._last_epoch
            if len(self._gaps) >= 5:
                typical = statistics.median(self._gaps)
                if gap > 1.6 * typical:
                    self.missed += int(round(gap / typical)) - 1
                    if not self._missed_said:
                        self._missed_said = True
                        self.report("missed", f"KrakenSDR frames written but not read (a {gap / 1000:.1f} s gap): "
                                              "the reader fell behind")
            self._gaps.append(gap)
        self._last_epoch = max(epoch, self._last_epoch or epoch)

    def tick(self, now: float | None) -> None:
        """Periodic (io thread): slots whose frames are all in; silence."""
        if now is None:
            return
        for s in sorted(k for k in self._pending if now >= k + 0.5 + SLOT_HOLD_S):
            self._emit(s)
        if self.last_frame_t is not None and not self.silent and now - self.last_frame_t > SILENT_S:
            self.silent = True
            self.report("silent", f"no new KrakenSDR frame for {SILENT_S:g} s (nothing above its squelch?)")

    def _emit(self, slot: int) -> None:
        t, chans, epoch = self._pending.pop(slot)
        self._last_slot = max(self._last_slot, slot)
        yaw = self.poses.yaw_at(t)
        over, ok = self._status.get(epoch, (False, True))
        flagged = self.cfg.reject_overdrive and (over or not ok)
        now = self.clock.now()
        present = {ch for ch, _ in chans}
        for ch, line in chans + [(c, None) for c in self._mapped if c not in present]:
            if line is None:  # its VFO below KrakenSDR's squelch in this frame: nothing detected
                bearings, rate = np.empty(0), self._rate(ch, 0)
            elif yaw is None:
                self.reject("no_heading", "no vehicle heading at the frame's time (GLOBAL_POSITION_INT.hdg)")
                bearings, rate = np.empty(0), None
            else:
                bearings, rate = self._measure(ch, line, yaw, flagged)
            bearings.setflags(write=False)
            try:
                self.sink(KrakenScan(float(slot), ch, bearings, None, t, rate), now)
            except DatagramError as err:
                self.reject("late_for_tick", f"scan of t={slot} after its tick ({err.reason})")
                continue
            self.scans += 1

    # ----------------------------------------------------------------- measurements
    def _gate(self, line, flagged: bool) -> str | None:
        if flagged:
            return "overdrive"
        if line.confidence < self.cfg.min_confidence:
            return "confidence"
        if line.power_db < self.cfg.min_power_db:
            return "power"
        return None

    def _track_convention(self, line) -> None:
        """``convention: auto``: the convention the line's main DoA is written in, read off its
        spectrum (kept until a line shows the other one, which is reported)."""
        if line.spectrum is None or self.cfg.convention != "auto":
            return
        seen = doa.detect_convention(line.doa_deg, line.spectrum)
        if seen is not None and seen != self.convention:
            if self.convention is not None:
                self.report("convention", f"KrakenSDR's main DoA is now written {seen}: its software changed?")
            self.convention = seen

    def _main_theta(self, line) -> float | None:
        """The main DoA as a unit-circle angle, or None when its convention is unknown."""
        self._track_convention(line)
        if self.convention is not None:
            return float(doa.unit_circle_deg(line.doa_deg, self.convention))
        if line.spectrum is not None:  # not learnt yet (main DoA at 0 or 180): the spectrum's own argmax
            return float(np.argmax(line.spectrum))
        self.reject("convention_unknown", "main DoA without a spectrum to tell unit-circle from compass "
                                          "(set kraken.convention)")
        return None

    def _measure(self, ch: int, line, yaw: float, flagged: bool) -> tuple[np.ndarray, float | None]:
        cfg = self.cfg
        gate = self._gate(line, flagged)
        if gate is not None:
            self.gated[gate] += 1
            return np.empty(0), None
        if cfg.measurements == "peaks" and line.spectrum is not None:
            self._track_convention(line)  # the spectrum's bins are unit-circle whatever the main DoA's
            angles, _ = doa.spectrum_peaks(line.spectrum, cfg.peak_floor_db, cfg.peak_prominence_db, cfg.max_peaks)
            if not self._main_among(line.doa_deg, angles):
                self.reject("doa_spectrum_mismatch", f"main DoA {line.doa_deg:g} is none of its spectrum's peaks "
                                                     "(a line mixing two frames?)")
                return np.empty(0), None
        else:
            theta = self._main_theta(line)
            angles = np.empty(0) if theta is None else np.array([theta])
        bearings = doa.bearing_from_array(angles, yaw, cfg.mount_offset_rad).reshape(-1)
        return bearings, self._rate(ch, len(bearings))

    def _main_among(self, doa_deg: float, angles: np.ndarray) -> bool:
        """Is the main DoA one of the peaks (in its convention, or either while unknown)? It is
        the estimator's maximum (or, ROOT-MUSIC, one of its roots): a line whose spectrum has no
        peak there mixes two frames (a read torn across KrakenSDR's rewrite) or two writers."""
        convs = (self.convention,) if self.convention else doa.CONVENTIONS
        return any(bool((doa.circular_distance_deg(angles, doa.unit_circle_deg(doa_deg, c)) <= MAIN_TOL_DEG).any())
                   for c in convs)

    def _rate(self, ch: int, n: int) -> float | None:
        """``clutter: adaptive``: the rate the last ``clutter_window`` sets of ``ch`` show, with
        this one's ``n``; else None (the filter's)."""
        if self.cfg.clutter != "adaptive":
            return None
        counts = self._counts[ch]
        counts.append(n)
        lo = self.cfg.clutter_min if self.cfg.clutter_min is not None else self.clutter_floor()
        return doa.clutter_rate(counts, self.p_detect(), min(lo, self.cfg.clutter_max), self.cfg.clutter_max)


class KrakenInput(Part):
    """The app's KrakenSDR input, one of its parts (onboard/app/app.py): the poller thread and the
    source. ``drain`` and ``periodic`` run on the io thread under the app lock. ``scenario``: its
    ``kraken`` section and targets; ``autopilot``: the autopilot side (its poses and UTC);
    ``scans``: the scan buffer the tick schedule takes from; ``ctx``: the app's clock, its
    parameters (PMON_PD and PMON_CLUTTER, the adaptive clutter's) and voice."""

    def __init__(self, ctx: AppContext, scenario, autopilot, scans: ScanBuffer):
        clock, params = ctx.clock, ctx.params
        cfg = scenario.kraken
        if not cfg.vfos:
            raise ConfigError("kraken.vfos: none: which VFO frequency is which target? (docs/KRAKENSDR.md)")
        self.url = cfg.url
        self.say = ctx.say
        try:
            self.poller = DocumentPoller(cfg.url, status_url_for(cfg.url, cfg.status_url), cfg.poll_s,
                                         prepare={"doa": kl.parse_document})
        except ValueError as exc:  # a URL the scenario's check let through
            raise ConfigError(f"kraken.url: {exc}") from None
        time_map = autopilot.utc if cfg.time_source == "autopilot" else HostTime(clock)
        self.source = KrakenSource(cfg, tuple(t.name for t in scenario.targets), clock, autopilot.poses,
                                   time_map, scans.add, lambda: params.settings.sensor.p_detect, self._report,
                                   lambda: params.settings.sensor.clutter_rate)
        self._down_said = self._status_said = self._restart_said = False
        self.handled = 0  # documents the io thread has handled

    def start(self) -> "KrakenInput":
        self.poller.start()
        return self

    def stop(self) -> None:
        self.poller.stop()

    def drain(self) -> None:
        for kind, doc, _local in self.poller.pop(DOCS_PER_CALL):
            try:
                self.source.offer(kind, doc)
            finally:
                self.handled += 1

    def jobs(self) -> tuple[Job, ...]:
        return (Job("periodic KrakenSDR", lambda local, now: self.periodic(now)),)

    def periodic(self, now: float | None) -> None:
        self.source.tick(now)
        down = self.poller.down.get("doa", False)
        if down and not self._down_said:
            self._down_said = True
            self._report("unreachable", f"KrakenSDR unreachable: {self.poller.last_error.get('doa')}")
        elif not down and self._down_said and self.poller.documents:
            self._down_said = False
            self._report("reachable", f"KrakenSDR {self.url} read again")
        if self.poller.restarts and not self._restart_said:
            self._restart_said = True  # once: poller.restarts counts the rest
            self._report("restart", f"KrakenSDR reader failed and was restarted ({self.poller.crash})")
        if self.poller.down.get("status", False) and not self._status_said:
            self._status_said = True  # its gates then see no overdrive: said once
            self._report("status", f"KrakenSDR status.json not read ({self.poller.last_error.get('status')}): "
                                   "ADC overdrive not gated")

    def status(self) -> dict[str, float]:
        """PMON_STAT's KrakenSDR fields (contract.STAT_FIELDS)."""
        s = self.source
        return {"kraken_frames": s.frames, "kraken_rejected": sum(s.rejected.values()),
                "kraken_gated": sum(s.gated.values())}

    def _report(self, reason: str, message: str) -> None:
        quiet = reason in ("back", "reachable")
        self.say(message, mavlink.MAV_SEVERITY_INFO if quiet else mavlink.MAV_SEVERITY_WARNING)
