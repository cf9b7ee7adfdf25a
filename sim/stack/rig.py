"""The one rig: a whole SITL stack on loopback, stood up one way for ``pmon demo``, the documented
procedure (sim/stack/procedure.py), ``python -m sim.stack.sitl_stack``, the benches and the tests.

    with Rig(RigConfig(speedup=2, auto_launch=True, out_dir="out")) as rig:
        rig.url(2)            # a ground station's MAVLink port on the autopilot
        rig.problem()         # None while every program runs, else which one ended

What runs:
- an autopilot: the mock ArduCopter (sim/mock/autopilot.py) or ArduPilot's own ArduCopter SITL
  (sim/firmware/ardupilot.py), at the scenario's UAV start, ``ports`` MAVLink TCP ports: 0 the app, 1 the
  DF feed, 2 and on ground stations and observers (sim/firmware/ardupilot.py's SERIALn order); or PX4's
  own SITL (sim/firmware/px4.py), where the same port numbers name UDP links (``PX4_PORTS``): 0 PX4's
  offboard/API link, the others its ground-station link, as on a vehicle;
- the onboard app (``pmon run``), on port 0, through a ``TcpProxy`` (PX4: ``UdpProxy``) a test can
  cut if asked;
- the live DF feed (``pmon feed live``), on port 1, sending to the app's DF port: with the rig,
  later (``start_feed``) or not at all. With ``df="kraken"`` the feed is a simulated KrakenSDR
  instead (sim/stack/kraken.py: its output served over HTTP, which the app reads with ``--kraken``); it
  starts before the app, whatever ``feed`` says (the app reads it from its start; it scans from
  the arming all the same).

Two layouts. By default every program is a process of its own, as on a vehicle (the app knows the
autopilot only through MAVLink, the feed only through its MAVLink link and UDP; and two busy
Python loops, core tick and truth step, then run on two cores instead of sharing one GIL). With
``in_process`` the mock and the app are threads of this process (``MockAutopilot``,
``OnboardApp``), for tests and benches that look inside them: the app's tick records and
counters, the setpoints the mock receives (``on_tick``, ``on_setpoint``). The feed is a process
in both: in this process its truth world held the GIL exactly while the app ticked.
"""
from __future__ import annotations

import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Callable, Mapping

from onboard.policy import DEFAULT as DEFAULT_POLICY
from sim.mock.multicopter import DEMO_VEHICLE_PARAMS
from sim.firmware.priority import app_priority, vehicle_priority, vehicle_threads

APP_PORT, FEED_PORT, GCS_PORT = 0, 1, 2  # the autopilot's MAVLink ports, by user
# PX4 (sim/firmware/px4.py): each port number as (link, listener index) on PX4's UDP links; None: a client
# that sends first (the observer, sim/stack/procedure.py)
PX4_PORTS = {0: ("api", 0), 1: ("gcs", 1), 2: ("gcs", 0), 3: ("gcs", None), 4: ("gcs", 2)}


@dataclass(frozen=True)
class RigConfig:
    scenario: str = "paper"  # name or YAML file (app and feed)
    policy: str = DEFAULT_POLICY  # the app's flight policy (pmon run --policy)
    seed: int = 1  # the app's
    feed_seed: int | None = None  # None: seed + 1
    autopilot_seed: int | None = None  # the mock's; None: seed
    autopilot: str = "mock"  # mock (sim/mock/autopilot.py) | ardupilot (the firmware's SITL) | px4 (PX4's SITL)
    binary: str | None = None  # the SITL binary, or PX4's folder (None: find_binary() / sim.firmware.px4.find_sitl())
    speedup: float = 1.0  # autopilot s per wall s
    params: Mapping[str, float] = field(default_factory=lambda: MappingProxyType(DEMO_VEHICLE_PARAMS))
    home: str = "start"  # where the copter boots: the scenario's UAV start, or its "origin"
    ready_s: float | None = None  # the mock's boot until it can arm, autopilot s (None: ArduCopter's)
    max_lag_s: float = 0.1  # the mock's clock slips rather than jump when starved (SITL-like)
    ports: int = 3  # the autopilot's MAVLink TCP ports (3..5 for ArduPilot)
    gcs_udp_out: int | None = None  # the mock also streams to a GCS listening on udp 127.0.0.1:PORT
    gcs_udpin: bool = False  # the mock also listens on a UDP port (Rig.udpin_port)
    signing_key_path: str | None = None  # MAVLink 2 signing on every link (mock, app, feed)
    in_process: bool = False  # the mock and the app as threads of this process
    auto_launch: bool = False  # pmon run --auto-launch: GUIDED, arm, take off, monitor
    app_args: tuple[str, ...] = ()  # more pmon run options (the app as a process)
    app_config: Mapping = field(default_factory=dict)  # more AppConfig fields (the app in process)
    link_proxy: bool = False  # the app reaches its port through a TcpProxy, PX4's a UdpProxy (Rig.proxy)
    feed: str = "start"  # start (with the rig) | later (Rig.start_feed) | none
    df: str = "datagram"  # the DF: datagram (the feed's UDP datagrams) | kraken (a simulated KrakenSDR)
    multipath: bool = True  # kraken: the DF model's clutter drawn as multipath peaks in its spectrum
    feed_duration_s: float | None = None  # scans sent (from feed_start); None: the scenario's mission
    # the feed's first scan (pmon feed live --start): at the arming, or once armed at the mission
    # altitude (the paper's mission: the UAV at h at t = 0, pmon demo), or "now"
    feed_start: str = "armed"
    out_dir: str | None = None  # the programs' logs; None: a temporary directory, removed at stop
    runlog_path: str | None = None  # the app's JSONL run log (None: none)
    truth_path: str | None = None  # the feed's truth JSONL (None: none)
    truth_kind: str = "nominal"  # how the feed's true targets move (sim/truth/kinds.py)
    tlog_path: str | None = None  # the app's tlog (None: none)

    def records_in(self, out: str | Path) -> "RigConfig":
        """This configuration with its logs, run log, truth and tlog in ``out`` (run.jsonl,
        truth.jsonl, app.tlog: what pmon demo and the procedure score and plot)."""
        from dataclasses import replace
        out = Path(out)
        return replace(self, out_dir=str(out), runlog_path=str(out / "run.jsonl"),
                       truth_path=str(out / "truth.jsonl"), tlog_path=str(out / "app.tlog"))


class Rig:
    """Autopilot, app and feed of one ``RigConfig``; ``start`` and ``stop`` them (or ``with``).

    ``ap``: ``MockAutopilot`` (in process), ``MockProcess`` or ``ArduPilotSitl``; ``app``:
    ``OnboardApp`` (in process) or a ``Proc``; ``feed``: a ``Proc`` once started. ``on_tick(rec)``
    hears every tick record and ``on_setpoint(t, msg)`` every SET_POSITION_TARGET_LOCAL_NED the
    mock receives (its own clock, s) before it handles it: in process only. ``link_tap(data)``, with
    ``link_proxy`` on a TCP link, hears every byte the app sends towards its autopilot."""

    def __init__(self, cfg: RigConfig = RigConfig(), on_tick: Callable[[dict], None] | None = None,
                 on_setpoint: Callable[[float, object], None] | None = None,
                 link_tap: Callable[[bytes], None] | None = None):
        from onboard.config import load_scenario
        from onboard.policy import POLICIES
        from sim.firmware.ardupilot import home_of

        if cfg.autopilot not in ("mock", "ardupilot", "px4") or cfg.feed not in ("start", "later", "none") \
                or cfg.df not in ("datagram", "kraken"):
            raise ValueError(f"rig: autopilot {cfg.autopilot!r}, feed {cfg.feed!r}, df {cfg.df!r}")
        from sim.stack.live_feed import START_MODES
        if cfg.feed_start not in START_MODES:
            raise ValueError(f"rig: feed_start {cfg.feed_start!r} (one of {', '.join(START_MODES)})")
        if cfg.df == "kraken" and cfg.feed == "none":
            raise ValueError("rig: df kraken needs the feed (the simulated KrakenSDR)")
        if cfg.in_process and cfg.autopilot != "mock":
            raise ValueError("rig: in_process needs the mock autopilot (a firmware's SITL is a program)")
        if (on_tick or on_setpoint) and not cfg.in_process:
            raise ValueError("rig: on_tick and on_setpoint look inside the app and the mock: in_process only")
        self.cfg = cfg
        self.sc = load_scenario(cfg.scenario, POLICIES[cfg.policy])
        self._tmp = None if cfg.out_dir else tempfile.mkdtemp(prefix="pmon-rig-")
        self.out = Path(cfg.out_dir or self._tmp)
        self.out.mkdir(parents=True, exist_ok=True)
        self.key = None
        if cfg.signing_key_path is not None:
            from onboard.app.signing import load_key
            self.key = load_key(cfg.signing_key_path)
        o = self.sc.origin
        self.home = home_of(self.sc) if cfg.home == "start" else (o.lat_deg, o.lon_deg, o.alt_m, 0.0)
        self.on_tick = on_tick
        self.link_tap = link_tap  # with link_proxy (TCP): hears every byte the app sends its autopilot
        self.app = None
        self.feed = None
        self.proxy = None
        self.df_port: int | None = None
        self.kraken_url: str | None = None  # df kraken: where the simulated KrakenSDR serves its output
        self._stopped = False
        self.ap = self._autopilot()
        if on_setpoint is not None:
            self._spy(on_setpoint)

    # ----- parts
    def _autopilot(self):
        cfg = self.cfg
        seed = cfg.seed if cfg.autopilot_seed is None else cfg.autopilot_seed
        # the firmware's own files (logs, parameters) in out/ when it is kept, else a temporary
        # directory of the driver's whose logs stay
        workdir = None if self._tmp else self.out / cfg.autopilot
        if cfg.autopilot == "ardupilot":
            from sim.firmware.ardupilot import ArduPilotSitl, find_binary
            return ArduPilotSitl(Path(cfg.binary) if cfg.binary else find_binary(), self.home, cfg.speedup,
                                 dict(cfg.params), ports=cfg.ports, log_path=self.out / "autopilot.log",
                                 workdir=workdir)
        if cfg.autopilot == "px4":
            from sim.firmware.px4 import Px4Sitl, find_sitl
            gcs = sum(1 for n, (link, i) in PX4_PORTS.items() if n < cfg.ports and link == "gcs" and i is not None)
            return Px4Sitl(Path(cfg.binary) if cfg.binary else find_sitl(), self.home[:3], cfg.speedup,
                           dict(cfg.params), workdir=workdir, log_path=self.out / "autopilot.log",
                           listeners={"gcs": gcs, "api": 1})
        if not cfg.in_process:
            from sim.firmware.processes import MockLinks, MockProcess
            return MockProcess(self.home, cfg.speedup, cfg.params, MockLinks(cfg.ports, cfg.gcs_udp_out, cfg.gcs_udpin),
                               self.out / "autopilot.log", seed, ready_s=cfg.ready_s,
                               signing_key_path=cfg.signing_key_path)
        from sim.mock.autopilot import BootTimeline, MockAutopilot

        endpoints = ["tcpin:127.0.0.1:0"] * cfg.ports
        if cfg.gcs_udp_out:
            endpoints.append(f"udpout:127.0.0.1:{cfg.gcs_udp_out}")
        if cfg.gcs_udpin:
            endpoints.append("udpin:127.0.0.1:0")
        return MockAutopilot(home=self.home[:3], speedup=cfg.speedup, seed=seed, endpoints=endpoints,
                             params=dict(cfg.params), signing_key=self.key, max_lag_s=cfg.max_lag_s,
                             boot=BootTimeline() if cfg.ready_s is None else BootTimeline.scaled(cfg.ready_s))

    def _spy(self, on_setpoint) -> None:
        self.ap.watch("SET_POSITION_TARGET_LOCAL_NED", lambda msg: on_setpoint(self.ap.copter.t, msg))

    def start_autopilot(self):
        self.ap.start()
        if self.cfg.in_process:  # the mock's simulation thread, as its process would be
            vehicle_threads(self.ap._thread)
        return self.ap

    def start_app(self) -> None:
        """The app on port 0 (or through the proxy); its DF port in ``df_port``."""
        cfg = self.cfg
        url = self.url(APP_PORT)
        if cfg.link_proxy and cfg.autopilot == "px4":  # a UDP link: the relay takes the app's port
            from sim.stack.udp_proxy import UdpProxy
            self.proxy = UdpProxy(int(url.rsplit(":", 1)[1]))
            url = self.proxy.url
        elif cfg.link_proxy:
            from sim.stack.tcp_proxy import TcpProxy
            self.proxy = TcpProxy(("127.0.0.1", self.port(APP_PORT)), tap=self.link_tap)
            url = f"tcp:127.0.0.1:{self.proxy.port}"
        if cfg.in_process:
            from onboard.app.app_config import AppConfig
            from onboard.app.app import OnboardApp
            from onboard.config import override
            sc = self.sc if self.kraken_url is None else override(self.sc, {"kraken.url": self.kraken_url})
            extra = {"rt_priority": app_priority(), **dict(cfg.app_config)}
            self.app = OnboardApp(AppConfig(url, sensor_port=0, auto_launch=cfg.auto_launch, seed=cfg.seed,
                                            runlog_path=cfg.runlog_path, tlog_path=cfg.tlog_path,
                                            signing_key_path=cfg.signing_key_path, kraken=self.kraken_url is not None,
                                            **extra), sc)
            if self.on_tick is not None:
                self.app.tick_listeners.append(self.on_tick)
            self.app.start()
            self.df_port = self.app.sensor_port
            return
        from sim.firmware.processes import Proc
        argv = [sys.executable, "-m", "onboard.cli", "run", "--mavlink", url, "--df", "127.0.0.1:0",
                "--scenario", cfg.scenario, "--seed", str(cfg.seed), "--policy", cfg.policy]
        for option, value in (("--runlog", cfg.runlog_path), ("--tlog", cfg.tlog_path),
                              ("--signing-key", cfg.signing_key_path)):
            argv += [option, str(value)] if value is not None else []
        argv += ["--auto-launch"] if cfg.auto_launch else []
        if cfg.autopilot == "px4" and (events := self.ap.events_metadata()) is not None:
            argv += ["--px4-events", str(events)]  # the build's: its EVENTs in words
        argv += ["--kraken", self.kraken_url] if self.kraken_url is not None else []
        argv += ["--rt-priority", str(app_priority())] if app_priority() else []  # app_args may change it
        self.app = Proc("app", argv + list(cfg.app_args), self.out / "app.log")
        self.df_port = int(self.app.wait_line(r"DF datagrams on udp 127\.0\.0\.1:(\d+)", 30).group(1))

    def start_feed(self):
        """``pmon feed live`` on port 1 to the app's DF port (or, ``df="kraken"``, as a KrakenSDR
        serving its output: started before the app, and this returns it): scans from the moment
        the vehicle is armed (``feed_start``: or armed at h), ``feed_duration_s`` of them. The
        feed's ``Proc``."""
        from sim.firmware.processes import Proc

        cfg = self.cfg
        if cfg.df == "kraken" and self.feed is not None:
            return self.feed
        assert self.feed is None and (self.app is not None or cfg.df == "kraken")
        seed = cfg.seed + 1 if cfg.feed_seed is None else cfg.feed_seed
        duration = cfg.feed_duration_s if cfg.feed_duration_s is not None else self.sc.mission.duration_s
        argv = [sys.executable, "-m", "sim.stack.feed", "live", "--mavlink", self.url(FEED_PORT),
                "--scenario", cfg.scenario, "--seed", str(seed), "--duration", f"{duration:g}",
                "--start", cfg.feed_start, "--kind", cfg.truth_kind]
        if cfg.df == "kraken":
            argv += ["--df", "kraken", "--kraken-dir", str(self.out / "kraken"),
                     "--multipath", "on" if cfg.multipath else "off"]
        else:
            argv += ["--to", f"127.0.0.1:{self.df_port}"]
        for option, value in (("--truth", cfg.truth_path), ("--signing-key", cfg.signing_key_path)):
            argv += [option, str(value)] if value is not None else []
        self.feed = Proc("feed", argv, self.out / "feed.log", vehicle_priority())
        if cfg.df == "kraken":
            self.kraken_url = self.feed.wait_line(r"KrakenSDR output at (\S+)", 30).group(1)
        return self.feed

    # ----- lifecycle
    def start(self) -> "Rig":
        """Autopilot, app, and the feed if ``feed`` is "start"; what started is stopped again
        when a part fails to."""
        try:
            self.start_autopilot()
            if self.cfg.df == "kraken":  # the KrakenSDR serves before the app reads it
                self.start_feed()
            self.start_app()
            if self.cfg.feed == "start":
                self.start_feed()
        except BaseException:
            self.stop()
            raise
        return self

    def stop_programs(self) -> None:
        """Stop the feed and the app, once (the autopilot runs on: ``stop`` ends it)."""
        if self._stopped:
            return
        self._stopped = True
        if self.feed is not None:
            self.feed.stop(timeout=10)
        if self.app is not None:
            self.app.stop() if self.cfg.in_process else self.app.stop(timeout=10)

    def stop(self) -> None:
        self.stop_programs()
        if self.proxy is not None:
            self.proxy.close()
        self.ap.stop()
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> "Rig":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ----- addresses and health
    def port(self, serial: int) -> int:
        """The autopilot's MAVLink TCP port ``serial`` (APP_PORT, FEED_PORT, GCS_PORT, ...)."""
        return self.ap.port("tcpin", serial) if self.cfg.in_process else self.ap.port(serial)

    def url(self, serial: int) -> str:
        """The MAVLink URL of port ``serial`` (PX4: a UDP link, ``PX4_PORTS``)."""
        if self.cfg.autopilot == "px4":
            link, i = PX4_PORTS[serial]
            return self.ap.talk_url(link) if i is None else self.ap.url(link, i)
        return f"tcp:127.0.0.1:{self.port(serial)}"

    @property
    def gcs_url(self) -> str:
        """A ground station's link (``pmon gcs --connect``)."""
        return self.url(GCS_PORT)

    @property
    def udpin_port(self) -> int:
        """The mock's UDP port for a ground station (``gcs_udpin``)."""
        return self.ap.port("udpin", 0) if self.cfg.in_process else self.ap.udpin_port

    def problem(self) -> str | None:
        """None while the autopilot and the app run, else one line saying which ended (the feed
        ends by itself when its scans run out: its exit code is the caller's to read)."""
        if self.app is not None and not self.cfg.in_process and self.app.p.poll() is not None:
            return f"the app exited (code {self.app.p.returncode}); see {self.app.log.name}"
        if not self.cfg.in_process and not self.ap.running:
            return f"the autopilot exited; see {self.out / 'autopilot.log'}"
        return None

    def wait_ready(self, timeout: float = 30.0) -> bool:
        """In process: until the mock can arm (its boot is over) and the app has its position and
        origin: where a test of something else starts from (wall s)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.ap.copter.position_ok and self.app.vehicle.ned_origin is not None \
                    and self.app.poses.latest() is not None:
                return True
            time.sleep(0.05)
        return False

