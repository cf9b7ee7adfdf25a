"""``pmon gcs`` / ``pmon-gcs``: operate the mission from a terminal over MAVLink.

Exit codes: 0 success; 1 refused, denied or failed (the reason is printed); 2 usage (bad
arguments, bad value); 3 timeout or vehicle unreachable; 130 interrupted. Errors are one line
on stderr; with --json, stdout also gets {"ok": false, "error": ..., "exit_code": ...}.
See docs/OPERATING.md.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading

from groundstation.errors import INTERRUPTED, OK, USAGE, GcsError, UsageError

DEFAULT_URL = "udpin:127.0.0.1:14550"  # where ArduPilot SITL's --out and MAVProxy's outputs go
NO_IDLE_ENV = "PMON_GCS_NO_IDLE"  # set to 1: the program keeps its normal priority (as --no-idle)

COMMANDS = """commands:
  status                      vehicle mode, armed, position, battery, link; the app's state and health
  watch [--count N] [--duration S] [--png FILE] [--scenario NAME]   live table of every target
  view [--port N] [--open] [--duration S] [--scenario NAME]   the mission live in a browser
  hub [--serve udp:H:P] [--out udp:H:P] [--tak URL] [--view PORT] ...   one vehicle link shared by
                              ground stations (QGroundControl, Mission Planner, MAVProxy, pmon gcs),
                              the targets as their traffic (ADSB_VEHICLE) and as CoT to TAK
  arm [--wait]                GUIDED (PX4: Hold), then arm (--wait: until the autopilot is ready and arms)
  takeoff ALT [--wait]        take off to ALT m above home (--wait: until there; --timeout
                              bounds the time without climbing)
  start | pause | resume | stop | launch     the onboard app's monitoring
  advise                      the onboard app to advisory: it plans and shows its next waypoint,
                              commands nothing (start hands the vehicle over to it)
  hold                        stop and hold position: ArduCopter BRAKE, PX4 Hold (the app sees a pilot override)
  mode NAME                   a flight mode in the autopilot's names, e.g. LOITER (ArduCopter), POSCTL,
                              AUTO.LOITER or HOLD (PX4): a pilot's mode switch
  rtl | land                  return to launch / land here
  params list | get NAME | set NAME VALUE     the onboard app's parameters (PMON_*)
  record FILE [--duration S]  tlog of everything the link carries
  plot LOG [--out PNG] [--truth FILE] [--scenario NAME]   flight from a tlog or the app's JSONL run log
  export LOG [--out BASE] [--format geojson|kml] [--at T,..] [--every S] [--truth FILE] [--scenario NAME]
                              the flight as GeoJSON and KML for map tools
"""


def _connection(p: argparse.ArgumentParser, suppress: bool) -> None:
    """The link's options (every command that talks to a vehicle); on a command's own parser
    too (``suppress``: not reset there when given before the command)."""
    d = (lambda v: argparse.SUPPRESS) if suppress else (lambda v: v)
    p.add_argument("--connect", metavar="URL", default=d(None),
                   help=f"MAVLink URL: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, serial device "
                        f"(default: $PMON_GCS_CONNECT or {DEFAULT_URL})")
    p.add_argument("--sysid", type=int, default=d(None), help="vehicle system id (default: the first autopilot heard)")
    p.add_argument("--timeout", type=float, default=d(5.0), help="seconds to wait for an answer (default 5)")
    p.add_argument("--signing-key", metavar="FILE", default=d(None),
                   help="MAVLink 2 signing key file (64 hex chars, mode 0600), the vehicle's: sign "
                        "every command and parameter write, accept only signed packets "
                        "(default: $PMON_GCS_SIGNING_KEY, else unsigned)")
    p.add_argument("--autopilot-unsigned", action="store_true", default=d(False),
                   help="with --signing-key: take the autopilot's own packets unsigned (PX4 cannot sign); "
                        "the onboard app's must still be signed")
    _output(p, suppress)


def _output(p: argparse.ArgumentParser, suppress: bool) -> None:
    p.add_argument("--json", action="store_true", default=argparse.SUPPRESS if suppress else False,
                   help="machine-readable output")
    p.add_argument("--no-idle", action="store_true", default=argparse.SUPPRESS if suppress else False,
                   help=f"keep normal CPU priority (default: the command runs at idle priority, so on the "
                   f"companion computer it never delays the onboard app's tick; also ${NO_IDLE_ENV}=1)")


def parser() -> argparse.ArgumentParser:
    from onboard.argcheck import OneLineParser, Version
    ap = OneLineParser(prog="pmon gcs", description="Ground station: operate the Passive Monitor "
                       "mission over MAVLink.", epilog=COMMANDS, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--version", action=Version)
    _connection(ap, suppress=False)
    sub = ap.add_subparsers(dest="cmd", required=True, metavar="COMMAND")

    def add(name, help_, link=True):
        p = sub.add_parser(name, help=help_, description=help_)
        (_connection if link else _output)(p, suppress=True)  # files need no link
        return p
    add("status", "vehicle and onboard-app status")
    _live_commands(add)
    from groundstation.hub_options import add_arguments as hub_arguments  # the hub's options live with it
    hub_arguments(add("hub", "share the vehicle link; targets to QGC/MP/MAVProxy (ADSB) and TAK (CoT)"))
    _flight_commands(add)
    _params_commands(add("params", "the onboard app's parameters"))
    r = add("record", "record a tlog")
    r.add_argument("file", metavar="FILE")
    r.add_argument("--duration", type=float, help="seconds (default: until Ctrl-C)")
    _file_commands(add)
    return ap


def _live_commands(add) -> None:
    """watch and view: the mission live, in the terminal or a browser."""
    w = add("watch", "live table of every target")
    w.add_argument("--count", type=int, help="stop after N updates")
    w.add_argument("--duration", type=float, help="stop after S seconds")
    w.add_argument("--png", help="also draw a top-down PNG, rewritten each second")
    w.add_argument("--scenario", default="paper", help="the scene the PNG draws (default paper)")
    vw = add("view", "the mission live in a browser (served on 127.0.0.1)")
    vw.add_argument("--port", type=int, default=8350, help="HTTP port on 127.0.0.1 (default 8350; 0: any free)")
    vw.add_argument("--open", action="store_true", help="open the page in the default browser")
    vw.add_argument("--duration", type=float, help="stop after S seconds (default: until Ctrl-C)")
    vw.add_argument("--scenario", default="paper", help="the mission's scenario: area, obstacles, goals, "
                    "origin (name or YAML file; default paper)")


def _flight_commands(add) -> None:
    """What flies the vehicle or the app: arm, takeoff, the app's actions, modes."""
    a = add("arm", "GUIDED (PX4: Hold), then arm the motors")
    a.add_argument("--wait", action="store_true",
                   help="first wait (within --timeout) for the autopilot's pre-arm checks to pass")
    t = add("takeoff", "take off to ALT m above home")
    t.add_argument("alt", type=float, metavar="ALT")
    t.add_argument("--wait", action="store_true",
                   help="return when at ALT; fails when the climb makes no progress for --timeout s")
    for name in ("start", "pause", "resume", "stop", "launch"):
        add(name, f"onboard app: {name}")
    add("advise", "onboard app: advisory (plan and publish the next waypoint, command nothing)")
    add("hold", "stop and hold position (ArduCopter BRAKE, PX4 Hold)")
    m = add("mode", "set a flight mode by the autopilot's name for it (ArduCopter: LOITER, BRAKE, ...; "
            "PX4: POSCTL, AUTO.LOITER or HOLD, ...)")
    m.add_argument("name", metavar="NAME")
    add("rtl", "return to launch")
    add("land", "land where it is")


def _params_commands(pp: argparse.ArgumentParser) -> None:
    psub = pp.add_subparsers(dest="pcmd", required=True, metavar="list|get|set")
    _connection(psub.add_parser("list", help="every PMON_* parameter with its value, range and doc"), True)
    g = psub.add_parser("get", help="one parameter's value")
    _connection(g, True)
    g.add_argument("name", metavar="NAME", help="e.g. PMON_PD")
    s = psub.add_parser("set", help="set a parameter (the app checks its range and answers with the value it keeps)")
    _connection(s, True)
    s.add_argument("name", metavar="NAME")
    s.add_argument("value", metavar="VALUE", help="a finite number")


def _file_commands(add) -> None:
    """plot and export: from a log file, no link."""
    pl = add("plot", "plot a flight from a tlog or the app's JSONL run log", link=False)
    pl.add_argument("log", metavar="LOG")
    pl.add_argument("--out", help="PNG to write (default: LOG with .png)")
    pl.add_argument("--truth", help="the feed's truth JSONL (default: truth.jsonl next to LOG, if any)")
    pl.add_argument("--scenario", default="paper", help="the scene drawn: area, obstacles, goals (default paper)")
    ex = add("export", "the flight as GeoJSON and KML (tlog or the app's JSONL run log)", link=False)
    ex.add_argument("log", metavar="LOG")
    ex.add_argument("--out", help="BASE of BASE.geojson and BASE.kml (default: LOG without its extension)")
    ex.add_argument("--format", choices=("geojson", "kml", "both"), default="both")
    ex.add_argument("--at", help="ellipses at these tick times, s, comma-separated (default: every --every s)")
    ex.add_argument("--every", type=float, default=10.0, help="ellipses every S s of ticks and at the last "
                    "(default 10; 0: the last only)")
    ex.add_argument("--truth", help="the feed's truth JSONL (default: truth.jsonl next to LOG, if any)")
    ex.add_argument("--scenario", default="paper", help="the mission's scenario: origin, area, obstacles, goals "
                    "(default paper)")


def run(args, console) -> tuple[str, dict]:
    from groundstation.gcs_link import GcsLink

    sc = _scenario(args.scenario) if getattr(args, "scenario", None) else None
    if args.cmd in ("plot", "export"):
        from groundstation.offline import from_log
        return from_log(args, sc)
    _check_arguments(args)
    tlog = args.file if args.cmd == "record" else None
    key = _signing_key(args)
    if args.cmd == "hub":
        from groundstation.hub import run_cli
        o = run_cli(args, key, sc, console)
        return o.text, o.data
    if args.autopilot_unsigned and key is None:
        raise UsageError("--autopilot-unsigned needs --signing-key (without a key nothing is signed)")
    with GcsLink(args.connect, args.timeout, args.sysid, tlog_path=tlog, signing_key=key,
                 autopilot_unsigned=args.autopilot_unsigned) as gl:
        gl.connect()
        o = _command(gl, args, sc, console)
    return o.text, o.data


def _check_arguments(args) -> None:
    """The values argparse cannot check, refused before any link opens (``args.value`` of
    ``params set`` becomes a float)."""
    from groundstation import protocol as P
    if args.cmd == "view" and not 0 <= args.port <= 65535:
        raise UsageError(f"view: --port must be in 0..65535, got {args.port}")
    if args.cmd == "view" and args.duration is not None and not args.duration > 0:
        raise UsageError("view: --duration must be > 0")
    if args.cmd == "mode" and not P.known_mode(args.name):
        raise UsageError(f"mode: unknown mode {args.name!r} (ArduCopter: {', '.join(P.mode_names())}; "
                         f"PX4: {', '.join(P.mode_names('PX4'))})")
    if args.cmd == "takeoff" and not (math.isfinite(args.alt) and 0 < args.alt <= 1000):
        raise UsageError(f"takeoff: ALT must be in (0, 1000] m, got {args.alt:g}")
    if args.cmd == "params" and args.pcmd == "set":
        try:
            args.value = float(args.value)
        except ValueError:
            raise UsageError(f"params set {args.name}: {args.value!r} is not a number")
        if not math.isfinite(args.value):
            raise UsageError(f"params set {args.name}: value must be a finite number")
    if args.cmd == "watch" and ((args.count is not None and args.count < 1)
                                or (args.duration is not None and args.duration <= 0)):
        raise UsageError("watch: --count must be >= 1 and --duration > 0")


def _signing_key(args) -> bytes | None:
    if not args.signing_key:
        return None
    from onboard.app.signing import KeyFileError, load_key  # the one key loader (app, mock, GCS)
    try:
        return load_key(args.signing_key)
    except KeyFileError as exc:
        raise UsageError(f"--signing-key {exc}")


def _command(gl, args, sc, console):
    """Run ``args.cmd`` over the connected link ``gl``: its ``Outcome``."""
    from groundstation import gcs_commands as C
    from groundstation import protocol as P
    cmd = args.cmd
    if cmd == "status":
        return C.status(gl)
    if cmd == "watch":
        from groundstation.watch import watch
        return watch(gl, args.count, args.duration, args.png, args.json, console, scenario=sc)
    if cmd == "view":
        from groundstation.view import open_in_browser, serve
        return serve(gl, sc, args.port, args.duration, args.json, console,
                     on_ready=open_in_browser if args.open else None)
    if cmd == "arm":
        return C.arm(gl, args.wait)
    if cmd == "takeoff":
        return C.takeoff(gl, args.alt, args.wait)
    if cmd in P.ACTIONS:
        return C.app_action(gl, cmd)
    if cmd == "hold":
        return C.set_mode(gl, "hold", gl.v.profile.hold_mode)
    if cmd == "mode":
        return C.set_mode(gl, f"mode {args.name.upper()}", args.name)
    if cmd in ("rtl", "land"):
        from onboard.app.mavlink_connection import mavlink
        nav = mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH if cmd == "rtl" else mavlink.MAV_CMD_NAV_LAND
        return C.set_mode(gl, cmd, cmd.upper(), nav)
    if cmd == "params":
        return {"list": lambda: C.params_list(gl), "get": lambda: C.params_get(gl, args.name),
                "set": lambda: C.params_set(gl, args.name, args.value)}[args.pcmd]()
    if cmd == "record":
        return _record(gl, args.duration, args.file)
    raise UsageError(f"unknown command {cmd}")  # pragma: no cover (argparse has checked)


def _scenario(name):
    from onboard.config import ConfigError, load_scenario
    try:
        return load_scenario(name)
    except ConfigError as exc:
        raise UsageError(f"--scenario {exc}")


def _record(gl, duration, path):
    import time

    from groundstation.gcs_commands import Outcome
    t0 = time.monotonic()
    try:
        while duration is None or time.monotonic() - t0 < duration:
            gl.pump(0.05)
    except KeyboardInterrupt:
        pass
    dt = time.monotonic() - t0
    return Outcome(f"record: {gl.received} messages in {dt:.1f} s to {path}",
                   {"file": path, "messages": gl.received, "seconds": round(dt, 2)})


def program(argv: list[str] | None = None) -> int:
    """ground station: status, watch, commands, parameters over MAVLink (pmon gcs --help)"""
    return main(argv, lower=True)


def main(argv: list[str] | None = None, lower: bool = False) -> int:
    """ground station: status, watch, commands, parameters over MAVLink (pmon gcs --help).
    ``lower``: as a program of its own, at idle priority (``_lower``); in-process callers (tests,
    benches) keep theirs."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if threading.current_thread() is threading.main_thread():
        # Ctrl-C (and a script's SIGINT) stops hub, watch and record even when started from a shell
        # that ignores SIGINT: a background job inherits SIG_IGN (as pmon demo and pmon eval do)
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        args = parser().parse_args(argv)
    except SystemExit as exc:  # argparse: usage errors are 2, --help is 0
        return int(exc.code or 0)
    if lower:
        _lower(args)
    args.connect = args.connect or os.environ.get("PMON_GCS_CONNECT") or DEFAULT_URL
    args.signing_key = args.signing_key or os.environ.get("PMON_GCS_SIGNING_KEY") or None
    if not args.timeout > 0:
        return _error(args, UsageError(f"--timeout must be > 0, got {args.timeout:g}"), USAGE)
    if args.sysid is not None and not 1 <= args.sysid <= 255:
        return _error(args, UsageError(f"--sysid must be in 1..255, got {args.sysid}"), USAGE)
    from rich.console import Console
    console = Console(file=sys.stdout, highlight=False)
    try:
        text, data = run(args, console)
    except UsageError as exc:
        return _error(args, exc, USAGE)
    except GcsError as exc:
        return _error(args, exc, exc.code)
    except KeyboardInterrupt:
        return _error(args, KeyboardInterrupt("interrupted"), INTERRUPTED)
    if args.json:
        if args.cmd != "watch":  # watch has printed one JSON line per update
            print(json.dumps({"ok": True, **data, "command": args.cmd}, default=str), flush=True)
    elif text:
        print(text, flush=True)
    return OK


def _lower(args) -> None:
    """At nice 19 (what it starts inherits it: a plot; onboard/app/realtime.py ``lower_priority``),
    unless --no-idle or $PMON_GCS_NO_IDLE: an operator's command started on the companion
    computer must not take CPU from the onboard app's tick (docs/DEPLOY.md). The hub is not
    lowered: it routes the app's telemetry and the operators' commands, a router's work."""
    if args.no_idle or args.cmd == "hub" or os.environ.get(NO_IDLE_ENV, "").strip().lower() in ("1", "true", "yes"):
        return
    from onboard.app.realtime import lower_priority
    lower_priority()


def script() -> int:
    """``pmon-gcs``: ``pmon gcs`` as a program of its own, its extra checked as ``pmon`` does."""
    from onboard.cli import refusal
    if (why := refusal("pmon-gcs", ("gcs",))):
        print(why, file=sys.stderr)
        return USAGE
    return program()


def _error(args, exc, code: int) -> int:
    msg = str(exc) or type(exc).__name__
    print(f"pmon gcs: {msg}", file=sys.stderr, flush=True)
    if getattr(args, "json", False):
        print(json.dumps({"ok": False, "error": msg, "exit_code": code}), flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
