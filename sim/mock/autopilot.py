"""Mock ArduCopter autopilot speaking MAVLink 2, for software-in-the-loop tests.

It behaves, on the wire, like a stock ArduCopter SITL as far as pmon and ordinary
clients (pymavlink, MAVProxy, MAVSDK) can tell:

- several endpoints at once (UDP out/in, TCP servers), routed like ArduPilot's
  MAVLink_routing: routes are learned per (sysid, compid), targeted messages go to the
  link that component was seen on, broadcasts go to every other link with a route,
  heartbeats to every other active link; only parseable messages are forwarded;
- HEARTBEAT, COMMAND_LONG/COMMAND_INT with ArduPilot's COMMAND_ACK results, SET_MODE,
  parameters, an empty mission, SET_POSITION_TARGET_* with ArduPilot's type_mask rules;
- telemetry only as asked for, as ArduCopter does: a HEARTBEAT a second, and each link's streams
  at the rates of its SRn_ parameters (0 by default, as in ArduCopter SITL) or as a client
  sets them (SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM);
- ArduCopter's boot (``BootTimeline``, measured on its 4.4 SITL): no GPS position, no EKF origin
  and arming refused ("Arm: Need Position Estimate") until the EKF is ready, ~43 s;
- its defects a client must not trigger: a COMMAND_LONG take-off, home or ROI whose position
  fields are NaN aborts an armed ArduCopter 4.4 (floating point exception); the mock counts it
  (``defects``) and goes silent like the crashed firmware;
- modes GUIDED, LOITER, BRAKE, POSHOLD, ALT_HOLD, STABILIZE (hold), RTL, LAND;
- its own clock: time_boot_ms runs at `speedup` x wall time and the kinematic model
  (sim.mock.multicopter, local NED with origin = home) is stepped at a fixed rate on that clock.

The parts: sim/mock/copter.py (modes, boot, the flight state machine), sim/mock/copter_params.py
(the parameters), sim/mock/links.py (endpoints and links), sim/mock/routing.py (reading links,
routing, dispatch on message type, fault injection), and the parts that answer messages, each
given the shared ``MockContext`` (sim/mock/context.py: their contract): sim/mock/commands.py
(commands and position targets), sim/mock/messages.py (streams, their requests and the messages
built), sim/mock/stores.py (parameter protocol, missions, FTP); this module the mock's
lifecycle, clock and loop around them, and the program.

Geodetic <-> local conversions use pymap3d; the local frame is NED (MAVLink's), and
`AutopilotState.pos_enu` gives the ENU mission frame of the core.

Run in-process (``with MockAutopilot(...) as ap:``) or as a process::

    python -m sim.mock.autopilot --udp 127.0.0.1:14550 --tcp 127.0.0.1:5760 \
        --speedup 5 --home=-35.363261,149.165230,584
"""

from __future__ import annotations

import argparse
import logging
import math
import select
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterable, Mapping, Optional, Sequence

import numpy as np

from onboard.app.mavlink2 import mavlink
from sim.mock.commands import Commands
from sim.mock.context import MockContext
from sim.mock.routing import Router
from sim.mock.stores import Stores
from sim.mock.messages import Telemetry
from sim.mock.copter import BootTimeline, Copter
from sim.mock.copter_params import Params
from sim.mock.copter import Mode  # noqa: F401  (the mock's API: MockAutopilot, BootTimeline, Mode)
from sim.mock.links import Endpoint, _Link, _TcpLink, _TcpListener, _UdpLink, _check_loopback
from sim.mock.multicopter import Vec3

log = logging.getLogger("sim.mock.autopilot")

@dataclass(frozen=True)
class AutopilotState:
    """Snapshot of the mock for tests (SI units, radians, degrees only for lat/lon)."""

    time_boot_ms: int
    mode: int
    mode_name: str
    armed: bool
    landed_state: int
    pos_ned: Vec3  # m, local NED, origin = home
    vel_ned: Vec3
    pos_enu: Vec3  # m, local ENU (the core's mission frame at this origin)
    vel_enu: Vec3
    yaw: float  # rad, heading from north, clockwise
    lat: float  # deg
    lon: float  # deg
    alt_amsl: float  # m
    alt_rel: float  # m above home



# --------------------------------------------------------------------------- the mock

class MockAutopilot:
    """A mock ArduCopter on MAVLink 2, run by a background thread.

    Args:
        home: (lat deg, lon deg, alt m AMSL); also the local NED origin.
        endpoints: "udpout:HOST:PORT" (send to a listening client, like SITL --out),
            "udpin:HOST:PORT" (listen; replies go to the last sender) and
            "tcpin:HOST:PORT" (TCP server; every accepted client is its own link);
            loopback hosts only; port 0 picks a free port (see `endpoints`).
        speedup: autopilot seconds per wall second.
        physics_hz: model step rate on the autopilot clock.
        params: parameter overrides, ArduPilot units (e.g. {"WPNAV_SPEED": 500}); the
            stream rates of endpoint n (its "serial port") are SRn_EXT_STAT, SRn_POSITION,
            SRn_EXTRA1..3 (Hz, 0 by default: only HEARTBEAT is sent unasked, as ArduCopter
            SITL does). Streamable: HEARTBEAT, SYS_STATUS, GPS_RAW_INT, EXTENDED_SYS_STATE,
            GLOBAL_POSITION_INT, LOCAL_POSITION_NED, ATTITUDE, VFR_HUD, SYSTEM_TIME,
            BATTERY_STATUS, EKF_STATUS_REPORT, HOME_POSITION, GPS_GLOBAL_ORIGIN,
            AUTOPILOT_VERSION, POSITION_TARGET_LOCAL_NED, POSITION_TARGET_GLOBAL_INT. Clients
            change them per link with SET_MESSAGE_INTERVAL and REQUEST_DATA_STREAM.
        boot: when the GPS, the EKF origin and arming become ready (``BootTimeline``: ArduCopter
            4.4's by default; ``BootTimeline.scaled(s)`` for a shorter wait).
        seed: seed of the position-noise generator; pos_noise: m/sqrt(s), 0 disables.
        unix_time0: UNIX time (s) at boot for SYSTEM_TIME; default: wall clock at start.
        signing_key: 32-byte MAVLink 2 signing key (onboard/app/signing.py): every link signs
            what it sends and drops unsigned or wrongly signed packets (counted
            ``signing_rejected``), like ArduPilot with a key set.
        max_lag_s: autopilot seconds the model may fall behind the wall clock before the
            clock slips (counted ``clock_slips``) instead of catching up. ArduPilot SITL runs
            slower than --speedup when the machine cannot keep up; set this small (e.g. 0.1)
            to behave the same on a loaded machine.
    """

    def __init__(
        self,
        home: tuple[float, float, float] = (-35.363261, 149.165230, 584.0),
        endpoints: Iterable[str | Endpoint] = ("tcpin:127.0.0.1:5760",),
        speedup: float = 1.0,
        physics_hz: float = 50.0,
        params: Mapping[str, float] = {},
        seed: int = 0,
        pos_noise: float = 0.02,
        unix_time0: Optional[float] = None,
        sysid: int = 1,
        compid: int = mavlink.MAV_COMP_ID_AUTOPILOT1,
        signing_key: Optional[bytes] = None,
        max_lag_s: float = 10.0,
        boot: BootTimeline = BootTimeline(),
    ):
        if not speedup > 0 or not physics_hz > 0:
            raise ValueError("speedup and physics_hz must be positive")
        self.sysid = sysid
        self.compid = compid
        self.speedup = float(speedup)
        self.max_lag_s = float(max_lag_s)
        self.signing_key = signing_key
        self._link_ids = 0
        self.dt = 1.0 / physics_hz
        self._endpoints = [e if isinstance(e, Endpoint) else Endpoint.parse(e) for e in endpoints]
        for ep in self._endpoints:
            _check_loopback(ep.host)
        self.params = Params(overrides=params)
        self.copter = Copter(home, self.params, np.random.default_rng(seed), pos_noise, boot)
        self.crashed: str | None = None  # why the mock went silent like the crashed firmware
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._links: list[_Link] = []
        self._listeners: list[_TcpListener] = []
        self._bound: list[Endpoint] = []
        self._counters: dict[str, int] = {}
        self._wall0 = 0.0
        self.ctx = MockContext(sysid, compid, self.copter, self.params,
                               mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid),
                               self._links, self._counters, self._crash)
        self.telemetry = Telemetry(self.ctx, unix_time0)
        self.parts = (self.telemetry, Commands(self.ctx, self.telemetry), Stores(self.ctx, self.telemetry))
        self.router = Router(self.ctx, self.parts)

    # ----- lifecycle
    def start(self) -> "MockAutopilot":
        """Bind every endpoint (raises OSError if a port is taken) and start the thread."""
        if self._thread is not None:
            raise RuntimeError("already started")
        self._bound = []
        try:
            self._open_endpoints()
        except Exception:
            self._close_all()
            raise
        self._wall0 = time.monotonic()
        if self.telemetry.unix_time0 is None:
            self.telemetry.unix_time0 = time.time()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="mock-autopilot", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close every socket (ports are free when this returns)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._close_all()

    def __enter__(self) -> "MockAutopilot":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def run_forever(self) -> None:
        """Run until stop() is called from another thread or a signal handler."""
        self.start()
        try:
            while not self._stop.wait(0.2):
                pass
        finally:
            self.stop()

    # ----- public observers
    @property
    def endpoints(self) -> list[Endpoint]:
        """The endpoints as bound (port 0 replaced by the port actually chosen)."""
        return list(self._bound)

    def port(self, kind: str, index: int = 0) -> int:
        """Bound port of the index-th endpoint of a kind ('udpout' gives its target port)."""
        return [e for e in self._bound if e.kind == kind][index].port

    @property
    def sim_time(self) -> float:
        """Autopilot time since boot, s."""
        with self._lock:
            return self.copter.t

    def state(self) -> AutopilotState:
        with self._lock:
            c = self.copter
            s = c.state
            lat, lon, alt = c.geodetic_from_ned(s.pos)
            return AutopilotState(
                time_boot_ms=int(c.t * 1000),
                mode=int(c.mode),
                mode_name=c.mode.name,
                armed=c.armed,
                landed_state=c.landed_state(),
                pos_ned=s.pos,
                vel_ned=s.vel,
                pos_enu=(s.pos[1], s.pos[0], -s.pos[2]),
                vel_enu=(s.vel[1], s.vel[0], -s.vel[2]),
                yaw=s.yaw,
                lat=lat,
                lon=lon,
                alt_amsl=alt,
                alt_rel=c.alt_above_home(),
            )

    def counters(self) -> dict[str, int]:
        """Copy of the event counters (rx, tx, bad_data, unknown_msgid, forwarded, ...)."""
        with self._lock:
            return dict(self._counters)

    def routes(self) -> set[tuple[int, int, str]]:
        """Learned routes as (sysid, compid, link name)."""
        with self._lock:
            return {(s, c, link.name) for s, c, link in self.router.routes}

    def watch(self, mtype: str, see: Callable[[object], None]) -> None:
        """Call ``see(msg)`` (on the mock's thread) before the mock handles each message of
        type ``mtype`` addressed to it, e.g. to record the setpoints a client sends."""
        with self._lock:
            self.router.watch(mtype, see)

    # ----- fault injection (tests)
    def cut_link(self, compid: int, seconds: float) -> int:
        """The link(s) a component is reached on go dead both ways for ``seconds`` of
        autopilot time (a radio out of range): nothing is read or written, the TCP connection
        stays up. Returns the number of links cut."""
        with self._lock:
            return self.router.cut(compid, seconds)

    def drop_link(self, compid: int) -> int:
        """Close the link(s) of a component (a TCP client must reconnect)."""
        with self._lock:
            return self.router.drop(compid)

    def wait_until(self, predicate: Callable[[AutopilotState], bool], timeout: float) -> bool:
        """Poll state() until predicate holds or `timeout` wall seconds pass."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate(self.state()):
                return True
            time.sleep(0.01)
        return predicate(self.state())

    # ----- plumbing
    def _count(self, key: str, n: int = 1) -> None:
        self.ctx.count(key, n)

    def _open_endpoints(self) -> None:
        for index, ep in enumerate(self._endpoints):
            if ep.kind == "tcpin":
                lst = _TcpListener(ep, index)
                self._listeners.append(lst)
                self._bound.append(Endpoint("tcpin", ep.host, lst.local[1]))
            else:
                link = self._secure(_UdpLink(ep, self.sysid, self.compid, self.telemetry.default_intervals(index)))
                link.port_index = index
                self._links.append(link)
                port = link.local[1] if ep.kind == "udpin" else ep.port
                self._bound.append(Endpoint(ep.kind, ep.host, port))

    def _close_all(self) -> None:
        for link in self._links:
            link.close()
        for lst in self._listeners:
            lst.close()
        self._links.clear()  # the list the parts share (MockContext.links)
        self._listeners = []
        self.router.routes.clear()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._iterate()
            except Exception:  # never let one bad iteration kill the autopilot
                with self._lock:
                    self._count("loop_errors")
                log.exception("mock autopilot loop error")
                time.sleep(0.01)

    def _iterate(self) -> None:
        sim_now = (time.monotonic() - self._wall0) * self.speedup
        with self._lock:
            steps = 0
            while self.copter.t + self.dt <= sim_now and steps < 500:
                self.copter.tick(self.dt)
                steps += 1
            if steps == 500:  # far behind (debugger, overload): skip instead of spiralling
                self._count("clock_skips")
                self._wall0 = time.monotonic() - self.copter.t / self.speedup
            elif sim_now - self.copter.t > self.max_lag_s:  # SITL-like: run slower, never jump
                self._count("clock_slips")
                self._wall0 = time.monotonic() - self.copter.t / self.speedup
            now_t = self.copter.t
            for link in self._links:
                link.muted = now_t < link.muted_until
            for part in self.parts:
                part.periodic(now_t)
            for link in self._links:
                link.flush()
        next_step_wall = self._wall0 + (self.copter.t + self.dt) / self.speedup
        timeout = min(max(next_step_wall - time.monotonic(), 0.0), 0.02)
        socks = [*self._links, *self._listeners]
        try:
            readable, _, _ = select.select(socks, [], [], timeout)
        except (OSError, ValueError):
            readable = []  # a socket closed under us; the next iteration drops it
        with self._lock:
            for obj in readable:
                if isinstance(obj, _TcpListener):
                    self._accept(obj)
                else:
                    self.router.read(obj)
            dead = [link for link in self._links if link.closed]
            for link in dead:
                self._links.remove(link)
                self.router.forget(link)
                self._count("links_closed")

    def _accept(self, lst: _TcpListener) -> None:
        got = lst.accept()
        if got is None:
            return
        sock, addr = got
        name = f"tcpin:{lst.local[0]}:{lst.local[1]}<-{addr[0]}:{addr[1]}"
        link = self._secure(_TcpLink(sock, name, self.sysid, self.compid,
                                     self.telemetry.default_intervals(lst.index)))
        link.port_index = lst.index
        self._links.append(link)
        self._count("links_opened")

    def _secure(self, link: _Link) -> _Link:
        if self.signing_key is not None:
            from onboard.app.signing import configure
            self._link_ids += 1
            configure(link.parser, self.signing_key, self._link_ids, sign_outgoing=False)
            configure(link.out, self.signing_key, self._link_ids)
        return link

    def _crash(self, why: str) -> None:
        """A defect the real firmware dies of: counted, logged, and the mock falls silent and
        drops every link (the process of a crashed SITL is gone)."""
        self._count("defects")
        self.crashed = why
        log.error("mock autopilot: defect that crashes ArduCopter 4.4: %s", why)
        for lk in self._links:
            lk.flush()
            lk.close()
        self._stop.set()


# --------------------------------------------------------------------------- CLI

def _parse_home(text: str) -> tuple[float, float, float]:
    try:
        lat, lon, alt = (float(v) for v in text.split(","))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--home wants LAT,LON,ALT, got {text!r}") from exc
    if not (-90 <= lat <= 90 and -180 <= lon <= 180 and math.isfinite(alt)):
        raise argparse.ArgumentTypeError(f"--home out of range: {text!r}")
    return (lat, lon, alt)


def main(argv: Optional[Sequence[str]] = None) -> int:
    from onboard.argcheck import HOST_PORT, HOST_PORT_BIND, SEED, SPEEDUP, OneLineParser, fail, number, param_item

    ap = OneLineParser(prog="python -m sim.mock.autopilot", description=__doc__.split("\n\n")[0])
    ap.add_argument("--udp", action="append", default=[], metavar="HOST:PORT", type=HOST_PORT,
                    help="send to a UDP listener (like SITL --out); repeatable")
    ap.add_argument("--udpin", action="append", default=[], metavar="HOST:PORT", type=HOST_PORT_BIND,
                    help="listen on UDP; replies go to the last sender; repeatable")
    ap.add_argument("--tcp", action="append", default=[], metavar="HOST:PORT", type=HOST_PORT_BIND,
                    help="TCP server port; repeatable")
    ap.add_argument("--speedup", type=SPEEDUP, default=1.0, help="autopilot s per wall s, (0, 1000]")
    ap.add_argument("--home", type=_parse_home, default=(-35.363261, 149.165230, 584.0),
                    help="LAT,LON,ALT (deg, deg, m AMSL), written --home=LAT,... when LAT < 0; "
                    "default ArduPilot's CMAC")
    ap.add_argument("--seed", type=SEED, default=0)
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", type=param_item,
                    help="parameter override in ArduPilot units; repeatable")
    ap.add_argument("--signing-key", metavar="FILE",
                    help="MAVLink 2 signing key file (64 hex chars, mode 0600): sign everything, "
                    "drop unsigned or wrongly signed packets")
    ap.add_argument("--ready-after", type=number(0.0, 600.0), default=BootTimeline.ready_s, metavar="S",
                    help="autopilot s after boot until it can arm (GPS and EKF origin earlier, in "
                    f"proportion); default {BootTimeline.ready_s:g}, as ArduCopter 4.4 SITL")
    ap.add_argument("--max-lag", type=number(0.0, 3600.0, lo_open=True), default=10.0, metavar="S",
                    help="autopilot s the model may fall behind before the clock slips "
                    "(small: run slower than --speedup on a loaded machine, like SITL)")
    args = ap.parse_args(argv)
    endpoints = ([f"udpout:{h}:{p}" for h, p in args.udp] + [f"udpin:{h}:{p}" for h, p in args.udpin]
                 + [f"tcpin:{h}:{p}" for h, p in args.tcp]) or ["tcpin:127.0.0.1:5760"]
    try:
        overrides = dict(args.param)
        key = None
        if args.signing_key:
            from onboard.app.signing import load_key
            key = load_key(args.signing_key)
        mock = MockAutopilot(home=args.home, endpoints=endpoints, speedup=args.speedup,
                             params=overrides, seed=args.seed, signing_key=key,
                             max_lag_s=args.max_lag, boot=BootTimeline.scaled(args.ready_after))
        mock.start()
    except KeyError as exc:  # Params: unknown parameter 'NAME'
        return fail(ap.prog, str(exc.args[0] if exc.args else exc))
    except (ValueError, OSError) as exc:
        return fail(ap.prog, str(exc))
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print("mock autopilot up: " + " ".join(str(e) for e in mock.endpoints), flush=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        mock.stop()
        print(f"mock autopilot stopped: {mock.counters()}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
