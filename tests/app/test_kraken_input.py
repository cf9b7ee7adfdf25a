"""KrakenSDR's output read by a running app over real HTTP and files (issue 32, items 1 and 6).

* the transport: a document caught mid-rewrite is never taken; the server going away and
  coming back, a server that trickles, a document too large: counted, said, recovered from;
* the app ticks every frame's second with every target's set, the bearings right;
* 10,000 hostile lines (truncated, overlong, wrong field counts, NaN, huge numbers, a spectrum
  of the wrong length, times ahead and far behind, unknown VFOs, other formats, bytes that are
  not UTF-8) between the good frames of a mission: no exception, no missed tick, every good line
  used, every bad one counted under its reason and each reason said once.
"""
from __future__ import annotations

import math
import os
import random
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from onboard.app.kraken import line as kl
from onboard.app.app_config import AppConfig
from onboard.app.app import OnboardApp
from onboard.app.autopilot.clock import ManualClock
from onboard.app.kraken.fetch import DocumentPoller, FileSource, HttpSource
from onboard.app.autopilot.pose import PoseSample
from onboard.config import load_scenario
from onboard.policy import with_policy
from onboard.core.bearings import bearing, wrap
from sim.stack.kraken import KrakenWriter, status_json
from tests.support.kraken_rig import M, UAV, YAW
from tests.support.kraken_rig import epoch as _epoch
from tests.support.kraken_rig import frame as _frame
from tests.support.kraken_rig import kraken_app as _app


def _wait(pred, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.002)
    return pred()


# ----------------------------------------------------------------------------- transport
def test_a_document_caught_mid_rewrite_is_never_taken(tmp_path):
    """A writer rewriting in place as KrakenSDR does, but slowly (the document in two writes,
    1 ms apart, 50 documents a second), and a poller reading as fast as it can: every document
    it takes is one that was written whole."""
    path = tmp_path / "DOA_value.html"
    docs = [(f"{k:06d}," * (50 + (k * 37) % 200)).encode() + b"\n" for k in range(300)]
    written = set(docs)
    f = open(path, "w+b")
    stop = threading.Event()

    def writer():
        k = 0
        while not stop.is_set():
            d = docs[k % len(docs)]
            f.seek(0)
            f.write(d[:len(d) // 2])
            f.flush()
            time.sleep(0.001)
            f.write(d[len(d) // 2:])
            f.truncate()
            f.flush()
            k += 1
            time.sleep(0.02)  # KrakenSDR writes a frame every few hundred ms; faster here

    naive_torn = [0]

    def naive():  # one read, taken as it is
        while not stop.is_set():
            if path.read_bytes() not in written:
                naive_torn[0] += 1
            time.sleep(0.0005)

    poller = DocumentPoller(str(path), None, 0.0005)
    threads = [threading.Thread(target=fn, daemon=True) for fn in (writer, naive)]
    for th in threads:
        th.start()
    poller.start()
    try:
        time.sleep(2.0)
    finally:
        stop.set()
        poller.stop()
        for th in threads:
            th.join()
        f.close()
    taken = [d for _, d, _ in poller.queue]
    assert len(taken) > 20, poller.reads
    torn = [d for d in taken if d not in written]
    assert not torn, (len(torn), len(taken))
    assert naive_torn[0] > 10  # a reader that takes one read as it is takes torn documents


def test_an_empty_document_is_not_taken(tmp_path):
    """A document truncated and not yet rewritten (a writer descheduled between its truncate and
    its write: two reads agree on it) is no document: not queued, and the next one is."""
    path = tmp_path / "status.json"
    path.write_text('{"timestamp_ms": 1}')
    poller = DocumentPoller(str(tmp_path / "DOA_value.html"), str(path), 0.01)
    assert poller.poll("status") and len(poller.queue) == 1
    path.write_text("")
    assert poller.poll("status") and len(poller.queue) == 1 and poller.empty == 1
    path.write_text('{"timestamp_ms": 2}')
    assert poller.poll("status") and [d for _, d, _ in poller.queue] == [b'{"timestamp_ms": 1}', b'{"timestamp_ms": 2}']
    path.write_text('{"timestamp_ms": 2}')  # the same again: not new
    assert poller.poll("status") and len(poller.queue) == 2
    poller.stop()


class _Trickle(BaseHTTPRequestHandler):
    def do_GET(self):  # noqa: N802 (http.server's name)
        self.send_response(200)
        self.send_header("Content-Length", "5000")
        self.end_headers()
        for _ in range(50):
            self.wfile.write(b"x" * 10)
            self.wfile.flush()
            time.sleep(0.1)

    def log_message(self, *a):
        pass


def test_http_failures_are_counted_and_recovered_from(tmp_path):
    w = KrakenWriter(tmp_path / "share", serve=("127.0.0.1", 0))
    port = w.server.server_address[1]
    w.write(_frame(10.0, [[0.1]] * M, 0))
    src = HttpSource(w.url, kl.MAX_DOC_BYTES, timeout_s=0.5)
    assert src.get().count(b"\n") == M
    url = w.url
    w.server.shutdown()
    w.server.server_close()
    w.server = None
    poller = DocumentPoller(url, None, 0.01, timeout_s=0.5)
    poller.start()
    try:
        assert _wait(lambda: poller.down["doa"] and poller.errors.get("doa connection_refused", 0) >= 2, 5)
        assert "refused" in poller.last_error["doa"]
        # the server back on the same port: read again, nothing queued twice
        from functools import partial
        from sim.stack.kraken import _QuietHandler
        srv = ThreadingHTTPServer(("127.0.0.1", port), partial(_QuietHandler, directory=str(w.folder)))
        threading.Thread(target=srv.serve_forever, daemon=True).start()
        try:
            assert _wait(lambda: poller.documents == 1 and not poller.down["doa"], 5), poller.errors
            w.write(_frame(11.0, [[0.2]] * M, 1))
            assert _wait(lambda: poller.documents == 2, 5)
        finally:
            srv.shutdown()
            srv.server_close()
    finally:
        poller.stop()
        w.close()
    # a 404, a trickling server, a document too large
    srv = ThreadingHTTPServer(("127.0.0.1", 0), _Trickle)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        slow = HttpSource(f"http://127.0.0.1:{srv.server_address[1]}/x", kl.MAX_DOC_BYTES, timeout_s=0.3)
        t0 = time.monotonic()
        with pytest.raises(Exception) as e:
            slow.get()
        assert e.value.kind == "timeout" and time.monotonic() - t0 < 1.0
    finally:
        srv.shutdown()
        srv.server_close()
    w2 = KrakenWriter(tmp_path / "big", serve=("127.0.0.1", 0))
    try:
        with pytest.raises(Exception) as e:
            HttpSource(w2.url.replace("DOA_value.html", "nothing.html"), 100).get()
        assert e.value.kind == "http_status" and "404" in str(e.value)
        w2.write("x" * (kl.MAX_DOC_BYTES + 1))
        with pytest.raises(Exception) as e:
            HttpSource(w2.url, kl.MAX_DOC_BYTES).get()
        assert e.value.kind == "too_large"
    finally:
        w2.close()
    fifo = tmp_path / "fifo"
    import os
    os.mkfifo(fifo)
    with pytest.raises(Exception) as e:
        FileSource(str(fifo), 100).get()
    assert e.value.kind == "file" and "FIFO" in str(e.value)


# ----------------------------------------------------------------------------- the app
def test_the_app_ticks_every_frame_with_the_right_bearings(tmp_path):
    w = KrakenWriter(tmp_path / "share", serve=("127.0.0.1", 0))
    clock = ManualClock(50.0)
    app = _app(w.url, clock)
    targets = np.array([[281.0, 925.0], [238.0, 706.0], [901.0, 925.0], [885.0, 676.0]])
    truth = bearing(targets, UAV[:2])
    got: list = []
    sink = app.kraken.source.sink
    app.kraken.source.sink = lambda d, now: (got.append(d), sink(d, now))
    try:
        for k in range(10):
            t = 51.0 + k
            clock.t = t + 0.05
            w.write(_frame(t, [[b] for b in truth], k), status_json(_epoch(t)))
            assert _wait(lambda: any(tk["t"] == t for tk in app.ticks), 5), (t, app.kraken.source.rejected)
    finally:
        app.stop()
        w.close()
    ticked = [tk for tk in app.ticks if tk["channels"]]
    assert [tk["t"] for tk in ticked] == [51.0 + k for k in range(10)]
    assert all(tk["channels"] == [0, 1, 2, 3] and tk["n_bearings"] == [1, 1, 1, 1] for tk in ticked), (
        [(tk["channels"], tk["n_bearings"]) for tk in ticked], app.kraken.source.rejected, app.kraken.source.gated)
    err = [abs(math.degrees(wrap(d.bearings[0] - truth[d.ch]))) for d in got]
    # the sim's noise-free bearings back through KrakenSDR's line, the heading and the peak fit
    assert len(err) == 40 and max(err) < 0.1, max(err)
    assert app.counters.get("io_errors", 0) == 0 and app.counters.get("tick_errors", 0) == 0


# ----------------------------------------------------------------------------- 10,000 hostile lines
def _good_line(t: float, ch: int, seed: int) -> str:
    return _frame(t, [[0.3 * (j + 1)] if j == ch else [] for j in range(M)], seed)


_BASES = [_good_line(0.0, k % M, k).rstrip("\n").rstrip() for k in range(16)]


def _at(line: str, t: float) -> str:
    """A line of ``_BASES`` with the time stamp of a frame measured at ``t``."""
    return str(_epoch(t)) + line[line.index(","):]


def _hostile(rng: random.Random, t: float, uniq: list[int]) -> list[tuple[bytes, str]]:
    """Hostile lines (bytes without the newline) with the reason each is refused for."""
    base = _at(rng.choice(_BASES), t)
    fields = base.split(", ")
    out = []
    kind = rng.randrange(12)
    if kind == 0:  # truncated mid-line (the rest never came), then a newline
        out.append(base[:rng.randrange(5, len(base) - 5)])
    elif kind == 1:  # overlong
        out.append(base + ", 1.00" * 1200)
    elif kind == 2:  # a header field missing or one too many
        f = list(fields)
        if rng.random() < 0.5:
            f.pop(rng.randrange(1, 17))
        else:
            f.insert(rng.randrange(1, 17), "7")
        out.append(", ".join(f))
    elif kind == 3:  # NaN, inf, huge numbers
        f = list(fields)
        f[rng.choice([1, 2, 3, 4, 6, 20, 200])] = rng.choice(["nan", "NaN", "inf", "-inf", "1e999", "9" * 40,
                                                              "1e308000", "0x1F", "1_000", "--3"])
        out.append(", ".join(f))
    elif kind == 4:  # a spectrum of the wrong length
        n = rng.choice([359, 361, 180, 720])
        out.append(", ".join(fields[:17] + (fields[17:] * 2)[:n]))
    elif kind in (5, 6):  # measured far in the future / far in the past (each its own frame)
        uniq[0] += 1
        dt = rng.choice([3.0, 30.0, 1e6]) if kind == 5 else -rng.choice([6.0, 60.0, 3600.0])
        f = _at(_BASES[0], t + dt).split(", ")
        f[0] = str(_epoch(t + dt) + uniq[0] % 400)  # a frame of its own
        out.append(", ".join(f))
    elif kind == 7:  # a VFO that is no target's
        uniq[0] += 1
        f = list(fields)
        f[0] = str(_epoch(t) + 1 + uniq[0] % 400)
        f[4] = str(rng.choice([144_800_000, 446_000_000, 433_150_000]))
        out.append(", ".join(f))
    elif kind == 8:  # the older 7-field line
        out.append(", ".join(fields[:7] + fields[17:]))
    elif kind == 9:  # not UTF-8
        b = bytearray(base.encode())
        b[rng.randrange(len(b))] = 0xFF
        return [(bytes(b), "not_utf8")]
    elif kind == 10:  # out of range: DoA, confidence, latency, epoch
        f = list(fields)
        i, v = rng.choice([(1, "361.0"), (1, "-2"), (2, "-1"), (6, "999999"), (0, "17"), (4, "12")])
        f[i] = v
        out.append(", ".join(f))
    else:  # a field that is not a number at all
        f = list(fields)
        f[rng.choice([0, 1, 2, 3, 8, 9, 10, 11, 100])] = rng.choice(["abc", "", "1.2.3", "--", "NOCALL"])
        out.append(", ".join(f))
    res = []
    for text in out:
        raw = text.encode()
        try:
            kl.parse_line(raw)
        except kl.LineError as err:
            res.append((raw, err.reason))
            continue
        res.append((raw, {5: "future_time", 6: "stale_time", 7: "unknown_vfo"}.get(kind, "valid")))
    return res


def _batch(rng: random.Random, t: float, uniq: list[int], n: int) -> list[tuple[bytes, str]]:
    """About ``n`` hostile lines for one document, within its size limit (a larger document is
    refused whole: tested on its own)."""
    out: list = []
    size = 0
    while len(out) < n:
        for raw, why in _hostile(rng, t, uniq):
            if why != "valid" and size + len(raw) + 2 < kl.MAX_DOC_BYTES - 4 * kl.MAX_LINE_BYTES:
                out.append((raw, why))
                size += len(raw) + 2
        if size > kl.MAX_DOC_BYTES - 5 * kl.MAX_LINE_BYTES:
            break
    return out


def _check_flood_cost_nothing(app, expected: dict, n_bad: int, n_good: int, n_seconds: int,
                              beats: list[float]) -> None:
    """After the flood: a tick for every good frame, every good line used, every bad one counted
    under its reason and said once, and the io loop's beat never stalled."""
    src, poller = app.kraken.source, app.kraken.poller
    assert n_bad >= 10_000
    assert app.counters.get("io_errors", 0) == 0 and app.counters.get("tick_errors", 0) == 0, app.errors.counts
    ticked = [tk for tk in app.ticks if tk["channels"]]
    assert [tk["t"] for tk in ticked] == [51.0 + k for k in range(n_seconds)], "a tick for every good frame"
    assert all(tk["channels"] == list(range(M)) and tk["n_bearings"] == [1] * M for tk in ticked)
    assert src.scans == n_good and app.scans.accepted == n_good  # every good line used
    got = {r: n for r, n in src.rejected.items() if n}
    assert got == expected, (got, expected)
    said = [text for _, text in app.events if "bad KrakenSDR data" in text]
    assert len(said) == len(expected) == len({s.split(":")[2] for s in said})  # each reason once
    # no status.json was ever written: said once, the frames used all the same
    assert sum("status.json not read" in text for _, text in app.events) == 1
    # the io loop kept turning (its beat is stamped every ~2 ms iteration)
    assert max(beats) < 0.25, max(beats)
    assert poller.queue_full == 0


@pytest.mark.timeout(300)
def test_10000_hostile_lines_between_good_frames_cost_nothing(tmp_path):
    w = KrakenWriter(tmp_path / "share", serve=("127.0.0.1", 0))
    clock = ManualClock(50.0)
    app = _app(w.url, clock)
    rng = random.Random(32)
    uniq = [0]
    expected: dict[str, int] = {}
    n_bad = n_good = 0
    n_seconds = 60
    poller = app.kraken.poller
    beats: list[float] = []
    stop = threading.Event()

    def watch():  # the io loop's beat: it must keep turning through the flood
        while not stop.is_set():
            beats.append(time.monotonic() - app._io_beat)
            time.sleep(0.005)

    threading.Thread(target=watch, daemon=True).start()

    def taken(before: int) -> bool:  # the poller took a new document and the io thread handled it
        return _wait(lambda: poller.documents > before and app.kraken.handled == poller.documents, 5)

    def write(data: bytes) -> None:
        # replaced whole (rename), not rewritten in place as KrakenSDR does: this test counts every
        # bad line exactly, and a read torn across an in-place rewrite by a descheduled writer
        # (test_a_document_caught_mid_rewrite_is_never_taken) would add the old document's tail
        tmp = w.folder / "next.tmp"
        tmp.write_bytes(data)
        os.replace(tmp, w.doc_path)

    def put(doc: str) -> None:
        before = poller.documents
        write(doc.encode())
        assert taken(before), "the poller took the document"

    try:
        for k in range(n_seconds):
            t = 51.0 + k
            clock.t = t + 0.05
            good = _frame(t, [[0.2 + 0.1 * j] for j in range(M)], k)
            # the good frame, with hostile lines in its document (they come first: a torn
            # start), then documents of nothing but hostile lines
            lines = _batch(rng, t, uniq, 20)
            for raw, why in lines:
                expected[why] = expected.get(why, 0) + 1
            n_bad += len(lines)
            n_good += M
            before = poller.documents
            write(b"".join(r + b" \n" for r, _ in lines) + good.encode())  # bytes: not-UTF-8 lines as they are
            assert taken(before)
            while n_bad < (k + 1) * 10_000 // n_seconds:
                chunk = _batch(rng, t, uniq, 50)
                for raw, why in chunk:
                    expected[why] = expected.get(why, 0) + 1
                n_bad += len(chunk)
                before = poller.documents
                write(b"".join(r + b" \n" for r, _ in chunk))
                assert taken(before)
            assert _wait(lambda: any(tk["t"] == t for tk in app.ticks), 5), (t, app.kraken.source.rejected)
        # other formats and a flood of lines in one document
        for doc, why in (("<DATA><DOA>12</DOA></DATA>", "format_version"), ('{"radioBearing": "12"}', "format_version")):
            put(doc)
            expected[why] = expected.get(why, 0) + 1
        put("1, 2\n" * 500)
        before = dict(poller.errors)
        write(b"1, 2\n" * (kl.MAX_DOC_BYTES // 5 + 1))  # a document too large: refused unread, counted
        assert _wait(lambda: poller.errors.get("doa too_large", 0) > before.get("doa too_large", 0), 5)
        expected["field_count"] += 4 * kl.MAX_LINES
        expected["too_many_lines"] = expected.get("too_many_lines", 0) + 500 - 4 * kl.MAX_LINES
        assert _wait(lambda: not poller.queue, 5)
        time.sleep(0.1)
    finally:
        stop.set()
        app.stop()
        w.close()
    _check_flood_cost_nothing(app, expected, n_bad, n_good, n_seconds, beats)


# ----------------------------------------------------------------------------- replay
def test_a_recording_replayed_as_krakensdr_reaches_the_app(tmp_path):
    """``pmon feed replay FILE --df kraken``: a recording of "Kraken App" lines written back as
    KrakenSDR's output, stamps moved to now; the app (time_source: host) ticks each frame."""
    from sim.stack.kraken import read_frames, replay_frames

    rec = tmp_path / "mydata.csv"
    rec.write_text("".join(_frame(10.0 + k, [[0.2 + 0.1 * j] for j in range(M)], k) for k in range(5)))
    frames = read_frames(rec)
    assert [len(lines) for _, lines in frames] == [M] * 5 and frames[1][0] - frames[0][0] == 1000
    bad = tmp_path / "bad.csv"
    bad.write_text(_frame(10.0, [[0.2]] * M, 0) + "1700000000000, 12, 3\n")
    with pytest.raises(ValueError, match=r"bad\.csv:5: field_count"):
        read_frames(bad)

    class WallClock:  # the autopilot's clock at 1x: autopilot 100 s now
        w0 = time.time()
        rate = 1.0

        def now(self):
            return 100.0 + time.time() - self.w0

    w = KrakenWriter(tmp_path / "share", serve=("127.0.0.1", 0))
    sc = with_policy(load_scenario("paper", {"kraken.poll_s": 0.005, "kraken.time_source": "host", "kraken.url": w.url}),
                     "paper")
    app = OnboardApp(AppConfig("udpin:127.0.0.1:0", sensor_port=0, kraken=True), sc, clock=WallClock())
    app.poses.keep_s = 1e6
    for k in range(1500):
        app.poses.add(PoseSample(90.0 + k / 10.0, UAV.copy(), np.zeros(3), YAW))
    app.start()
    try:
        assert replay_frames(frames, w, time.time, threading.Event(), log=lambda s: None) == 5
        assert _wait(lambda: len([tk for tk in app.ticks if tk["channels"]]) == 5, 5)
    finally:
        app.stop()
        w.close()
    ticked = [tk for tk in app.ticks if tk["channels"]]
    assert all(tk["channels"] == list(range(M)) and tk["n_bearings"] == [1] * M for tk in ticked)
    assert np.allclose(np.diff([tk["t"] for tk in ticked]), 1.0)
    assert {r: n for r, n in app.kraken.source.rejected.items() if n} == {}
