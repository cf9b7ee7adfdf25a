"""KrakenSDR's DoA output as the app's DF (issue 32): its line, its angle convention pinned to
KrakenSDR's own code, heading and time, frames to one scan a second, gates, the measurement set.

The convention (docs/KRAKENSDR.md): krakenrf/krakensdr_doa's ``SignalProcessor.run`` sends its
main DoA, as it writes it in the "Kraken App" line (``theta_0``, the unit-circle angle, in the
current writer), to ``calculate_end_lat_lng(lat, lng, doa, heading)`` for its map output, which
draws the line of bearing at ``theta = heading + (360 - doa)`` degrees with the great-circle
destination formula (bearing clockwise from north). ``_krakens_line_of_bearing`` below is that
formula; the tests take the bearing of the end point it gives and require the app's bearing to
be it. The adapter's sign or zero flipped makes them fail (checked at the end).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from onboard.app.kraken import line as kl
from onboard.app.kraken.line import KrakenLine
from onboard.app.autopilot.clock import ManualClock, UtcMap
from onboard.app.df.datagram import ScanBuffer
from onboard.app.kraken.source import KrakenSource
from onboard.app.autopilot.pose import PoseHistory, PoseSample
from onboard.config import load_scenario
from onboard.core import doa
from onboard.core.bearings import bearing, wrap
from sim.stack.kraken import KrakenModel, format_line, frame_lines, plot_db, render_spectrum

SC = load_scenario("paper")
FREQS = {j: v.freq_hz for j, v in enumerate(SC.kraken.vfos)}
UNIX0 = 1_700_000_000.0  # the autopilot's boot, Unix s
LAT, LON = 35.1450, 33.4110
CLEAN = KrakenModel(multipath=False, ripple_db=0.0, floor_db=-40.0)


def _krakens_line_of_bearing(lat, lon, doa_deg, heading_deg):
    """KrakenSDR's ``calculate_end_lat_lng`` (kraken_sdr_signal_processor.py): from the station,
    100 km (its line_length, over its Earth radius 6372.795477598 km) along the bearing
    heading + (360 - doa) degrees clockwise from north. Returns the end point (lat, lon)."""
    R, d = 6372.795477598, 100.0
    theta = math.radians(heading_deg + (360.0 - doa_deg))
    p1, l1 = math.radians(lat), math.radians(lon)
    p2 = math.asin(math.sin(p1) * math.cos(d / R) + math.cos(p1) * math.sin(d / R) * math.cos(theta))
    l2 = l1 + math.atan2(math.sin(theta) * math.sin(d / R) * math.cos(p1), math.cos(d / R) - math.sin(p1) * math.sin(p2))
    return math.degrees(p2), math.degrees(l2)


def _initial_bearing(lat1, lon1, lat2, lon2) -> float:
    """Initial great-circle bearing (rad, clockwise from north) from (lat1, lon1) to (lat2, lon2):
    the inverse problem of KrakenSDR's destination formula, on the same sphere."""
    p1, l1, p2, l2 = map(math.radians, (lat1, lon1, lat2, lon2))
    y = math.sin(l2 - l1) * math.cos(p2)
    x = math.cos(p1) * math.sin(p2) - math.sin(p1) * math.cos(p2) * math.cos(l2 - l1)
    return math.atan2(y, x)


# ----------------------------------------------------------------------------- harness
class Rig:
    """A KrakenSource fed by hand: manual clock, a pose history with headings, the autopilot's
    UTC, scans into a ScanBuffer."""

    def __init__(self, cfg=None, yaw_deg: float = 0.0, yaw_error_deg: float = 0.0, t0: float = 100.0):
        self.cfg = cfg or SC.kraken
        self.clock = ManualClock(t0)
        self.poses = PoseHistory(keep_s=600.0)
        self.utc = UtcMap()
        for k in range(9):
            self.utc.observe(int((UNIX0 + 50.0 + k) * 1e6), int((50.0 + k) * 1e3))
        self.yaw = math.radians(yaw_deg)
        for k in range(int(t0 * 10) - 300, int(t0 * 10) + 600):  # 10 Hz, 30 s back, 60 s ahead
            self.poses.add(PoseSample(k / 10.0, np.array([150.0, 200.0, 40.0]), np.zeros(3),
                                      float(wrap(self.yaw + math.radians(yaw_error_deg)))))
        self.buffer = ScanBuffer(len(SC.targets))
        self.reports: list[tuple[str, str]] = []
        self.src = KrakenSource(self.cfg, tuple(t.name for t in SC.targets), self.clock, self.poses, self.utc,
                                self.buffer.add, lambda: SC.sensor.p_detect, lambda r, m: self.reports.append((r, m)),
                                lambda: SC.sensor.clutter_rate)

    def epoch(self, t: float, latency_ms: int = 436) -> int:
        return int(round((UNIX0 + t) * 1000 + latency_ms / 2))

    def scans(self) -> dict:
        out = {}
        for k, chans in self.buffer.pending.items():
            out[k] = chans
        return out


def _doc(rig: Rig, t: float, bearings_per_ch, model: KrakenModel = CLEAN, seed: int = 0) -> bytes:
    scans = [(np.asarray(b, float), np.arange(len(b)) == 0) for b in bearings_per_ch]
    return frame_lines(rig.epoch(t, model.latency_ms), scans, FREQS, rig.yaw, model,
                       np.random.default_rng(seed)).encode()


# ----------------------------------------------------------------------------- the line
def test_a_line_as_krakensdr_writes_it_parses_field_by_field():
    s = plot_db(render_spectrum([40.0], [1.0], CLEAN, np.random.default_rng(0)))
    text = format_line(KrakenLine(1712345678901, 40.0, 17.25, -42.5, 433200000, "UCA", 436, "NOCALL", 35.1, 33.4, 12.5, s))
    assert text.endswith(" \n") and text.count(",") == kl.HEADER_FIELDS + doa.SPECTRUM_BINS - 1
    line = kl.parse_line(text.encode()[:-1])
    assert (line.epoch_ms, line.doa_deg, line.confidence, line.power_db, line.freq_hz, line.array,
            line.latency_ms, line.station, line.lat_deg, line.lon_deg, line.heading_deg) == (
        1712345678901, 40.0, 17.25, -42.5, 433200000, "UCA", 436, "NOCALL", 35.1, 33.4, 12.5)
    assert line.spectrum.shape == (360,) and int(np.argmax(line.spectrum)) == 40
    assert line.measured_unix_s == pytest.approx(1712345678.901 - 0.218)
    assert not line.spectrum.flags.writeable
    # no spectrum at all: the main DoA alone
    head = text.split(", 0.")[0].split(", GPS")[0] + ", GPS, R, R, R, R"
    assert kl.parse_line(head.encode()).spectrum is None


# ----------------------------------------------------------------------------- the convention
def _app_bearing(doa_field: float, heading_deg: float, convention: str = "unit_circle",
                 measurements: str = "main") -> float:
    """The app's bearing (rad) of a line written with ``doa_field`` (in ``convention``) whose
    spectrum peaks at the unit-circle angle, with the vehicle heading ``heading_deg``."""
    theta = doa_field if convention == "unit_circle" else (360.0 - doa_field) % 360.0
    rig = Rig(replace(SC.kraken, measurements=measurements), yaw_deg=heading_deg)
    s = plot_db(render_spectrum([theta], [1.0], CLEAN, np.random.default_rng(1)))
    text = format_line(KrakenLine(rig.epoch(100.0), doa_field, 20.0, -40.0, FREQS[0], "UCA", 436, "X", LAT, LON,
                                  heading_deg, s))
    rig.src.offer("doa", text.encode())
    d = rig.buffer.pending[100.0][0]
    assert len(d.bearings) == 1, d.bearings
    return float(d.bearings[0])


CASES = [(d, h) for d in (0.0, 10.0, 90.0, 135.0, 180.0, 250.0, 271.0, 359.0) for h in (0.0, 37.5, 200.0)]


def _convention_errors_deg(app_bearing) -> np.ndarray:
    errs = []
    for d, h in CASES:
        end = _krakens_line_of_bearing(LAT, LON, d, h)
        want = _initial_bearing(LAT, LON, *end)
        errs.append(abs(math.degrees(wrap(app_bearing(d, h) - want))))
    return np.array(errs)


def test_bearing_convention_is_krakensdrs_own_line_of_bearing():
    # unit-circle main DoA (krakensdr_doa's writer today), the main DoA and the spectrum's peak
    assert _convention_errors_deg(_app_bearing).max() < 0.01
    assert _convention_errors_deg(lambda d, h: _app_bearing(d, h, measurements="peaks")).max() < 0.05
    # a writer that puts 360 - theta in the line (another version of its software): the same
    # bearings, the convention read off the spectrum
    assert _convention_errors_deg(lambda d, h: _app_bearing((360.0 - d) % 360.0, h, "compass")).max() < 0.01


def test_the_convention_test_fails_when_the_sign_or_the_zero_is_flipped(monkeypatch):
    real = doa.bearing_from_array
    for flipped in (lambda th, hd, m=0.0: real(-np.asarray(th, float), hd, m),  # counterclockwise read as clockwise
                    lambda th, hd, m=0.0: real(np.asarray(th, float) + 180.0, hd, m)):  # zero at the back
        monkeypatch.setattr(doa, "bearing_from_array", flipped)
        assert _convention_errors_deg(_app_bearing).max() > 10.0
    monkeypatch.setattr(doa, "bearing_from_array", real)
    assert _convention_errors_deg(_app_bearing).max() < 0.01


# ----------------------------------------------------------------------------- heading and mount
def _geometry_errors_deg(yaw_error_deg: float, mount_deg: float = 0.0) -> np.ndarray:
    """Bearings the app makes of targets at known places, from spectra KrakenSDR would show on a
    vehicle heading 63.4 degrees with the array mounted ``mount_deg`` right of the nose, with the
    pose history's heading off by ``yaw_error_deg``; their errors against the geometry."""
    cfg = replace(SC.kraken, mount_offset_deg=mount_deg)
    rig = Rig(cfg, yaw_deg=63.4, yaw_error_deg=yaw_error_deg)
    uav = np.array([150.0, 200.0])
    targets = np.array([[281.0, 925.0], [238.0, 706.0], [901.0, 925.0], [885.0, 676.0]])
    truth = bearing(targets, uav)
    model = replace(CLEAN, mount_offset_rad=cfg.mount_offset_rad)
    rig.src.offer("doa", _doc(rig, 100.0, [[b] for b in truth], model))
    got = rig.buffer.pending[100.0]
    return np.array([abs(math.degrees(wrap(got[j].bearings[0] - truth[j]))) for j in range(4)])


def test_bearings_use_the_heading_at_the_frame_and_the_mount_offset():
    assert _geometry_errors_deg(0.0).max() < 0.05
    assert _geometry_errors_deg(0.0, mount_deg=-90.0).max() < 0.05


def test_a_one_degree_heading_error_is_detected():
    err = _geometry_errors_deg(1.0)
    assert err.min() > 0.9 and err.max() < 1.1  # every bearing off by the heading's error
    err = _geometry_errors_deg(-1.0, mount_deg=30.0)
    assert err.min() > 0.9


def test_heading_is_taken_at_the_frames_time_not_the_ticks():
    # the vehicle yaws at 20 deg/s; a frame measured 0.2 s before its slot's second must use the
    # heading then (4 degrees less than at the second)
    rig = Rig()
    rig.poses = PoseHistory(keep_s=600.0)
    for k in range(800, 1200):
        rig.poses.add(PoseSample(k / 10.0, np.array([150.0, 200.0, 40.0]), np.zeros(3),
                                 float(wrap(math.radians(2.0 * (k - 1000))))))
    rig.src.poses = rig.poses
    t = 99.8
    yaw_then = math.radians(-4.0)
    theta = doa.array_from_bearing(0.7, yaw_then)
    s = plot_db(render_spectrum([theta], [1.0], CLEAN, np.random.default_rng(2)))
    text = format_line(KrakenLine(rig.epoch(t), float(round(theta)), 20.0, -40.0, FREQS[0], "UCA", 436, "X", 0, 0, 0, s))
    rig.src.offer("doa", text.encode())
    assert rig.buffer.pending == {}  # held: a frame nearer 100 s may follow
    rig.clock.t = 100.9
    rig.src.tick(rig.clock.t)
    d = rig.buffer.pending[100.0][0]
    assert d.t == 100.0 and d.t_measured == pytest.approx(t, abs=2e-3)
    assert abs(math.degrees(wrap(d.bearings[0] - 0.7))) < 0.05


# ----------------------------------------------------------------------------- time and slots
def test_frames_faster_than_a_second_give_one_scan_a_second_nearest_its_second():
    rig = Rig(t0=100.0)
    times = [99.55, 99.95, 100.35, 100.75, 101.15, 101.55]  # 2.5 frames/s
    for t in times:
        rig.clock.t = t + 0.3
        rig.src.offer("doa", _doc(rig, t, [[0.1], [0.2], [0.3], [0.4]], seed=int(t * 100)))
        rig.src.tick(rig.clock.t)
    rig.clock.t = 103.0
    rig.src.tick(rig.clock.t)
    got = {k: {ch: round(d.t_measured, 2) for ch, d in v.items()} for k, v in rig.buffer.pending.items()}
    # each second's nearest frame: 99.95 (at once: none can be nearer), 101.15 (nearer than 100.75,
    # which was held), 101.55 (held until its slot is over)
    assert got == {100.0: dict.fromkeys(range(4), 99.95), 101.0: dict.fromkeys(range(4), 101.15),
                   102.0: dict.fromkeys(range(4), 101.55)}, got
    assert rig.src.decimated == 3 and rig.src.frames == 6


def test_times_too_far_ahead_or_behind_are_refused_and_said_once():
    rig = Rig(t0=100.0)
    rig.src.offer("doa", _doc(rig, 103.0, [[0.1]] * 4))
    rig.src.offer("doa", _doc(rig, 104.0, [[0.1]] * 4))
    rig.src.offer("doa", _doc(rig, 94.0, [[0.1]] * 4))
    assert rig.src.rejected["future_time"] == 8 and rig.src.rejected["stale_time"] == 4
    assert [r for r, _ in rig.reports] == ["future_time", "stale_time"]
    assert rig.buffer.pending == {}
    # without the autopilot's UTC nothing can be placed in time
    rig2 = Rig()
    rig2.src.time_map = UtcMap()
    rig2.src.offer("doa", _doc(rig2, 100.0, [[0.1]] * 4))
    assert rig2.src.rejected["no_time_reference"] == 4


def test_the_same_frame_read_twice_is_used_once_and_squelched_vfos_are_empty_sets():
    rig = Rig()
    doc = _doc(rig, 100.0, [[0.1], [], [0.3], [0.4]])  # T2's VFO below squelch: no line
    assert doc.count(b"\n") == 3
    rig.src.offer("doa", doc)
    rig.src.offer("doa", doc)
    got = rig.buffer.pending[100.0]
    assert sorted(got) == [0, 1, 2, 3] and len(got[1].bearings) == 0 and rig.src.repeated == 1
    assert rig.buffer.complete(100.0)


# ----------------------------------------------------------------------------- the measurement set
def test_peaks_are_the_set_and_the_clutter_rate_follows_them():
    adaptive = replace(SC.kraken, clutter="adaptive")
    rig = Rig(adaptive)
    model = replace(CLEAN, multipath=True, multipath_db=(-6.0, -3.0))
    for k in range(25):
        t = 100.0 + k
        rig.clock.t = t + 0.3
        rig.src.offer("doa", _doc(rig, t, [[0.1 + 0.01 * k, 2.0, -2.0]] * 4, model, seed=k))
    last = rig.buffer.pending[124.0][0]
    assert len(last.bearings) == 3
    # three measurements a scan, p_D = 0.95: Lambda = 2.05 (between the filter's own 1 and 10)
    assert last.clutter_rate == pytest.approx(3 - 0.95)
    # one a scan: the filter's own rate, never less
    rig1 = Rig(adaptive)
    for k in range(5):
        rig1.clock.t = 100.3 + k
        rig1.src.offer("doa", _doc(rig1, 100.0 + k, [[0.1 + 0.01 * k]] * 4, seed=k))
    assert rig1.buffer.pending[104.0][0].clutter_rate == SC.sensor.clutter_rate == 1.0
    rig2 = Rig(replace(adaptive, clutter_min=0.2))
    rig2.src.offer("doa", _doc(rig2, 100.0, [[0.1]] * 4))
    assert rig2.buffer.pending[100.0][0].clutter_rate == 0.2
    # the default (clutter: fixed): the filter's own rate
    rig3 = Rig()
    rig3.src.offer("doa", _doc(rig3, 100.0, [[0.1, 2.0, -2.0]] * 4, model))
    assert len(rig3.buffer.pending[100.0][0].bearings) == 3 and rig3.buffer.pending[100.0][0].clutter_rate is None
    # the main DoA alone, the filter's own rate
    rig2 = Rig(replace(SC.kraken, measurements="main", clutter="fixed"))
    rig2.src.offer("doa", _doc(rig2, 100.0, [[0.1, 2.0, -2.0]] * 4, model))
    d = rig2.buffer.pending[100.0][0]
    assert len(d.bearings) == 1 and d.clutter_rate is None


def test_gates_empty_the_set():
    rig = Rig(replace(SC.kraken, min_confidence=30.0))
    rig.src.offer("doa", _doc(rig, 100.0, [[0.1]] * 4))
    assert all(len(d.bearings) == 0 for d in rig.buffer.pending[100.0].values())
    assert rig.src.gated["confidence"] == 4
    rig = Rig(replace(SC.kraken, min_power_db=-30.0))
    rig.src.offer("doa", _doc(rig, 100.0, [[0.1]] * 4))
    assert rig.src.gated["power"] == 4
    # status.json flags the frame: ADC overdrive, or the DAQ out of sync
    from sim.stack.kraken import status_json
    for flags in ({"overdrive": True}, {"daq_ok": False}):
        rig = Rig()
        rig.src.offer("status", status_json(rig.epoch(100.0), **flags).encode())
        rig.src.offer("status", status_json(rig.epoch(101.0)).encode())
        rig.src.offer("doa", _doc(rig, 100.0, [[0.1]] * 4))
        rig.clock.t = 101.3
        rig.src.offer("doa", _doc(rig, 101.0, [[0.1]] * 4))
        assert rig.src.gated["overdrive"] == 4
        assert all(len(d.bearings) == 0 for d in rig.buffer.pending[100.0].values())
        assert all(len(d.bearings) == 1 for d in rig.buffer.pending[101.0].values())


def test_unknown_vfos_and_other_formats_are_refused_by_name():
    rig = Rig()
    freqs = {0: 446.0e6}
    doc = frame_lines(rig.epoch(100.0), [(np.array([0.1]), np.array([True]))], freqs, 0.0, CLEAN,
                      np.random.default_rng(0))
    rig.src.offer("doa", doc.encode())
    assert rig.src.rejected["unknown_vfo"] == 1
    rig.src.offer("doa", b"<DATA><STATION_ID>NOCALL</STATION_ID><DOA>12</DOA></DATA>")
    rig.src.offer("doa", b'{"station_id": "NOCALL", "radioBearing": "12"}')
    assert rig.src.rejected["format_version"] == 2
    msgs = dict(rig.reports)
    assert "unknown_vfo" in msgs and "446000000 Hz" in msgs["unknown_vfo"]
    assert "Kraken App" in msgs["format_version"]


# ----------------------------------------------------------------------------- time, status, config
def test_the_autopilots_utc_maps_unix_time_and_a_stray_message_moves_nothing():
    utc = UtcMap()
    assert utc.autopilot_time(UNIX0) is None
    utc.observe(0, 5000)  # no GPS time yet: ignored
    assert utc.autopilot_time(UNIX0) is None
    for k in range(5):
        utc.observe(int((UNIX0 + 10 + k) * 1e6), (10 + k) * 1000)
    utc.observe(int((UNIX0 + 3600) * 1e6), 15000)  # forged or garbled: an hour off
    assert utc.autopilot_time(UNIX0 + 20.0) == pytest.approx(20.0)
    assert utc.unix_time(20.0) == pytest.approx(UNIX0 + 20.0)
    for k in range(6):  # a reboot: time since boot starts again, the offset moves; followed
        utc.observe(int((UNIX0 + 100 + k) * 1e6), k * 1000)
    assert utc.autopilot_time(UNIX0 + 103.0) == pytest.approx(3.0)


def test_host_time_maps_through_this_computers_clock_at_the_autopilots_rate():
    from onboard.app.autopilot.clock import HostTime

    class Clock:
        rate = 4.0  # a SITL at 4x

        def now(self):
            return 200.0

    h = HostTime(Clock(), wall=lambda: UNIX0 + 10.0)
    assert h.autopilot_time(UNIX0 + 9.5) == pytest.approx(198.0)  # 0.5 wall s ago = 2 autopilot s


def test_a_bad_status_document_is_counted_and_the_frames_still_used():
    rig = Rig()
    for doc in (b"{not json", b'{"timestamp_ms": "x"}', b"[]", b'{"timestamp_ms": 1, "daq_ok": 3}', b"\xff\xfe"):
        rig.src.offer("status", doc)
    assert rig.src.rejected["status_invalid"] == 5
    rig.src.offer("doa", _doc(rig, 100.0, [[0.1]] * 4))
    assert all(len(d.bearings) == 1 for d in rig.buffer.pending[100.0].values())


def test_a_change_of_convention_is_said():
    rig = Rig(replace(SC.kraken, measurements="main"))
    for k, conv in enumerate(("unit_circle", "unit_circle", "compass")):
        model = replace(CLEAN, convention=conv)
        rig.clock.t = 100.05 + k
        rig.src.offer("doa", _doc(rig, 100.0 + k, [[0.7]] * 4, model))
    assert rig.src.convention == "compass"
    assert [m for r, m in rig.reports if r == "convention"] == [
        "KrakenSDR's main DoA is now written compass: its software changed?"]
    got = [rig.buffer.pending[100.0 + k][0].bearings[0] for k in range(3)]
    assert np.allclose(got, got[0], atol=math.radians(1.0))  # one degree: the main DoA's grid


@pytest.mark.parametrize("change, error", [
    ({"kraken.vfos": [{"target": "T9", "freq_hz": 433e6}]}, "kraken.vfos[0].target: no target named 'T9'"),
    ({"kraken.vfos": [{"target": "T1", "freq_hz": 433e6}, {"target": "T2", "freq_hz": 433.001e6}]},
     "kraken.vfos[1].freq_hz: two VFOs with the same frequency"),
    ({"kraken.vfos": [{"target": "T1", "freq_hz": 433e6}, {"target": "T1", "freq_hz": 434e6}]},
     "kraken.vfos[1].target: two VFOs with the same target"),
    ({"kraken.url": "ftp://x/y"}, "kraken.url: must be http://HOST:PORT/PATH"),
    ({"kraken.convention": "north"}, "kraken.convention: must be one of auto, unit_circle, compass"),
    ({"kraken.poll_s": 0}, "kraken.poll_s: must be in [0.005, 10] s"),
    ({"kraken.mount_offset_deg": 1e400}, "kraken.mount_offset_deg: must be finite"),
    ({"kraken.colour": 1}, "kraken.colour: unknown key"),
])
def test_the_kraken_section_is_checked(change, error):
    from onboard.config import ConfigError
    with pytest.raises(ConfigError, match=error.replace("[", r"\[").replace("]", r"\]").replace(".", r"\.")
                       .replace("(", r"\(").replace(")", r"\)").replace("'", "'")):
        load_scenario("paper", change)


def test_pmon_run_refuses_kraken_without_vfos(tmp_path, capsys):
    import yaml

    from onboard.cli import main
    tree = yaml.safe_load(open("config/paper.yaml"))
    del tree["kraken"]
    path = tmp_path / "nokraken.yaml"
    path.write_text(yaml.safe_dump(tree))
    rc = main(["run", "--mavlink", "udpin:127.0.0.1:0", "--df", "127.0.0.1:0", "--scenario", str(path), "--kraken"])
    err = capsys.readouterr().err
    assert rc == 2 and err.strip() == ("pmon run: kraken.vfos: none: which VFO frequency is which target? "
                                       "(docs/KRAKENSDR.md)")


def test_after_an_autopilot_reboot_the_slots_start_again():
    rig = Rig(t0=300.0)
    rig.src.offer("doa", _doc(rig, 300.0, [[0.1]] * 4))
    assert 300.0 in rig.buffer.pending
    # the autopilot rebooted: its clock reads 20 s; the app's buffer starts again too
    rig.clock.t = 20.05
    rig.buffer = ScanBuffer(len(SC.targets))
    rig.src.sink = rig.buffer.add
    rig.src.offer("doa", _doc(rig, 20.0, [[0.1]] * 4))
    assert 20.0 in rig.buffer.pending and rig.src.decimated == 0


def test_a_frame_is_dated_at_the_middle_of_its_acquisition():
    # KrakenSDR stamps the end of the frame and writes its acquisition time as the latency
    for latency_ms in (436, 1000, 3000):
        rig = Rig()
        model = replace(CLEAN, latency_ms=latency_ms)
        scans = [(np.array([0.1]), np.array([True]))] * 4
        doc = frame_lines(rig.epoch(100.0, latency_ms), scans, FREQS, rig.yaw, model, np.random.default_rng(0))
        assert f", {latency_ms}, " in doc
        rig.src.offer("doa", doc.encode())
        assert rig.buffer.pending[100.0][0].t_measured == pytest.approx(100.0, abs=2e-3)
        # the same stamp read as if the latency were 0 would be latency/2 later
        assert (rig.epoch(100.0, latency_ms) / 1000.0 - UNIX0) - 100.0 == pytest.approx(latency_ms / 2000.0, abs=1e-3)


def test_frames_written_but_never_read_are_counted_and_said():
    # KrakenSDR's document holds its newest frame only: a reader that falls behind loses frames
    rig = Rig()
    for k in (0, 1, 2, 3, 4, 5, 8, 9, 13):
        rig.clock.t = 100.05 + k
        rig.src.offer("doa", _doc(rig, 100.0 + k, [[0.1]] * 4, seed=k))
    assert rig.src.missed == 2 + 3
    assert [m for r, m in rig.reports if r == "missed"] == [
        "KrakenSDR frames written but not read (a 3.0 s gap): the reader fell behind"]


def test_pmon_stat_carries_the_krakensdr_counts_to_the_ground_station():
    """PMON_STAT's KrakenSDR fields as the publisher encodes them and the ground station decodes
    them: the counts with a KrakenSDR input, None (NaN on the wire) without one."""
    from groundstation import protocol as P
    from onboard.app.contract import KRAKEN_STAT_FIELDS, STAT_FIELDS, State
    from onboard.app.mavlink_connection import mavlink
    from onboard.app.gcs.publisher import Publisher
    from onboard.app.autopilot.vehicle import Vehicle

    class Wire:
        mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
        sent: list = []

        def send(self, msg):
            self.sent.append(self.mav.decode(bytearray(msg.pack(self.mav))))
            return True

    class Clock:
        def now(self):
            return 12.0

    stat = dict.fromkeys(STAT_FIELDS, 0.0)
    stat.update(dict(zip(KRAKEN_STAT_FIELDS, (1234.0, 7.0, 3.0))))
    pub = Publisher(Wire(), Clock(), Vehicle(sysid=1), lambda: State.PAUSED, lambda: stat)
    pub.publish_stat()
    assert P.AppStatus.from_msg(Wire.sent[-1]).kraken == (1234, 7, 3)
    stat.update(dict.fromkeys(KRAKEN_STAT_FIELDS, math.nan))
    pub.publish_stat()
    assert P.AppStatus.from_msg(Wire.sent[-1]).kraken is None
