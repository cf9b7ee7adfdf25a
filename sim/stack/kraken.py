"""A simulated KrakenSDR: the truth world's bearings written exactly as KrakenSDR writes them.

KrakenSDR (krakenrf/krakensdr_doa, ``SignalProcessor.run`` and ``save_processing_status``)
rewrites, each frame, ``_share/DOA_value.html`` (one "Kraken App" CSV line per VFO above its
squelch: onboard/app/kraken/line.py) and ``_share/status.json``, in place, and serves
``_share`` over HTTP on port 8081. ``KrakenWriter`` does the same (the same file operations, so
a reader can catch a document mid-rewrite as it can KrakenSDR's) and serves the folder on
127.0.0.1 with Python's HTTP server; ``KrakenFeed`` is ``pmon feed live`` writing that instead
of datagrams (``pmon feed live --df kraken``).

What a frame holds, per target channel (``KrakenModel``):

* the DF model's scan (sim/truth/sensors.py ``df_scan_labelled``: the same draws as the datagram
  feed's, so a seed gives the same bearings either way): the target's bearing with
  probability p_D and noise sigma, Poisson(Lambda) clutter bearings;
* as a DoA spectrum over KrakenSDR's 360 unit-circle bins, seen from the array on the vehicle
  (heading from the telemetry at the scan time, ``mount_offset``): a lobe (Gaussian, ``lobe_deg``)
  at the target's bearing, and with ``multipath`` a lobe at each clutter bearing, of a power
  drawn relative to the direct path's (``multipath_db``: a reflection can be stronger than a
  shadowed direct path), over a smooth noise floor (``floor_db``, ripple of ``ripple_db``);
  without ``multipath`` the clutter bearings are drawn (the stream stays the datagram feed's)
  but not written;
* KrakenSDR's main DoA (the spectrum's argmax on its 1-degree grid, written unit-circle or, as
  other versions of its software do, compass), its confidence (the spectrum's peak-to-average,
  ``calculate_doa_papr``), a channel power, the frame's latency, its own position and GPS
  heading fields; no line for a channel with nothing in its spectrum (below KrakenSDR's squelch),
  and no new document when no channel has one (KrakenSDR then writes nothing).

A frame is measured at each whole second T of autopilot time (as the datagram feed's scans):
its time stamp is the end of its acquisition, ``T + latency / 2``, in Unix ms through the
autopilot's UTC (SYSTEM_TIME).
"""
from __future__ import annotations

import json
import math
import os
import threading
import time
from dataclasses import dataclass
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

from onboard.app.kraken.line import KrakenLine
from onboard.core import doa
from onboard.settings import ConfigError
from sim.stack.live_feed import LiveFeed, LiveFeedConfig, Telemetry

DOC_NAME = "DOA_value.html"
STATUS_NAME = "status.json"
MIN_SPEED_FOR_HEADING = 2.0  # m/s: KrakenSDR takes the GPS course as heading above this ...
MIN_DURATION_FOR_HEADING = 3.0  # ... held this long (krakensdr_doa MIN_SPEED_/MIN_DURATION_FOR_VALID_HEADING)
# a feed that fell behind (its process descheduled) holds its next frame until the newest one was
# the document this long (autopilot s) and, once a reader reads it, was read READS_TO_TAKE times
# (the app takes a document two equal reads give), holding at most MIN_SHOWN_S: else it wrote the
# overdue frame and the due one back to back and the app (polling every 50 ms) lost the first
MIN_SHOWN_S = 0.5
READS_TO_TAKE = 2


@dataclass(frozen=True)
class KrakenModel:
    """How a simulated KrakenSDR renders the DF model's bearings."""

    lobe_deg: float = 4.0  # std of a source's lobe in the DoA spectrum
    floor_db: float = -25.0  # noise floor, relative to the direct path's peak
    ripple_db: float = 3.0  # the floor's smooth ripple, peak
    multipath: bool = True  # clutter bearings written as multipath lobes
    multipath_db: tuple[float, float] = (-10.0, 3.0)  # their power relative to the direct path, uniform
    power_db: float = -40.0  # channel power written (dB), +- 1 dB
    latency_ms: int = 436  # acquisition time of a frame: 2^20 samples at 2.4 MHz
    convention: str = "unit_circle"  # the main DoA as written: unit_circle (krakensdr_doa main) | compass
    mount_offset_rad: float = 0.0  # the array's 0, clockwise from the vehicle's nose
    overdrive_every: int = 0  # flag every n-th frame's status.json with ADC overdrive (0: never)
    station: str = "pmon-sim"


def render_spectrum(theta_deg, power_rel, model: KrakenModel, rng: np.random.Generator) -> np.ndarray:
    """The linear DoA spectrum over the 360 unit-circle bins of lobes at ``theta_deg`` with
    powers ``power_rel`` over the model's noise floor."""
    bins = np.arange(doa.SPECTRUM_BINS, dtype=float)
    k = np.arange(1, 6)[:, None]  # a smooth floor: an estimator's output over 5 antennas has no fine ripple
    wave = (rng.normal(0.0, 1.0, (5, 1)) * np.cos(np.radians(bins) * k + rng.uniform(0, 2 * np.pi, (5, 1)))).sum(0)
    p = 10 ** ((model.floor_db + model.ripple_db * wave / max(np.abs(wave).max(), 1e-9)) / 10)
    for c, a in zip(np.atleast_1d(theta_deg), np.atleast_1d(power_rel)):
        p = p + a * np.exp(-0.5 * (doa.circular_distance_deg(bins, c) / model.lobe_deg) ** 2)
    return p


def plot_db(p: np.ndarray) -> np.ndarray:
    """What KrakenSDR writes of a spectrum: ``DOA_plot_util`` (normalised to its maximum,
    10 log10, floored at -100 dB) shifted up by its minimum (the writer's ``+ np.abs(np.min())``)."""
    db = np.maximum(10 * np.log10(np.abs(p) / np.abs(p).max()), -100.0)
    return db + np.abs(db.min())


def papr_db(p: np.ndarray) -> float:
    """KrakenSDR's confidence: ``calculate_doa_papr``, 10 log10(max / mean) of the spectrum."""
    return float(10 * np.log10(np.abs(p).max() / np.abs(p).mean()))


def format_line(ln: KrakenLine) -> str:
    """``ln`` as KrakenSDR's ``SignalProcessor.run`` writes it, its newline included: the field
    order, the ", " separators, the spectrum's ``{:.2f}``, the " \\n" end (the reader's
    ``KrakenLine``, written: ``parse_line`` reads it back)."""
    head = (f"{int(ln.epoch_ms)}, {ln.doa_deg}, {ln.confidence}, {ln.power_db}, {int(ln.freq_hz)}, {ln.array}, "
            f"{int(ln.latency_ms)}, {ln.station}, {ln.lat_deg}, {ln.lon_deg}, {ln.heading_deg}, {ln.heading_deg}, "
            "GPS, R, R, R, R")
    spectrum = () if ln.spectrum is None else ln.spectrum
    return head + "".join(", " + "{:.2f}".format(v) for v in spectrum) + " \n"


def status_json(epoch_ms: int, overdrive: bool = False, daq_ok: bool = True) -> str:
    """status.json as ``save_processing_status`` writes it (the fields a reader uses, and some)."""
    return json.dumps({"timestamp_ms": int(epoch_ms), "station_id": "pmon-sim", "hardware_id": "KrakenSDR",
                       "software_version": "sim", "gps_status": "Disabled",
                       "daq_status": {"daq_connected": True, "frame_sync": True, "sample_delay_sync": daq_ok,
                                      "iq_sync": daq_ok, "adc_overdrive": bool(overdrive)},
                       "daq_ok": bool(daq_ok)})


def frame_lines(epoch_ms: int, scans, freqs: dict[int, float], yaw_rad: float, model: KrakenModel,
                rng: np.random.Generator, gps: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> str:
    """The document of one frame: per channel with a VFO (``freqs``: channel -> Hz), its line,
    from ``scans`` (per channel: bearings in rad and the mask of the target's, as
    ``df_scan_labelled`` gives them). Channels with nothing to show have no line. Random draws
    (floor, multipath powers, channel power) from ``rng`` in channel order. ``gps``: KrakenSDR's
    own fix, (latitude deg, longitude deg, heading deg), as each line carries it."""
    lat, lon, heading_deg = gps
    out = []
    for ch, (bearings, is_target) in enumerate(scans):
        if ch not in freqs:
            continue
        keep = is_target | model.multipath
        lo, hi = model.multipath_db
        power = np.where(is_target, 1.0, 10 ** (rng.uniform(lo, hi, len(bearings)) / 10))
        chan_db = model.power_db + rng.uniform(-1.0, 1.0)
        if not keep.any():
            continue  # below the squelch: KrakenSDR writes no line for this VFO
        theta = doa.array_from_bearing(np.asarray(bearings)[keep], yaw_rad, model.mount_offset_rad)
        p = render_spectrum(theta, power[keep], model, rng)
        theta0 = float(np.argmax(p))  # DOA_theta[argmax]: its 1-degree grid
        main = theta0 if model.convention == "unit_circle" else 360.0 - theta0
        out.append(format_line(KrakenLine(epoch_ms, main, papr_db(p), round(chan_db, 4), int(freqs[ch]), "UCA",
                                          model.latency_ms, model.station, lat, lon, heading_deg, plot_db(p))))
    return "".join(out)


class _QuietHandler(SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass

    def do_GET(self):  # noqa: N802 (http.server's name)
        writer = getattr(self.server, "kraken_writer", None)
        frames = writer.frames if writer is not None else 0
        super().do_GET()
        if writer is not None and self.path.split("?")[0].endswith(DOC_NAME):
            with writer.lock:
                writer.served = max(writer.served, frames)  # the document of this many frames was read
                if frames == writer.frames:  # ... and no frame written since this read began
                    writer.newest_reads += 1


class KrakenWriter:
    """KrakenSDR's ``_share`` folder: DOA_value.html and status.json rewritten in place, served
    over HTTP (``serve``: (host, port), port 0 picks one; ``url`` then names the document)."""

    def __init__(self, folder: str | os.PathLike, serve: tuple[str, int] | None = None):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.doc_path, self.status_path = self.folder / DOC_NAME, self.folder / STATUS_NAME
        # opened once, rewritten in place each frame, as KrakenSDR's DOA_res_fd
        self._doc = open(self.doc_path, "w+")
        self.server: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None
        if serve is not None:
            handler = partial(_QuietHandler, directory=str(self.folder))
            self.server = ThreadingHTTPServer(serve, handler)
            self.server.kraken_writer = self
            self._thread = threading.Thread(target=self.server.serve_forever, name="kraken-http", daemon=True)
            self._thread.start()
        self.frames = 0
        self.served = 0  # frames written when the document was last read over HTTP
        self.newest_reads = 0  # reads over HTTP of the newest frame's document (begun after it was written)
        self.lock = threading.Lock()

    @property
    def url(self) -> str:
        if self.server is None:
            return str(self.doc_path)
        host, port = self.server.server_address[:2]
        return f"http://{host}:{port}/{DOC_NAME}"

    def write_status(self, status: str) -> None:
        with open(self.status_path, "w", encoding="utf-8") as f:
            f.write(status)

    def write(self, doc: str, status: str | None = None) -> None:
        if status is not None:  # KrakenSDR writes its status before processing the frame
            self.write_status(status)
        self._doc.seek(0)
        self._doc.write(doc)
        self._doc.truncate()
        self._doc.flush()
        with self.lock:
            self.frames += 1
            self.newest_reads = 0

    def close(self, linger_s: float = 3.0) -> None:
        """Stop serving, once the last frame's document has been read (KrakenSDR keeps serving it:
        a reader must not miss the last frame because the simulator ended), or ``linger_s``."""
        import time

        deadline = time.monotonic() + linger_s
        while self.server is not None and self.served < self.frames and time.monotonic() < deadline:
            time.sleep(0.01)
        if self.server is not None and self.frames:
            time.sleep(min(0.5, max(deadline - time.monotonic(), 0.0)))  # a reader reads twice (kraken_fetch)
        if self.server is not None:
            self.server.shutdown()
            self.server.server_close()
            self.server = None
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._doc.close()


class KrakenFeed(LiveFeed):
    """``pmon feed live`` as a KrakenSDR on the vehicle: the same truth world and DF draws as the
    datagram feed (same seed, same bearings), written as KrakenSDR's output each second."""

    def __init__(self, cfg: LiveFeedConfig, scenario, writer: KrakenWriter, model: KrakenModel = KrakenModel(),
                 log=print):
        super().__init__(cfg, scenario, log)
        if not scenario.kraken.vfos:
            raise ConfigError("kraken.vfos: none: which VFO frequency is which target? (docs/KRAKENSDR.md)")
        names = [t.name for t in scenario.targets]
        self.freqs = {names.index(v.target): v.freq_hz for v in scenario.kraken.vfos}
        self.writer, self.model = writer, model
        # its own stream (floor, multipath powers): the truth's and the DF's stay the datagram feed's
        self.render_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed, spawn_key=(2,)))
        self.heading_deg = 0.0  # KrakenSDR's GPS heading field
        self._moving_since: float | None = None
        self.skipped_no_time = 0
        self._shown_since: float | None = None  # autopilot s the newest frame was written
        self.held = 0  # frames held back (_hold)

    sent_unit = "KrakenSDR lines"

    def destination(self, dest) -> str:
        return self.writer.url

    def run(self) -> int:
        rc = super().run()
        self.log(f"feed: KrakenSDR: {self.writer.frames} frames written, {self.skipped_no_time} scans without "
                 f"the autopilot's UTC or heading, {self.held} held to keep the one before shown "
                 f"{MIN_SHOWN_S:g} s (the feed fell behind)")
        return rc

    def scan(self, T, states, uav, tel: Telemetry):
        from sim.truth.sensors import df_scan_labelled

        labelled = df_scan_labelled(states[:, :2], uav[:2], self.df, self.rng)
        self._frame(T, labelled, uav, tel)
        # the truth record's bearings: those the spectrum shows
        return tuple(b[m | self.model.multipath] for b, m in labelled)

    def deliver(self, T, bearings, sock, dest) -> None:
        pass  # written in scan(): KrakenSDR has nothing to send

    def _gps_heading(self, T: float, tel: Telemetry) -> float:
        pose = tel.poses.latest()
        if pose is None:
            return self.heading_deg
        speed = float(np.hypot(pose.vel[0], pose.vel[1]))
        if speed >= MIN_SPEED_FOR_HEADING:
            self._moving_since = T if self._moving_since is None else self._moving_since
            if T - self._moving_since >= MIN_DURATION_FOR_HEADING:
                self.heading_deg = round(math.degrees(math.atan2(pose.vel[0], pose.vel[1])) % 360.0, 1)
        else:
            self._moving_since = None
        return self.heading_deg

    def _frame(self, T: float, labelled, uav, tel: Telemetry) -> None:
        yaw = tel.poses.yaw_at(T)
        unix = tel.utc.unix_time(T)
        if yaw is None or unix is None:
            self.skipped_no_time += 1
            return
        epoch = int(round(unix * 1000.0 + self.model.latency_ms / 2.0))  # the end of the acquisition
        lat, lon, _ = self.frame.geodetic_from_enu(uav)
        doc = frame_lines(epoch, labelled, self.freqs, yaw, self.model, self.render_rng,
                          (round(lat, 7), round(lon, 7), self._gps_heading(T, tel)))
        if not doc:
            return  # no VFO above the squelch: KrakenSDR writes nothing
        every = self.model.overdrive_every
        over = bool(every) and (self.writer.frames + 1) % every == 0
        self._hold(tel.clock)
        self.writer.write(doc, status_json(epoch, overdrive=over))
        self._shown_since = tel.clock.now()
        self.sent += doc.count("\n")

    def _hold(self, clock) -> None:
        """Keep the newest frame the document before writing the next (``MIN_SHOWN_S``,
        ``READS_TO_TAKE``). A KrakenSDR is a device of its own that writes a frame per acquisition
        and processing, never two at once; this simulator, descheduled past a frame's time (a
        loaded machine), would write that frame late and the next one, then due too, right after
        it, or write a frame just before it was descheduled (its server with it) and the next one
        as it woke: the document, which holds the newest frame only, was readable for
        milliseconds, too short for a reader polling every 50 ms. The held frame keeps its own
        time stamp (its measurement's)."""
        start = clock.now()
        w = self.writer
        readers = w.server is not None and w.served > 0  # someone reads the document over HTTP
        held = False
        while self._shown_since is not None and start is not None and not self.stop_event.is_set():
            now = clock.now()
            if now is None or now < self._shown_since or now >= start + MIN_SHOWN_S:
                break  # (a clock gone back, a reboot: not held; nor longer than MIN_SHOWN_S)
            if now >= self._shown_since + MIN_SHOWN_S and (not readers or w.newest_reads >= READS_TO_TAKE):
                break
            held = True
            time.sleep(0.002)
        self.held += held


# ----------------------------------------------------------------------------- pmon feed live --df kraken
def add_feed_arguments(p) -> None:
    """``pmon feed live`` options of the KrakenSDR mode (sim/stack/feed.py)."""
    from onboard.argcheck import HOST_PORT_BIND

    p.add_argument("--df", choices=("datagram", "kraken"), default="datagram",
                   help="datagram (default: DF datagrams to --to) or kraken: write KrakenSDR's output "
                        "(DOA_value.html, status.json) and serve it over HTTP (docs/KRAKENSDR.md)")
    p.add_argument("--kraken-dir", metavar="DIR", help="kraken: the folder written (default: a temporary one)")
    p.add_argument("--kraken-http", type=HOST_PORT_BIND, default=("127.0.0.1", 0), metavar="HOST:PORT",
                   help="kraken: serve the folder here (default 127.0.0.1:0, a free port; the URL is printed)")
    p.add_argument("--multipath", choices=("on", "off"), default="on",
                   help="kraken: the DF model's clutter written as multipath peaks (on) or only the target's "
                        "peak (off)")


def feed_from_args(args, sc, cfg: LiveFeedConfig, log=print) -> tuple[KrakenFeed, KrakenWriter]:
    """The KrakenSDR feed ``pmon feed live --df kraken`` runs; the writer to close after it."""
    import tempfile
    import time

    folder = args.kraken_dir or tempfile.mkdtemp(prefix="pmon-kraken-")
    writer = KrakenWriter(folder, serve=tuple(args.kraken_http))
    # its status from its start, as KrakenSDR's (written every frame its DAQ delivers, whether
    # or not a VFO is above the squelch): the app reads it from its own start
    writer.write_status(status_json(int(round(time.time() * 1000))))
    try:
        model = KrakenModel(multipath=args.multipath == "on",
                            mount_offset_rad=sc.kraken.mount_offset_rad)
        feed = KrakenFeed(cfg, sc, writer, model, log=log)
    except BaseException:
        writer.close()
        raise
    log(f"feed: KrakenSDR output at {writer.url}")
    return feed, writer


# ----------------------------------------------------------------------------- pmon feed replay --df kraken
def read_frames(path: str | os.PathLike) -> list[tuple[int, list[str]]]:
    """The frames of a KrakenSDR recording ("Kraken App" lines: its data recording, mydata.csv,
    or DOA_value.html documents one after another): [(time stamp ms, [line, ...])] in file
    order, consecutive lines of one stamp one frame. Every line is checked as the app checks it
    (onboard/app/kraken/line.py); a bad one is a ValueError naming its line."""
    from onboard.app.kraken import line as kl
    from onboard.files import open_regular

    with open_regular(path, 512 * 1024 * 1024) as f:
        try:
            frames = kl.recording_frames(f)
        except kl.RecordingError as exc:
            raise ValueError(f"{os.fspath(path)}:{exc.number}: {exc.error}") from None
    return [(epoch, [r.raw.decode("utf-8").rstrip() + " \n" for r in lines]) for epoch, lines in frames]


def replay_frames(frames, writer: KrakenWriter, unix_now, stop: threading.Event, speedup: float = 1.0,
                  log=print) -> int:
    """Write recorded frames as KrakenSDR would, each when its time comes, their stamps moved so
    that the first is written 1 s from now (``unix_now()``: Unix s on the clock the app maps
    KrakenSDR's stamps with: the autopilot's UTC or this computer's); ``speedup``: recorded
    seconds per second. Returns the frames written. The bearings are the recording's, relative
    to the array: a replay tests the input path and its timing, not the geometry of this flight."""
    import time

    if not frames:
        log("replay: no frames")
        return 0
    first = frames[0][0]
    start = unix_now() + 1.0
    done = 0
    for epoch, lines in frames:
        due = start + (epoch - first) / 1000.0 / speedup
        while not stop.is_set() and unix_now() < due:
            time.sleep(0.002)
        if stop.is_set():
            break
        stamp = int(round(due * 1000.0))
        writer.write("".join(str(stamp) + line[line.index(","):] for line in lines), status_json(stamp))
        done += 1
    log(f"replay: wrote {done} KrakenSDR frames to {writer.url}")
    return done


def add_replay_arguments(p) -> None:
    """``pmon feed replay`` options of the KrakenSDR mode (sim/stack/feed.py)."""
    from onboard.argcheck import HOST_PORT_BIND

    p.add_argument("--df", choices=("datagram", "kraken"), default="datagram",
                   help="datagram (default) or kraken: FILE is a KrakenSDR recording ('Kraken App' lines) "
                        "written back as KrakenSDR's output and served (docs/KRAKENSDR.md)")
    p.add_argument("--kraken-dir", metavar="DIR", help="kraken: the folder written (default: a temporary one)")
    p.add_argument("--kraken-http", type=HOST_PORT_BIND, default=("127.0.0.1", 0), metavar="HOST:PORT",
                   help="kraken: serve the folder here (default 127.0.0.1:0; the URL is printed)")


def replay_from_args(args, stop: threading.Event, log=print) -> int:
    """``pmon feed replay FILE --df kraken``: with ``--mavlink`` on the autopilot's UTC, else on
    this computer's clock at ``--speedup``."""
    import tempfile
    import time

    frames = read_frames(args.file)
    writer = KrakenWriter(args.kraken_dir or tempfile.mkdtemp(prefix="pmon-kraken-"), serve=tuple(args.kraken_http))
    tel = None
    try:
        log(f"feed: KrakenSDR output at {writer.url}")
        if args.mavlink:
            from onboard.app.autopilot.pose import Frame
            tel = Telemetry(args.mavlink, Frame(0, 0, 0)).start()
            while not stop.is_set() and (tel.clock.now() is None or tel.utc.unix_time(0.0) is None):
                time.sleep(0.01)

            def unix_now() -> float:
                return tel.utc.unix_time(tel.clock.now() or 0.0) or time.time()
            return replay_frames(frames, writer, unix_now, stop, 1.0, log)
        return replay_frames(frames, writer, time.time, stop, args.speedup, log)
    finally:
        if tel is not None:
            tel.stop()
        writer.close()
