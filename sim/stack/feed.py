"""Simulated direction-finder feeds: live (truth world + DF model: sim/stack/live_feed.py) and replay (a
recorded file), and ``pmon feed``'s command line (also ``python -m sim.stack.feed``).

Truth JSONL, one line per scan:
    {"t": T, "k": k, "uav_enu": [e, n, u], "targets": [[x, y, z, vx, vy, vz], ...],
     "bearings": [[...], ...]}          # the bearings sent, per channel
preceded by a header line {"header": {...scenario, seed, origin...}}.

Replay: sends the "bearings" of such a file (or of any JSONL with t/ch/bearings_rad records) on
the autopilot clock (``--mavlink``, times rebased to the first whole second after start) or on a
wall clock (``--speedup``, times kept). The bearings were taken from where the UAV was in the
recording: a replay tests the app's input path and timing, not geometry of a new flight.
"""
from __future__ import annotations

import json
import math
import socket
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

from onboard.app.df import datagram as dg
from onboard.app.autopilot.pose import Frame
from sim.stack.live_feed import START_MODES, LiveFeed, LiveFeedConfig, Telemetry, _sleep_until


def read_recording(path: str | Path) -> Iterator[tuple[float, int, list[float]]]:
    """(t, ch, bearings) from a truth JSONL (``bearings`` per channel) or a datagram JSONL.

    A regular file only (onboard/files.py: a FIFO or /dev/zero would hang the reader); every
    record is checked as it is read (t a finite number >= 0, ch an integer 0..255, bearings finite
    numbers in (-pi, pi]), a bad one is a ValueError naming its line, never another exception."""
    from onboard.files import open_regular

    with open_regular(path, text=True) as f:
        for n, line in enumerate(f, 1):
            line = line.strip()
            if not line:
                continue
            try:
                rec = json.loads(line)
            except (ValueError, RecursionError) as exc:
                raise ValueError(f"{path}:{n}: not JSON: {str(exc)[:80]}") from None
            if not isinstance(rec, dict) or "header" in rec:
                continue
            try:
                t = _finite(rec["t"], 0.0, 1e9)
                if "bearings" in rec:
                    if not isinstance(rec["bearings"], list) or len(rec["bearings"]) > 256:
                        raise ValueError("bearings must be a list per channel (at most 256)")
                    scans = list(enumerate(rec["bearings"]))
                elif "bearings_rad" in rec:
                    ch = rec["ch"]
                    if isinstance(ch, bool) or not isinstance(ch, int) or not 0 <= ch <= 255:
                        raise ValueError("ch must be an integer 0..255")
                    scans = [(ch, rec["bearings_rad"])]
                else:
                    raise ValueError("neither 'bearings' nor 'bearings_rad'")
                for ch, b in scans:
                    if not isinstance(b, list) or len(b) > dg.MAX_BEARINGS:
                        raise ValueError(f"bearings of ch {ch} must be a list of at most {dg.MAX_BEARINGS}")
                    yield t, ch, [_finite(x, -math.pi, math.pi) for x in b]
            except KeyError as exc:
                raise ValueError(f"{path}:{n}: missing {exc.args[0]!r}") from None
            except ValueError as exc:
                raise ValueError(f"{path}:{n}: {exc}") from None


def _finite(v, lo: float, hi: float) -> float:
    """A JSON number in [lo, hi] as a float (an integer past a float's range is out of it, not an
    OverflowError)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
        shown = repr(v) if len(repr(v)) <= 24 else repr(v)[:21] + "..."
        raise ValueError(f"{shown} is not a number in [{lo:g}, {hi:g}]")
    return float(v)


class WallClock:
    resets = 0  # never: a replay's clock is the wall's (the autopilot clock counts reboots)

    def __init__(self, speedup: float = 1.0, t0: float = 0.0):
        self.speedup, self.t0, self.start = speedup, t0, time.monotonic()

    def now(self) -> float:
        return self.t0 + (time.monotonic() - self.start) * self.speedup


def replay(path: str | Path, dest: tuple[str, int], mavlink_url: str | None = None,
           speedup: float = 1.0, stop: threading.Event | None = None,
           log: Callable[[str], None] = print, frame: Frame | None = None) -> int:
    """Send a recording; returns the number of datagrams sent."""
    records = sorted(read_recording(path), key=lambda r: (r[0], r[1]))
    if not records:
        log(f"replay: {path}: no scans")
        return 0
    stop = stop or threading.Event()
    tel = None
    offset = 0.0
    if mavlink_url:
        tel = Telemetry(mavlink_url, frame or Frame(0, 0, 0)).start()
        while tel.clock.now() is None and not stop.is_set():
            time.sleep(0.01)
        clock = tel.clock
        offset = math.floor(clock.now()) + 1.0 - records[0][0]  # rebase onto the autopilot clock
    else:
        clock = WallClock(speedup, records[0][0])
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sent = 0
    try:
        for seq, (t, ch, b) in enumerate(records):
            if not _sleep_until(clock, t + offset, stop):
                break
            sock.sendto(dg.encode(t + offset, ch, b, seq), dest)
            sent += 1
    finally:
        sock.close()
        if tel is not None:
            tel.stop()
    log(f"replay: sent {sent} datagrams")
    return sent


def main(argv=None) -> int:
    """``pmon feed live|replay ...`` (also ``python -m sim.stack.feed``)."""
    import signal

    from onboard.argcheck import fail
    from onboard.config import ConfigError

    ap = _parser()
    args = ap.parse_args(argv)
    host, port = args.to
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        if args.mode == "live":
            return _live(args, stop)
        if args.df == "kraken":
            from sim.stack.kraken import replay_from_args
            replay_from_args(args, stop, log=lambda s: print(s, flush=True))
            return 0
        replay(args.file, (host, port), args.mavlink, args.speedup, stop,
               log=lambda s: print(s, flush=True))
        return 0
    except (ConfigError, ValueError, OSError) as exc:
        return fail(ap.prog, str(exc))


def _parser():
    from onboard.argcheck import HOST_PORT, MAVLINK_URL, OUT_FILE, SEED, SPEEDUP, OneLineParser, number

    ap = OneLineParser(prog="pmon feed", description="simulated DF feed to the onboard app")
    sub = ap.add_subparsers(dest="mode", required=True)
    lv = sub.add_parser("live", help="truth world + DF model, UAV pose from MAVLink telemetry")
    lv.add_argument("--mavlink", required=True, type=MAVLINK_URL, help="the feed's own connection to the "
                    "autopilot, e.g. tcp:127.0.0.1:5760 or udpin:127.0.0.1:14551")
    lv.add_argument("--to", default=("127.0.0.1", 14600), type=HOST_PORT, help="the app's DF port HOST:PORT")
    lv.add_argument("--scenario", default="paper")
    lv.add_argument("--truth", type=OUT_FILE, help="write the truth JSONL here")
    lv.add_argument("--seed", type=SEED, default=1)
    from sim.truth.kinds import TRUTH_KINDS
    lv.add_argument("--kind", choices=TRUTH_KINDS, default="nominal",
                    help="how the true targets move (default nominal: as the scenario says; docs/RESULTS.md)")
    lv.add_argument("--duration", type=number(1.0, 1e7), help="scans to send (s); default: mission.duration_s")
    lv.add_argument("--start", choices=START_MODES, default="armed",
                    help="first scan when the vehicle arms (default), when it is armed and at the mission "
                         "altitude (altitude: the paper's mission, no take-off), or as soon as its clock "
                         "and position are known (now)")
    lv.add_argument("--altitude", type=number(0.0, 1e4), help="--start altitude: the mission altitude h, m "
                    "(default: the scenario's uav.altitude_m)")
    lv.add_argument("--signing-key", metavar="FILE", help="MAVLink 2 signing key file of the autopilot link")
    from sim.stack.kraken import add_feed_arguments
    add_feed_arguments(lv)
    rp = sub.add_parser("replay", help="send a recorded truth/datagram JSONL")
    rp.add_argument("file")
    rp.add_argument("--to", default=("127.0.0.1", 14600), type=HOST_PORT)
    rp.add_argument("--mavlink", type=MAVLINK_URL, help="pace on this autopilot's clock (times rebased)")
    rp.add_argument("--speedup", type=SPEEDUP, default=1.0, help="without --mavlink: wall-clock pace")
    from sim.stack.kraken import add_replay_arguments
    add_replay_arguments(rp)
    return ap


def _live(args, stop: threading.Event) -> int:
    """``pmon feed live``: the feed (datagrams, or KrakenSDR's files with ``--df kraken``) until
    its end or ``stop``."""
    from onboard.config import load_scenario

    host, port = args.to
    sc = load_scenario(args.scenario)
    key = None
    if args.signing_key:
        from onboard.app.signing import load_key
        key = load_key(args.signing_key)  # KeyFileError is a ValueError: exit 2
    cfg = LiveFeedConfig(args.mavlink, host, port, args.truth, args.seed, args.duration, args.start,
                         signing_key=key, altitude_m=args.altitude, kind=args.kind)
    log = lambda s: print(s, flush=True)  # noqa: E731
    writer = None
    if args.df == "kraken":
        from sim.stack.kraken import feed_from_args
        feed, writer = feed_from_args(args, sc, cfg, log)
    else:
        feed = LiveFeed(cfg, sc, log=log)
    feed.stop_event = stop
    try:
        return feed.run()
    finally:
        if writer is not None:
            writer.close()


if __name__ == "__main__":
    sys.exit(main())
