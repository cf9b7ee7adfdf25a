"""The simulated KrakenSDR when its simulator falls behind (the flake of
tests/firmware/test_kraken_ardupilot.py, branch kflake): the feed process descheduled for 0.3 s
wrote its overdue frame and the next, due, one milliseconds apart, and the app, reading the document
(which holds the newest frame only) every 50 ms, never saw the first: "KrakenSDR frames written
but not read (a 2.0 s gap)". Each frame must stay the document long enough for a reader to take
it (``MIN_SHOWN_S``), as each of a KrakenSDR's frames does."""
from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

from onboard.app.kraken.fetch import DocumentPoller
from onboard.config import load_scenario
from sim.stack.kraken import MIN_SHOWN_S, KrakenFeed, KrakenWriter
from sim.stack.live_feed import LiveFeedConfig


class WallClock:
    """An autopilot clock running at wall speed from ``t0`` s (speedup 1)."""

    resets = 0

    def __init__(self, t0: float):
        self.t0, self.m0 = t0, time.monotonic()

    def jump(self, s: float) -> None:
        self.t0 += s

    def now(self) -> float:
        return self.t0 + time.monotonic() - self.m0


def _telemetry(clock) -> SimpleNamespace:
    pose = SimpleNamespace(vel=np.zeros(3), t=clock.now())
    return SimpleNamespace(clock=clock, poses=SimpleNamespace(yaw_at=lambda t: 0.0, latest=lambda: pose),
                           utc=SimpleNamespace(unix_time=lambda t: 1.8e9 + t))


def test_a_frame_overdue_with_the_next_is_still_shown_long_enough_to_be_read(tmp_path):
    sc = load_scenario("paper")
    writer = KrakenWriter(tmp_path / "share", serve=("127.0.0.1", 0))
    feed = KrakenFeed(LiveFeedConfig("tcp:127.0.0.1:1", seed=3), sc, writer, log=lambda s: None)
    poller = DocumentPoller(writer.url, None, 0.05).start()  # the app's reader, its default period
    clock = WallClock(12.02)  # frame 11 was due 1.02 s ago, frame 12 0.02 s ago: the feed fell behind
    tel = _telemetry(clock)
    uav = np.array([*sc.uav.start_m[:2], sc.uav.altitude_m])
    scans = tuple((np.array([0.5 + ch]), np.array([True])) for ch in range(len(sc.targets)))
    try:
        time.sleep(0.2)  # the poller has read the empty document
        t0 = clock.now()
        for T in (11.0, 12.0):
            feed._frame(T, scans, uav, tel)
        shown = clock.now() - t0  # the first frame was the document this long
        time.sleep(0.3)
        docs = [doc for kind, doc, _ in poller.pop(100) if kind == "doa"]
    finally:
        poller.stop()
        writer.close(linger_s=0.0)
    epochs = [int(doc.split(b",", 1)[0]) for doc in docs]
    first = int(round((1.8e9 + 11.0) * 1000 + feed.model.latency_ms / 2))
    assert epochs == [first, first + 1000], epochs  # both frames read, in order
    assert writer.frames == 2 and feed.held == 1 and shown >= MIN_SHOWN_S - 0.01, (writer.frames, feed.held, shown)


def _epochs(poller) -> list[int]:
    return [int(doc.split(b",", 1)[0]) for kind, doc, _ in poller.pop(100) if kind == "doa"]


def test_a_frame_written_just_before_the_feed_stalled_is_read_before_the_next(tmp_path):
    """The feed wrote frame 11 and was descheduled (its server with it) for an autopilot second:
    frame 11 was never readable, and frame 12, due as the feed woke, would have replaced it at
    once. It is held until a reader has taken frame 11."""
    sc = load_scenario("paper")
    writer = KrakenWriter(tmp_path / "share", serve=("127.0.0.1", 0))
    feed = KrakenFeed(LiveFeedConfig("tcp:127.0.0.1:1", seed=3), sc, writer, log=lambda s: None)
    clock = WallClock(10.0)
    tel = _telemetry(clock)
    uav = np.array([*sc.uav.start_m[:2], sc.uav.altitude_m])
    scans = tuple((np.array([0.5 + ch]), np.array([True])) for ch in range(len(sc.targets)))
    first = DocumentPoller(writer.url, None, 0.05).start()
    second = None
    try:
        feed._frame(10.0, scans, uav, tel)
        time.sleep(0.3)
        first.stop()  # the app has read frame 10 ...
        clock.jump(0.8)
        feed._frame(11.0, scans, uav, tel)  # ... frame 11 is written, and the feed stalls an autopilot s
        clock.jump(1.0)
        second = DocumentPoller(writer.url, None, 0.05).start()  # the app reads on as the feed wakes
        feed._frame(12.0, scans, uav, tel)
        time.sleep(0.3)
        epochs = _epochs(second)
    finally:
        first.stop()
        if second is not None:
            second.stop()
        writer.close(linger_s=0.0)
    stamp = int(round((1.8e9 + 11.0) * 1000 + feed.model.latency_ms / 2))
    assert epochs == [stamp, stamp + 1000], epochs
    assert feed.held == 1, feed.held
