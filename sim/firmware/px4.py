"""PX4's own SITL firmware (SIH quadrotor, headless) as a child process: the real PX4 autopilot
for conformance tests and benches, as sim/firmware/ardupilot.py is for ArduCopter.

    sitl = Px4Sitl(find_sitl(), home=(35.1468, 33.4126, 160.0), speed=2).start()
    sitl.url("api")         # udpin:127.0.0.1:P: the companion's link (PX4's offboard/API link)
    sitl.url("gcs")         # udpin:127.0.0.1:Q: a ground station where PX4 would send (its 14550)
    sitl.talk_url("gcs")    # udpout:127.0.0.1:R: any number of clients that speak first
    sitl.restart()          # SIGTERM, then boot again on the same instance, workdir and ports
    sitl.stop()             # the console log and the ULogs stay (``log_file``, ``ulogs()``)

The build is a folder with PX4's ``run-sih.sh`` (``../shared/px4/``: PX4 v1.16.0
``px4_sitl_default``; its README has what was measured on it). Each instance gets a PX4 instance
number ``-i N`` no other PX4 holds (PX4's machine-wide lock /tmp/px4_lock-N, probed, and a pmon
lock file held while it runs) and a working directory of its own (parameters, dataman, ULogs:
fresh per start unless given).

**Network.** PX4 binds its MAVLink UDP ports on all interfaces and every instance's ground
station link sends to 127.0.0.1:14550. So PX4 runs in a network namespace of its own whose only
interface is loopback (sim/firmware/netns.py: root, or unprivileged user namespaces), and each MAVLink
link is relayed to a UDP socket on the host's 127.0.0.1 that this process binds to a free port
and keeps across restarts. Nothing of PX4 is reachable from outside the machine, parallel
instances cannot collide, and clients use plain loopback URLs. A link's datagrams go to each of
its ``listeners`` ports (clients that wait for the autopilot, as a companion does on PX4's
14540: ``url(link, i)``) and to every client that sent to the link's own port in the last 120 s
(``talk_url``: MAVProxy, anything that sends a heartbeat first); PX4 sees one
peer per link, as behind mavlink-router on a vehicle.

**Parameters.** ``params`` go to PX4's rcS as ``PX4_PARAM_NAME`` and again after rcS's own
settings, before any flight module starts: rcS sources ``px4-rc.sihsim`` through the PATH, whose
first entry is the working directory's ``bin/``, so the driver writes one there that sets them and
then sources PX4's own. They win over rcS's multi-instance and speed-factor settings. That file
also sets MAV_SYS_ID (``sysid``, default 1 as on a vehicle, not SITL's N + 1: set any later and
commander keeps N + 1 and ignores commands to 1) and, at a speed factor other than 1, resets to
PX4's defaults the four link-loss timeouts rcS multiplies by the factor (COM_DL_LOSS_T,
COM_RC_LOSS_T, COM_OF_LOSS_T, COM_OBC_LOSS_T): PX4's clock is the simulation's (lockstep), so
its defaults are already faithful for a client that runs on the autopilot's clock, as pmon does.

As a program, for a terminal session (docs/SITL.md)::

    python -m sim.firmware.px4 --speed 1 --param COM_OBL_RC_ACT=5      # prints the URLs
"""
from __future__ import annotations

import argparse
import contextlib
import fcntl
import functools
import glob
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from onboard.argcheck import param_item
from sim.firmware.priority import fifo_argv, vehicle_priority
from sim.firmware.processes import log_tail

ENV_VAR = "PMON_PX4_SITL"
REPO = Path(__file__).resolve().parents[2]
SHARED_DIR = REPO.parent / "shared" / "px4"  # beside the checkout
WORKPLACE_DIR = Path("/work/shared/px4")  # the workplace's copy (.ci/run names it too)
SCRIPT = "run-sih.sh"
FIRST_INSTANCE = 20  # tried from here up: leaves 0.. to a developer's own PX4 SITL
LAST_INSTANCE = 99
BOOT_LINE = "Startup script returned successfully"
BOOT_TIMEOUT_S = 30.0  # wall s from the process to PX4's startup script done
# the link-loss timeouts rcS multiplies by PX4_SIM_SPEED_FACTOR (etc/init.d-posix/rcS)
SPEED_SCALED_PARAMS = ("COM_DL_LOSS_T", "COM_RC_LOSS_T", "COM_OF_LOSS_T", "COM_OBC_LOSS_T")


# what a vehicle flown by pmon is set up with (docs/SITL.md): when the app's setpoints stop (the
# app or its link gone), Hold instead of PX4's default Position mode, which without RC sinks
# (measured: 46 -> 24 m above home in ~20 s)
RECOMMENDED_PARAMS = {"COM_OBL_RC_ACT": 5}


class SitlError(RuntimeError):
    """PX4 SITL could not be started or stopped; the message says why in one line."""


def links_of(instance: int) -> dict[str, tuple[int, int]]:
    """PX4's MAVLink UDP links (etc/init.d-posix/px4-rc.mavlink) on instance N, in its namespace:
    name -> (port PX4 listens on, port it sends to)."""
    return {"gcs": (18570 + instance, 14550),
            "api": (14580 + instance, 14540 + instance if instance <= 9 else 14549),
            "payload": (14280 + instance, 14030 + instance)}


def find_sitl() -> Path | None:
    """The folder holding ``run-sih.sh``: ``$PMON_PX4_SITL`` (the folder or the script) if set,
    else ``../shared/px4/`` beside the checkout, else the workplace's /work/shared/px4, else None."""
    env = os.environ.get(ENV_VAR)
    if env:
        p = Path(env)
        return p.parent if p.name == SCRIPT or p.is_file() else p
    for d in (SHARED_DIR, WORKPLACE_DIR):
        if (d / SCRIPT).is_file():
            return d
    return None


@functools.lru_cache(maxsize=1)
def namespace_problem() -> str | None:
    """Why no network namespace can be made here (one line), or None (checked once, in a child)."""
    p = subprocess.run([sys.executable, "-m", "sim.firmware.netns", "--check"], capture_output=True, text=True,
                       cwd=REPO, timeout=30)
    return None if p.returncode == 0 else (p.stderr.strip().splitlines() or ["failed"])[-1]


def skip_reason() -> str | None:
    """Why the PX4 tests cannot run here (one line), or None."""
    d = find_sitl()
    if d is None:
        return (f"no PX4 SITL: set {ENV_VAR} to a folder with PX4's {SCRIPT} and bin/px4 "
                f"(px4_sitl_default, v1.16; ../shared/px4/README.md says how it was built)")
    if not (d / SCRIPT).is_file() or not os.access(d / "bin" / "px4", os.X_OK):
        return f"{ENV_VAR}={d}: no {SCRIPT} and executable bin/px4 there"
    if (why := namespace_problem()) is not None:
        return f"PX4 SITL runs in a network namespace of its own (it binds all interfaces): {why}"
    return None


def home_of(scenario) -> tuple[float, float, float]:
    """The scenario's UAV start on the ground (deg, deg, m AMSL), as PX4_HOME_LAT/LON/ALT take it."""
    from sim.firmware.ardupilot import home_of as ardupilot_home
    return ardupilot_home(scenario)[:3]


def _px4_lock_free(instance: int) -> bool:
    """PX4 holds a POSIX record lock on /tmp/px4_lock-N while instance N runs: probe it (and
    leave N to its owner where another user's PX4 left its lock or socket file there)."""
    path = Path(tempfile.gettempdir()) / f"px4_lock-{instance}"
    if path.exists() and not os.access(path, os.W_OK):  # another user's: PX4 could not open it
        return False
    sock = path.with_name(f"px4-sock-{instance}")  # left by a run of another user: PX4 cannot replace it
    with contextlib.suppress(OSError):
        if sock.lstat().st_uid != os.getuid():
            return False
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        return False
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)  # releases the probe's lock


@dataclass
class Px4Sitl:
    """One PX4 SITL (SIH quad) process in its own network namespace. ``home`` = (lat deg, lon deg,
    alt m AMSL); ``speed``: PX4_SIM_SPEED_FACTOR (simulated s per wall s)."""

    folder: Path
    home: tuple[float, ...] = (47.397743, 8.545593, 488.9)  # PX4's SIH default
    speed: float = 1.0
    params: Mapping[str, float] = field(default_factory=dict)
    instance: int | None = None  # None: the first free one from FIRST_INSTANCE
    workdir: Path | None = None  # None: a new temporary directory (its logs stay after stop)
    log_path: Path | None = None  # PX4's console output (None: workdir/px4.log)
    listeners: Mapping[str, int] = field(default_factory=lambda: {"gcs": 1, "api": 1})
    sysid: int | None = 1  # MAV_SYS_ID (None: SITL's instance + 1)
    stock_timeouts: bool = True  # undo rcS's speed-factor scaling of the link-loss timeouts
    proc: subprocess.Popen | None = field(default=None, init=False)
    boots: int = field(default=0, init=False)

    def __post_init__(self):
        self.folder = Path(self.folder)
        if not 0 < self.speed <= 50:
            raise SitlError(f"speed must be in (0, 50], got {self.speed}")
        for link, n in self.listeners.items():
            if link not in links_of(0) or not 0 <= n <= 8:
                raise SitlError(f"listeners: {link}={n}: links are {sorted(links_of(0))}, 0..8 each")
        self._lock = None
        self._own_dir = False
        self._host: dict[str, socket.socket] = {}
        self._push: dict[str, list[int]] = {}

    # ----- lifecycle
    def start(self) -> "Px4Sitl":
        if self.proc is not None:
            return self
        if not (self.folder / SCRIPT).is_file():
            raise SitlError(f"{self.folder}: no {SCRIPT} (a PX4 px4_sitl_default build folder)")
        if self.workdir is None:
            self.workdir = Path(tempfile.mkdtemp(prefix="pmon-px4-"))
            self._own_dir = True
        self.workdir = Path(self.workdir).resolve()
        self.workdir.mkdir(parents=True, exist_ok=True)
        try:
            if self._lock is None:
                self._claim_instance()
            if not self._host:
                self._open_host_side()
            self._boot()
        except BaseException:
            self.stop()
            raise
        return self

    def restart(self, down_s: float = 0.0) -> None:
        """Stop PX4 (SIGTERM: it shuts down) and boot it again on the same instance, working
        directory (its parameters kept) and host ports, after ``down_s`` wall seconds down."""
        self._terminate()
        time.sleep(down_s)
        self._boot()

    def stop(self) -> None:
        """Stop PX4 and free its instance and ports. The console log and the ULogs stay where
        they are (``log_file``, ``ulogs()``); of a temporary working directory only they stay."""
        self._terminate()
        for s in self._host.values():
            s.close()
        self._host.clear()
        if self._lock is not None:
            self._lock.close()
            self._lock = None
        if self._own_dir and self.workdir is not None:
            keep = {"log", self.log_file.name}
            for p in self.workdir.iterdir():
                if p.name not in keep:
                    if p.is_dir() and not p.is_symlink():
                        shutil.rmtree(p, ignore_errors=True)
                    else:
                        p.unlink(missing_ok=True)

    def __enter__(self) -> "Px4Sitl":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    # ----- addresses and files
    def port(self, link: str) -> int:
        """The host port a client sends to on ``link`` (gcs, api, payload)."""
        if link not in self._host:
            raise SitlError(f"no link {link!r} (not started, or not among listeners {dict(self.listeners)})")
        return self._host[link].getsockname()[1]

    def talk_url(self, link: str) -> str:
        """For clients that send first (a heartbeat): any number of them per link."""
        return f"udpout:127.0.0.1:{self.port(link)}"

    def url(self, link: str, i: int = 0) -> str:
        """For the i-th client that listens where PX4 sends (``udpin``), as a companion on 14540."""
        self.port(link)
        push = self._push.get(link, [])
        if not 0 <= i < len(push):
            raise SitlError(f"link {link!r} has {len(push)} listener ports, not {i + 1}")
        return f"udpin:127.0.0.1:{push[i]}"

    @property
    def log_file(self) -> Path:
        return Path(self.log_path) if self.log_path else Path(self.workdir) / "px4.log"

    def events_metadata(self) -> Path | None:
        """The build's event metadata (what ``pmon run --px4-events`` reads), if it has one."""
        p = self.folder / "etc" / "extras" / "all_events.json.xz"
        return p if p.is_file() else None

    def ulogs(self) -> list[Path]:
        """The ULogs PX4 wrote (workdir/log/DATE/TIME.ulg), oldest first."""
        return sorted(Path(p) for p in glob.glob(str(Path(self.workdir) / "log" / "*" / "*.ulg")))

    # ----- internals
    def _claim_instance(self) -> None:
        lock_dir = Path(tempfile.gettempdir())
        candidates = [self.instance] if self.instance is not None else range(FIRST_INSTANCE, LAST_INSTANCE + 1)
        for n in candidates:
            try:  # read-only: another user's lock file locks as well
                f = os.fdopen(os.open(lock_dir / f"pmon-px4-sitl-i{n}.lock", os.O_RDONLY | os.O_CREAT, 0o666))
            except OSError:
                continue
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                f.close()
                continue
            if _px4_lock_free(n):
                self.instance, self._lock = n, f
                return
            f.close()
        raise SitlError(f"no free PX4 instance in {candidates!r} (/tmp/px4_lock-N held)")

    def _open_host_side(self) -> None:
        for link, n in self.listeners.items():
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            self._host[link] = s
            ports = []
            for _ in range(n):  # a free port now, for a client to bind (udpin) soon after
                with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                    probe.bind(("127.0.0.1", 0))
                    ports.append(probe.getsockname()[1])
            self._push[link] = ports

    def _write_rc(self) -> None:
        """workdir/bin/px4-rc.sihsim, found by rcS on the PATH before PX4's own (see the module)."""
        lines = ["#!/bin/sh", "# written by pmon's sim/firmware/px4.py: after rcS's settings, before the flight modules start"]
        if self.sysid is not None:
            lines.append(f"param set MAV_SYS_ID {int(self.sysid)}")
        if self.stock_timeouts and self.speed != 1:
            lines.append("param reset " + " ".join(SPEED_SCALED_PARAMS))
        lines += [f"param set {k} {_value(v)}" for k, v in self.params.items()]
        lines.append(". ${R}etc/init.d-posix/px4-rc.sihsim")
        (self.workdir / "bin").mkdir(exist_ok=True)
        (self.workdir / "bin" / "px4-rc.sihsim").write_text("\n".join(lines) + "\n")

    def _boot(self) -> None:
        self._write_rc()
        env = {k: v for k, v in os.environ.items() if not k.startswith(("PX4_PARAM_", "PX4_HOME_", "PX4_SIM"))}
        env.update({f"PX4_PARAM_{k}": _value(v) for k, v in self.params.items()})
        env.update(PX4_HOME_LAT=f"{self.home[0]:.7f}", PX4_HOME_LON=f"{self.home[1]:.7f}",
                   PX4_HOME_ALT=f"{self.home[2]:.2f}")
        argv = [sys.executable, "-m", "sim.firmware.netns", "--parent", str(os.getpid())]
        fds = []
        for link, s in self._host.items():
            listen, target = links_of(self.instance)[link]
            argv += ["--link", ",".join(str(x) for x in (s.fileno(), target, listen, *self._push[link]))]
            fds.append(s.fileno())
        argv += ["--", "sh", str(self.folder / SCRIPT), str(self.instance), f"{self.speed:g}", str(self.workdir)]
        env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
        start = self.log_file.stat().st_size if self.log_file.exists() else 0
        with open(self.log_file, "ab") as log:
            self.proc = subprocess.Popen(fifo_argv(argv, vehicle_priority()), cwd=self.workdir, stdout=log,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                         pass_fds=fds, start_new_session=True)
        self.boots += 1
        deadline = time.monotonic() + BOOT_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise SitlError(f"PX4 exited with {self.proc.returncode} at boot ({log_tail(self.log_file, start)}); "
                                f"see {self.log_file}")
            with open(self.log_file, "rb") as f:
                f.seek(start)
                if BOOT_LINE.encode() in f.read():
                    return
            time.sleep(0.05)
        self._terminate()
        raise SitlError(f"PX4 did not finish its startup script within {BOOT_TIMEOUT_S:g} s "
                       f"({log_tail(self.log_file, start)}); see {self.log_file}")

    def _terminate(self) -> None:
        p, self.proc = self.proc, None
        if p is None or p.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            p.send_signal(signal.SIGTERM)  # the relay passes it on: PX4 runs 'shutdown'
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait(timeout=5)


def _value(v) -> str:
    f = float(v)
    return str(int(f)) if f.is_integer() else repr(f)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim.firmware.px4",
                                 description="Start PX4's SITL (SIH quad) at a scenario's UAV start, reachable "
                                 "on loopback only, and print its MAVLink URLs.")
    ap.add_argument("--sitl", help=f"folder with {SCRIPT} (default ${ENV_VAR}, else ../shared/px4)")
    ap.add_argument("--scenario", default="paper", help="home = this scenario's UAV start (default paper)")
    ap.add_argument("--speed", type=float, default=1.0, help="PX4_SIM_SPEED_FACTOR (default 1)")
    ap.add_argument("--instance", type=int, help=f"PX4 -i (default: the first free from {FIRST_INSTANCE})")
    ap.add_argument("--workdir", help="PX4's working directory (default: a new temporary one)")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", type=param_item,
                    help="PX4 parameter at every boot; repeatable (e.g. COM_OBL_RC_ACT=5)")
    ap.add_argument("--gcs-listeners", type=int, default=1, metavar="N",
                    help="udpin ports on the ground-station link (default 1; e.g. 2: pmon gcs and pmon feed live)")
    args = ap.parse_args(argv)
    from onboard.config import ConfigError, load_scenario
    folder = Path(args.sitl) if args.sitl else find_sitl()
    if folder is None:
        print(f"python -m sim.firmware.px4: {skip_reason()}", file=sys.stderr)
        return 2
    if not 0 < args.speed <= 50:
        ap.error(f"--speed must be in (0, 50], got {args.speed}")
    if args.instance is not None and not 0 <= args.instance <= LAST_INSTANCE:
        ap.error(f"--instance must be in 0..{LAST_INSTANCE}, got {args.instance}")
    try:
        sc = load_scenario(args.scenario)
    except ConfigError as exc:
        print(f"python -m sim.firmware.px4: {exc}", file=sys.stderr)
        return 2
    home = home_of(sc)
    if not 1 <= args.gcs_listeners <= 8:
        ap.error(f"--gcs-listeners must be in 1..8, got {args.gcs_listeners}")
    sitl = Px4Sitl(folder, home, args.speed, dict(args.param), instance=args.instance,
                   workdir=Path(args.workdir) if args.workdir else None,
                   listeners={"gcs": args.gcs_listeners, "api": 1})
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(1))
    try:
        sitl.start()
    except SitlError as exc:
        print(f"python -m sim.firmware.px4: {exc}", file=sys.stderr)
        return 1
    try:
        print(f"PX4 SITL (SIH quad) -i {sitl.instance}, sysid {sitl.sysid}, at {home[0]:.6f}, {home[1]:.6f}, "
              f"{home[2]:.1f} m ({sc.name}'s UAV start), {args.speed:g}x; console log {sitl.log_file}, "
              f"ULogs {sitl.workdir / 'log'}", flush=True)
        print(f"  companion (PX4's offboard/API link): {sitl.url('api')}", flush=True)
        gcs = ", ".join(sitl.url("gcs", i) for i in range(args.gcs_listeners))
        print(f"  ground station (PX4's GCS link): {gcs}  (or, sending first: {sitl.talk_url('gcs')})",
              flush=True)
        if (events := sitl.events_metadata()) is not None:  # absolute: pmon run may start anywhere
            print(f"  event metadata (pmon run --px4-events): {events.resolve()}", flush=True)
        while not stop and sitl.running:
            time.sleep(0.2)
        if not sitl.running and not stop:
            print(f"python -m sim.firmware.px4: PX4 exited (see {sitl.log_file})", file=sys.stderr)
            return 1
    finally:
        sitl.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
