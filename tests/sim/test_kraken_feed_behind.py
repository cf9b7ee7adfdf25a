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

from onboard.app.kraken_fetch import DocumentPoller
from onboard.config import load_scenario
from sim.kraken import MIN_SHOWN_S, KrakenFeed, KrakenWriter
from sim.live_feed import LiveFeedConfig


class WallClock:
    """An autopilot clock running at wall speed from ``t0`` s (speedup 1)."""

    resets = 0

    def __init__(self, t0: float):
        self.t0, self.m0 = t0, time.monotonic()

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
