"""A SITL stack on loopback for ground-station work: the mock ArduCopter, the onboard app and the
live DF feed as threads of one process, nothing launched by itself (an operator, or a test,
arms, takes off and starts monitoring).

    with SitlStack(speedup=4) as st:       # ports picked by the OS
        st.gcs_url                          # tcp:127.0.0.1:PORT, a ground station's link
        st.start_feed()                     # DF scans start (when the vehicle is armed)

Or as a process, for a terminal session (docs/OPERATING.md):

    python -m sim.stack --gcs-udp 14550     # then: pmon gcs status

Used by tests/test_gcs*.py and bench/gcs_latency.py. ``pmon demo`` is the self-flying version
(separate processes, --auto-launch).
"""
from __future__ import annotations

import signal
import sys
import threading
from dataclasses import dataclass

from sim.autopilot import BootTimeline, MockAutopilot  # sets MAVLINK20 before pymavlink is imported

from onboard.app.app import AppConfig, OnboardApp
from onboard.config import load_scenario
from onboard.policy import DEFAULT as DEFAULT_POLICY
from onboard.policy import POLICIES
from sim.ardupilot import home_of
from sim.multicopter import DEMO_VEHICLE_PARAMS
from sim.feed import LiveFeed, LiveFeedConfig


@dataclass(frozen=True)
class StackConfig:
    scenario: str = "paper"
    speedup: float = 4.0
    seed: int = 1
    feed_duration_s: float = 600.0
    gcs_udp_port: int | None = None  # also stream to a GCS listening on udp 127.0.0.1:PORT
    gcs_udpin: bool = False  # also listen for a GCS on udp (port via SitlStack.udpin_port)
    runlog_path: str | None = None
    truth_path: str | None = None
    tlog_path: str | None = None
    signing_key_path: str | None = None  # MAVLink 2 signing on every link (mock, app, feed)
    ready_s: float = BootTimeline.ready_s  # autopilot s after boot until it can arm (ArduCopter's)
    policy: str = DEFAULT_POLICY  # the app's flight policy (onboard/policy.py), as pmon run's


class SitlStack:
    """Mock autopilot (TCP ports: app, feed, GCS), onboard app, DF feed (on demand)."""

    def __init__(self, cfg: StackConfig = StackConfig(), **overrides):
        from dataclasses import replace
        self.cfg = replace(cfg, **overrides)
        self.sc = load_scenario(self.cfg.scenario, POLICIES[self.cfg.policy])
        self.key = None
        if self.cfg.signing_key_path is not None:
            from onboard.app.signing import load_key
            self.key = load_key(self.cfg.signing_key_path)
        home = home_of(self.sc)  # the copter stands at the scenario's UAV start
        endpoints = ["tcpin:127.0.0.1:0"] * 3
        if self.cfg.gcs_udp_port:
            endpoints.append(f"udpout:127.0.0.1:{self.cfg.gcs_udp_port}")
        if self.cfg.gcs_udpin:
            endpoints.append("udpin:127.0.0.1:0")
        self.ap = MockAutopilot(home=home[:3], speedup=self.cfg.speedup,
                                seed=self.cfg.seed, endpoints=endpoints, params=DEMO_VEHICLE_PARAMS,
                                signing_key=self.key, boot=BootTimeline.scaled(self.cfg.ready_s))
        self.app: OnboardApp | None = None
        self.feed: LiveFeed | None = None
        self._feed_thread: threading.Thread | None = None

    @property
    def gcs_url(self) -> str:
        return f"tcp:127.0.0.1:{self.ap.port('tcpin', 2)}"

    @property
    def udpin_port(self) -> int:
        return self.ap.port("udpin", 0)

    def start(self) -> "SitlStack":
        self.ap.start()
        try:
            self.app = OnboardApp(AppConfig(f"tcp:127.0.0.1:{self.ap.port('tcpin', 0)}", sensor_port=0,
                                            seed=self.cfg.seed, runlog_path=self.cfg.runlog_path,
                                            tlog_path=self.cfg.tlog_path,
                                            signing_key_path=self.cfg.signing_key_path), self.sc).start()
        except Exception:
            self.ap.stop()
            raise
        return self

    def wait_ready(self, timeout: float = 30.0) -> bool:
        """Until the mock can arm (its boot is over) and the app has its position and origin:
        where a test of something else starts from (wall s)."""
        import time
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.ap.copter.position_ok and self.app.vehicle.ned_origin is not None \
                    and self.app.poses.latest() is not None:
                return True
            time.sleep(0.05)
        return False

    def start_feed(self) -> LiveFeed:
        """DF scans from the truth world, from the moment the vehicle is armed."""
        assert self.app is not None and self.feed is None
        self.feed = LiveFeed(LiveFeedConfig(f"tcp:127.0.0.1:{self.ap.port('tcpin', 1)}",
                                            app_port=self.app.sensor_port, seed=self.cfg.seed + 1,
                                            duration_s=self.cfg.feed_duration_s, start="armed",
                                            truth_path=self.cfg.truth_path, signing_key=self.key),
                             self.sc, log=lambda s: None)
        self._feed_thread = threading.Thread(target=self.feed.run, name="sitl-feed", daemon=True)
        self._feed_thread.start()
        return self.feed

    def stop(self) -> None:
        if self.feed is not None:
            self.feed.stop_event.set()
            if self._feed_thread is not None:
                self._feed_thread.join(timeout=5)
        if self.app is not None:
            self.app.stop()
        self.ap.stop()

    def __enter__(self) -> "SitlStack":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def main(argv=None) -> int:
    from onboard.argcheck import OUT_FILE, PORT, SEED, SPEEDUP, OneLineParser, fail, number

    p = OneLineParser(prog="python -m sim.stack", description=__doc__.split("\n")[0])
    p.add_argument("--speedup", type=SPEEDUP, default=1.0, help="autopilot s per wall s, (0, 1000] (default 1)")
    p.add_argument("--gcs-udp", type=PORT, default=14550, metavar="PORT",
                   help="stream to a ground station listening on udp 127.0.0.1:PORT (default 14550)")
    p.add_argument("--seed", type=SEED, default=1)
    p.add_argument("--ready-after", type=number(0.0, 600.0), default=BootTimeline.ready_s, metavar="S",
                   help="autopilot s after boot until the mock can arm (default "
                   f"{BootTimeline.ready_s:g}, as ArduCopter 4.4 SITL)")
    p.add_argument("--policy", choices=tuple(POLICIES), default=DEFAULT_POLICY,
                   help="the app's flight policy (pmon run --policy; default flight)")
    p.add_argument("--runlog", type=OUT_FILE, help="the app's JSONL run log")
    p.add_argument("--truth", type=OUT_FILE, help="the feed's truth JSONL")
    p.add_argument("--signing-key", metavar="FILE",
                   help="MAVLink 2 signing key file (mode 0600): mock, app and feed sign, and drop "
                   "unsigned packets; give the GCS the same file (pmon gcs --signing-key FILE)")
    args = p.parse_args(argv)
    import logging
    logging.basicConfig(level=logging.WARNING)
    from onboard.app.signing import KeyFileError
    try:
        st = SitlStack(StackConfig(speedup=args.speedup, seed=args.seed, gcs_udp_port=args.gcs_udp,
                                   runlog_path=args.runlog, truth_path=args.truth,
                                   signing_key_path=args.signing_key,
                                   ready_s=args.ready_after, policy=args.policy)).start()
    except KeyFileError as exc:
        return fail(p.prog, str(exc))
    except OSError as exc:  # a log file's directory missing, a port in use ...
        return fail(p.prog, f"cannot open {exc.filename or 'a socket'}: {exc.strerror or exc}")
    st.start_feed()
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"sitl stack up: GCS on udpin:127.0.0.1:{args.gcs_udp} or {st.gcs_url}; speedup "
          f"{args.speedup:g}{'; signed' if st.key else ''}; Ctrl-C stops", flush=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        st.stop()
        print("sitl stack stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
