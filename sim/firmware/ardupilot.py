"""ArduPilot's own SITL firmware as a child process: the real autopilot for conformance tests,
benches and the demo.

    sitl = ArduPilotSitl(find_binary(), home=(35.145, 33.411, 160.0), speedup=4).start()
    sitl.url(0)        # tcp:127.0.0.1:5860: SERIAL0 (one client per TCP port)
    sitl.url(1)        # SERIAL1, sitl.url(2): SERIAL2 (url(3), url(4): SERIAL5, 6 with ports=5)
    sitl.restart()     # SIGTERM, then boot again on the same instance and parameters (eeprom kept)
    sitl.stop()

The binary is ArduPilot's ``arducopter`` built with ``./waf configure --board sitl`` (the one
in ``../shared/ardupilot/`` is 4.4.0-dev, stock, with its test harness's ``copter.parm``). Each
instance runs in a directory of its own (it writes eeprom.bin and logs there) on an instance
number ``-I N`` no other process holds: the ports of N (5760 + 10 N and up, 5501 + 10 N) are
checked free and a lock file is held while it runs, so tests in separate processes can fly
side by side. The firmware's serial ports listen on all interfaces (its own choice; clients here
connect on 127.0.0.1 only).

As a program, for a terminal session (docs/SITL.md)::

    python -m sim.firmware.ardupilot --speedup 1 --param WPNAV_SPEED=2000   # prints the three URLs
"""
from __future__ import annotations

import argparse
import contextlib
import fcntl
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

from onboard.argcheck import param_item  # NAME=VALUE, finite (bench/sitl_response.py imports it from here)
from sim.firmware.priority import fifo_argv, vehicle_priority
from sim.firmware.processes import log_tail

ENV_VAR = "PMON_ARDUPILOT_SITL"
REPO = Path(__file__).resolve().parents[2]
SHARED_BINARY = REPO.parent / "shared" / "ardupilot" / "arducopter"
FIRST_INSTANCE = 20  # instances tried from here up: leaves 0.. to a developer's own SITL
LAST_INSTANCE = 99
# MAVLink ports as TCP servers: SERIAL0..2 (the app, the DF feed, a ground station) and, when
# asked for, SERIAL5 and SERIAL6 (more ground stations; SERIAL3/4 are the simulated GPSs). The
# TCP port of ``tcp:K`` on instance N is BASE + 10 N + K (ArduPilot's SITL_State).
SERIALS = ((0, 0), (1, 2), (2, 3), (5, 5), (6, 6))  # (SERIALn, K)
BASE_PORT = 5760
SERIAL_OFFSETS = tuple(k for _, k in SERIALS)
SIM_PORT_IN = 5501  # its physics-model UDP port, + 10 N


class SitlError(RuntimeError):
    """SITL could not be started or stopped; the message says why in one line."""


def find_binary() -> Path | None:
    """``$PMON_ARDUPILOT_SITL`` if set, else ``../shared/ardupilot/arducopter`` beside the
    repository if it exists, else None."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env)
    return SHARED_BINARY if SHARED_BINARY.is_file() else None


def skip_reason() -> str | None:
    """Why the ArduPilot tests cannot run here (one line), or None when a binary is there."""
    b = find_binary()
    if b is None:
        return (f"no ArduPilot SITL: set {ENV_VAR} to an arducopter built with "
                f"'./waf configure --board sitl && ./waf copter'")
    if not (b.is_file() and os.access(b, os.X_OK)):
        return f"{ENV_VAR}={b}: not an executable file"
    return None


def home_of(scenario) -> tuple[float, float, float, float]:
    """Where the copter stands at boot: the scenario's UAV start on the ground, geodetic
    (deg, deg, m AMSL, heading deg), as SITL's --home takes it."""
    from onboard.app.autopilot.pose import Frame

    o = scenario.origin
    lat, lon, alt = Frame(o.lat_deg, o.lon_deg, o.alt_m).geodetic_from_enu(
        (scenario.uav.start_m[0], scenario.uav.start_m[1], 0.0))
    return (lat, lon, alt, 0.0)


def default_params_file(binary: Path) -> Path | None:
    """The ``copter.parm`` beside the binary (the test harness's defaults), if there is one."""
    p = Path(binary).with_name("copter.parm")
    return p if p.is_file() else None


def _ports_free(instance: int) -> bool:
    for off in SERIAL_OFFSETS:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(("0.0.0.0", BASE_PORT + 10 * instance + off))
            except OSError:
                return False
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("0.0.0.0", SIM_PORT_IN + 10 * instance))
        except OSError:
            return False
    return True


@dataclass
class ArduPilotSitl:
    """One ArduCopter SITL process. ``home`` = (lat deg, lon deg, alt m AMSL[, yaw deg])."""

    binary: Path
    home: tuple[float, ...]
    speedup: float = 1.0
    params: dict[str, float] = field(default_factory=dict)  # over copter.parm, at every boot
    defaults: Path | None = None  # None: copter.parm beside the binary
    model: str = "+"
    instance: int | None = None  # None: the first free one from FIRST_INSTANCE
    workdir: Path | None = None  # None: a temporary directory; stop() keeps only its logs
    ports: int = 3  # MAVLink TCP ports: 3 (SERIAL0..2), 4 (and SERIAL5) or 5 (and SERIAL6)
    log_path: Path | None = None  # the firmware's stdout/stderr (None: workdir/arducopter.log)
    proc: subprocess.Popen | None = field(default=None, init=False)
    boots: int = field(default=0, init=False)  # boots that came up (a restart is one more)
    boot_crashes: int = field(default=0, init=False)  # boots that crashed and were booted again

    def __post_init__(self):
        self.binary = Path(self.binary)
        if not (self.speedup > 0 and self.speedup <= 100):
            raise SitlError(f"speedup must be in (0, 100], got {self.speedup}")
        if not 3 <= self.ports <= len(SERIALS):
            raise SitlError(f"ports must be in 3..{len(SERIALS)}, got {self.ports}")
        self._lock = None
        self._own_dir = False

    # ----- lifecycle
    def start(self) -> "ArduPilotSitl":
        if self.proc is not None:
            return self
        if not (self.binary.is_file() and os.access(self.binary, os.X_OK)):
            raise SitlError(f"{self.binary}: not an executable ArduPilot SITL binary")
        if self.workdir is None:
            self.workdir = Path(tempfile.mkdtemp(prefix="pmon-sitl-"))
            self._own_dir = True
        self.workdir.mkdir(parents=True, exist_ok=True)
        if self.instance is None or self._lock is None:
            self._claim_instance()
        self._boot(wipe=True)
        return self

    def restart(self, down_s: float = 0.0) -> None:
        """Stop the firmware (SIGTERM) and boot it again on the same instance and eeprom, after
        ``down_s`` wall seconds down: a reboot or a power cycle as the companion sees it."""
        self._terminate()
        time.sleep(down_s)
        self._boot(wipe=False)

    def stop(self) -> None:
        self._terminate()
        if self._lock is not None:
            self._lock.close()
            self._lock = None
        if self._own_dir and self.workdir is not None and self.workdir.is_dir():
            # the console log it printed and the firmware's dataflash logs stay: a failed
            # flight's evidence (the eeprom and the rest go)
            for p in self.workdir.iterdir():
                if p.name not in ("arducopter.log", "logs"):
                    shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                self.workdir.rmdir()  # only if nothing was kept

    def __enter__(self) -> "ArduPilotSitl":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    # ----- addresses
    def port(self, serial: int) -> int:
        """TCP port of MAVLink port ``serial``: 0, 1, 2 (SERIAL0..2), 3 (SERIAL5), 4 (SERIAL6)."""
        if self.instance is None:
            raise SitlError("not started")
        if not 0 <= serial < self.ports:
            raise SitlError(f"no MAVLink port {serial}: this SITL has {self.ports}")
        return BASE_PORT + 10 * self.instance + SERIALS[serial][1]

    def url(self, serial: int) -> str:
        return f"tcp:127.0.0.1:{self.port(serial)}"

    # ----- internals
    def _claim_instance(self) -> None:
        lock_dir = Path(tempfile.gettempdir())
        candidates = [self.instance] if self.instance is not None else \
            range(FIRST_INSTANCE, LAST_INSTANCE + 1)
        for n in candidates:
            f = open(lock_dir / f"pmon-ardupilot-sitl-I{n}.lock", "w")
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                f.close()
                continue
            if _ports_free(n):
                self.instance, self._lock = n, f
                return
            f.close()
        raise SitlError(f"no free SITL instance in {candidates!r}: ports 5760+10N taken")

    def _defaults_arg(self) -> str:
        files = []
        base = self.defaults or default_params_file(self.binary)
        if base is not None:
            files.append(str(base))
        params = dict(self.params)
        for n, _ in SERIALS[3:self.ports]:  # SERIAL5.. speak MAVLink 2 only when told to
            params.setdefault(f"SERIAL{n}_PROTOCOL", 2)
        if params:
            extra = self.workdir / "pmon.parm"
            extra.write_text("".join(f"{k} {float(v):g}\n" for k, v in params.items()))
            files.append(str(extra))
        return ",".join(files)

    def _boot(self, wipe: bool) -> None:
        """Start the firmware and wait until every serial port listens. A crash at boot (killed by
        a signal before its ports opened: once in a CI run, SIGABRT) is reported in its log and
        on stderr and booted once more; a second crash, or an exit with a status (bad arguments,
        a port taken), raises with the log's last lines."""
        for attempt in (1, 2):
            status, tail = self._boot_once(wipe)
            if status is None:
                return
            if status >= 0 or attempt == 2:
                break
            self.boot_crashes += 1
            note = (f"pmon: {self.binary.name} crashed at boot (signal {-status}); booting it again\n")
            with open(self._log_file(), "a") as log:
                log.write(note)
            print(f"sim.firmware.ardupilot: {note.strip()}; its last lines: {tail}", file=sys.stderr)
        raise SitlError(f"{self.binary.name} exited with {status} at boot ({tail}); "
                        f"see {self._log_file()}")

    def _log_file(self) -> Path:
        return self.log_path or self.workdir / "arducopter.log"

    def _boot_once(self, wipe: bool) -> tuple[int | None, str]:
        """One boot: (None, "") once every port listens, else (its exit status, its log's last
        lines joined by " | ")."""
        home = ",".join(f"{x:g}" for x in (*self.home[:3], self.home[3] if len(self.home) > 3 else 0))
        argv = [str(self.binary), "--model", self.model, "--speedup", f"{self.speedup:g}",
                "-I", str(self.instance), "--home", home, "--disable-fgview"]
        if wipe:
            argv.append("--wipe")
        defaults = self._defaults_arg()
        if defaults:
            argv += ["--defaults", defaults]
        for n, k in SERIALS[:self.ports]:
            argv += [f"--serial{n}", f"tcp:{k}"]
        path = self._log_file()
        start = path.stat().st_size if path.exists() else 0
        log = open(path, "ab")
        try:
            self.proc = subprocess.Popen(fifo_argv(argv, vehicle_priority()), cwd=self.workdir, stdout=log,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
        finally:
            log.close()
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:  # every serial port listening = booted
            status = self.proc.poll()
            if status is not None:
                self.proc = None
                return status, log_tail(path, start)
            if all(_listening(self.port(i)) for i in range(self.ports)):
                self.boots += 1
                return None, ""
            time.sleep(0.05)
        self._terminate()
        raise SitlError(f"{self.binary.name} did not open its serial ports within 20 s "
                        f"({log_tail(path, start)}); see {path}")

    def _terminate(self) -> None:
        p, self.proc = self.proc, None
        if p is None or p.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=5)
        deadline = time.monotonic() + 5.0  # the kernel frees the ports with the process
        while time.monotonic() < deadline and any(_listening(self.port(i)) for i in range(self.ports)):
            time.sleep(0.05)


def _listening(port: int) -> bool:
    """True if something accepts TCP on 127.0.0.1:port. Probes SITL with a connect, which
    SITL takes as its one client and drops when we close: probe only before clients attach."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim.firmware.ardupilot",
                                 description="Start ArduPilot's ArduCopter SITL on loopback at a "
                                 "scenario's origin and print its MAVLink URLs.")
    ap.add_argument("--binary", help=f"arducopter SITL binary (default ${ENV_VAR}, else "
                    f"../shared/ardupilot/arducopter)")
    ap.add_argument("--scenario", default="paper", help="home = this scenario's UAV start (default paper)")
    ap.add_argument("--speedup", type=float, default=1.0, help="simulated s per wall s (default 1)")
    ap.add_argument("--instance", type=int, help="SITL -I (default: the first free from "
                    f"{FIRST_INSTANCE})")
    ap.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", type=param_item,
                    help="parameter over copter.parm at boot; repeatable (e.g. WPNAV_SPEED=2000)")
    args = ap.parse_args(argv)
    from onboard.config import ConfigError, load_scenario
    binary = Path(args.binary) if args.binary else find_binary()
    if binary is None:
        print(f"python -m sim.firmware.ardupilot: {skip_reason()}", file=sys.stderr)
        return 2
    if not (args.speedup > 0 and args.speedup <= 100):
        ap.error(f"--speedup must be in (0, 100], got {args.speedup}")
    if args.instance is not None and not 0 <= args.instance <= LAST_INSTANCE:
        ap.error(f"--instance must be in 0..{LAST_INSTANCE}, got {args.instance}")
    params = dict(args.param)
    try:
        sc = load_scenario(args.scenario)
    except ConfigError as exc:
        print(f"python -m sim.firmware.ardupilot: {exc}", file=sys.stderr)
        return 2
    home = home_of(sc)
    sitl = ArduPilotSitl(binary, home, args.speedup, params, instance=args.instance)
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(1))
    try:
        sitl.start()
    except SitlError as exc:
        print(f"python -m sim.firmware.ardupilot: {exc}", file=sys.stderr)
        return 1
    try:
        print(f"ArduCopter SITL -I {sitl.instance} at {home[0]:.6f}, {home[1]:.6f}, {home[2]:.1f} m "
              f"({sc.name}'s UAV start), {args.speedup:g}x; log {sitl.workdir / 'arducopter.log'}",
              flush=True)
        for i, who in enumerate(("the onboard app", "the DF feed", "a ground station")):
            print(f"  SERIAL{i}: {sitl.url(i)}   ({who})", flush=True)
        while not stop and sitl.running:
            time.sleep(0.2)
        if not sitl.running and not stop:
            print("python -m sim.firmware.ardupilot: the firmware exited "
                  f"(see {sitl.workdir / 'arducopter.log'})", file=sys.stderr)
            return 1
    finally:
        sitl.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
