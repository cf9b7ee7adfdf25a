"""``pmon run``: the onboard app as a process (companion computer)."""
from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

from onboard.app.df.udp_input import DEFAULT_RATE_HZ, parse_sources
from onboard.app.realtime import parse_cpus
from onboard.argcheck import (
    HOST_PORT_BIND,
    MAVLINK_URL,
    OUT_FILE,
    SEED,
    checked,
    integer,
    number,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mavlink", default="tcp:127.0.0.1:5760", type=MAVLINK_URL,
                   help="autopilot connection as pymavlink takes it: udpin:HOST:PORT, "
                   "udpout:HOST:PORT, tcp:HOST:PORT, or a serial device (with --baud) "
                   "(default tcp:127.0.0.1:5760, ArduPilot SITL's first port)")
    p.add_argument("--baud", type=integer(50, 20_000_000), default=921600, help="serial baud rate (default 921600)")
    p.add_argument("--df", default=("127.0.0.1", 14600), type=HOST_PORT_BIND, metavar="HOST:PORT",
                   help="UDP address to receive DF datagrams on; port 0 picks a free one "
                   "(default 127.0.0.1:14600)")
    p.add_argument("--df-from", metavar="HOST[:PORT],...", type=checked(parse_sources), default=(),
                   help="accept DF datagrams only from these senders (HOST: any port of it); default: "
                   "the first sender whose datagram is valid (docs/DATAGRAM.md, who may send)")
    p.add_argument("--df-rate", type=number(1.0, 1e6), default=DEFAULT_RATE_HZ, metavar="N",
                   help="DF datagrams/s accepted per sender; the excess is dropped unparsed (default 1000)")
    p.add_argument("--kraken", nargs="?", const="", metavar="URL",
                   help="also read a KrakenSDR's DoA output (its 'Kraken App' CSV): the scenario's kraken "
                   "section says which VFO is which target; URL (http://HOST:8081/DOA_value.html or a file "
                   "path) overrides its kraken.url (docs/KRAKENSDR.md)")
    p.add_argument("--scenario", default="paper", help="YAML file or built-in name (default paper)")
    from onboard.policy import DEFAULT, POLICIES
    p.add_argument("--policy", choices=tuple(POLICIES), default=DEFAULT,
                   help="how to decide where to fly: flight (default: the declared defaults, the best "
                   "measured, lookahead on the vehicle's motion, at the autopilot's speed limits) or "
                   "paper (the overlay that restores the paper's one-step rule on its jump model and "
                   "its filter); onboard/policy.py")
    p.add_argument("--sysid", type=integer(1, 255), help="vehicle system id (default: the first autopilot heard)")
    p.add_argument("--auto-launch", action="store_true",
                   help="by itself: arm, take off to h, the mission mode (ArduCopter GUIDED, PX4 OFFBOARD), "
                   "start monitoring (SITL/demo only)")
    p.add_argument("--advise", action="store_true",
                   help="start in advisory: track, plan from where the vehicle is and publish the next "
                   "waypoint while a pilot or a mission flies; nothing is commanded until `pmon gcs start` "
                   "(docs/OPERATING.md, Advisory)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="initial PMON_* parameter; repeatable")
    p.add_argument("--runlog", type=OUT_FILE, help="JSONL run log, one line per tick")
    p.add_argument("--tlog", type=OUT_FILE, help="MAVLink telemetry log (both directions), mavlogdump.py reads it")
    p.add_argument("--gcs-sysid", type=integer(1, 255), action="append", metavar="SYSID",
                   help="system id of a ground station allowed to command the app and write its "
                   "parameters; repeatable (default 255)")
    p.add_argument("--signing-key", metavar="FILE",
                   help="MAVLink 2 signing key file (64 hex chars, mode 0600): sign every message, "
                   "drop unsigned or wrongly signed ones (docs/MAVLINK.md, Signing)")
    p.add_argument("--autopilot-unsigned", action="store_true",
                   help="with --signing-key: take the autopilot's own packets unsigned (component 1 of "
                   "--sysid, default 1), for an autopilot that cannot sign (PX4 v1.16); every other "
                   "sender, a ground station's commands included, must still sign (docs/SAFETY.md)")
    p.add_argument("--px4-events", metavar="FILE",
                   help="PX4's event metadata (its build's etc/extras/all_events.json.xz): PX4's arming "
                   "refusals and failsafes in words; without it the app says only that PX4 refused")
    p.add_argument("--rt-priority", type=integer(0, 98), metavar="N",
                   help="the io thread (MAVLink, setpoints) at SCHED_FIFO N, the tick worker at N - 1, memory "
                   "locked; where not permitted, one warning and normal scheduling; 0: normal (default: the "
                   "scenario's app.rt_priority, 0; docs/DEPLOY.md)")
    p.add_argument("--cpu-affinity", type=checked(parse_cpus), metavar="LIST",
                   help="run on these CPUs only, e.g. 1 or 2-3 or 0,2 (default: all)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--quiet", action="store_true", help="print only errors")


def run(args) -> int:
    from onboard.app.app_config import AppConfig
    from onboard.app.app import OnboardApp
    from onboard.app.autopilot.px4_events import EventMetadataError
    from onboard.app.signing import KeyFileError
    from onboard.config import ConfigError

    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="%(message)s", stream=sys.stdout)
    host, port = args.df  # every argument is checked by its type= (onboard/argcheck.py)
    gcs = tuple(args.gcs_sysid or (255,))
    if args.autopilot_unsigned and not args.signing_key:
        print("pmon run: --autopilot-unsigned needs --signing-key (without a key nothing is signed)",
              file=sys.stderr)
        return 2
    if args.advise and args.auto_launch:
        print("pmon run: --advise and --auto-launch exclude each other (advisory commands nothing)",
              file=sys.stderr)
        return 2
    sc = _scenario(args)
    if sc is None:
        return 2
    cfg = AppConfig(args.mavlink, host, port, args.baud, args.sysid, args.auto_launch,
                    args.seed, args.runlog, args.tlog, gcs_sysids=gcs, signing_key_path=args.signing_key,
                    df_sources=args.df_from, df_rate_hz=args.df_rate, px4_events_path=args.px4_events,
                    autopilot_unsigned=args.autopilot_unsigned, kraken=args.kraken is not None,
                    rt_priority=sc.app.rt_priority, advise=args.advise)
    process = _process_scheduling(args.cpu_affinity, sc.app.rt_priority > 0)
    try:
        app = OnboardApp(cfg, sc)
    except (KeyFileError, EventMetadataError, ConfigError) as exc:  # ConfigError: --kraken without kraken.vfos
        print(f"pmon run: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # connection refused, address in use, a log file's directory missing ...
        what = exc.filename or f"--mavlink {args.mavlink} or --df {host}:{port}"
        print(f"pmon run: cannot open {what}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    if not _set_params(app, args.param):
        app.stop()
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"pmon run: mavlink {args.mavlink}, DF datagrams on udp {host}:{app.sensor_port}, "
          f"policy {args.policy} ({sc.planning.planner}, {sc.planning.motion} motion)", flush=True)
    if app.kraken is not None:
        print(f"pmon run: KrakenSDR DoA from {app.kraken.url}", flush=True)
    app.start()
    _report_scheduling(process, app.realtime)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        app.stop()
        _report_stopped(app)
    return 0


def _scenario(args):
    """The scenario with the command line's overrides, or None (the error said): a bad scenario
    refuses to start, with one error naming the field."""
    from onboard.config import ConfigError, load_scenario, override
    from onboard.policy import POLICIES

    try:
        sc = load_scenario(args.scenario, POLICIES[args.policy])
        if args.kraken:  # --kraken URL: the scenario's kraken.url, checked as a file's
            sc = override(sc, {"kraken.url": args.kraken})
        if args.rt_priority is not None:
            sc = override(sc, {"app.rt_priority": args.rt_priority})
    except ConfigError as exc:
        print(f"pmon run: {exc}", file=sys.stderr)
        return None
    return sc


def _set_params(app, items: list[str]) -> bool:
    """Each --param NAME=VALUE into the app's parameters; False (the first refusal said) if one is refused."""
    for item in items:
        name, _, value = item.partition("=")
        try:
            refused = app.params.set(name.strip().upper(), float(value))
        except ValueError:
            refused = f"{item!r}: value is not a number"
        if refused:
            print(f"pmon run: --param {refused}", file=sys.stderr)
            return False
    return True


def _report_stopped(app) -> None:
    """The run's counts, once stopped."""
    c = app.counters
    print(f"pmon run: stopped: {c.get('ticks', 0)} ticks, {c.get('ticks_skipped', 0)} skipped, "
          f"{c.get('ticks_late', 0)} late{_overruns(c)}, datagrams {app.scans.accepted} accepted "
          f"{app.scans.rejected_total} rejected {app.df.dropped_total} dropped unparsed", flush=True)
    if app.kraken is not None:
        k, p = app.kraken.source, app.kraken.poller
        print(f"pmon run: KrakenSDR: {k.lines} lines, {k.frames} frames ({k.missed} missed), {k.scans} scans, "
              f"{sum(k.rejected.values())} rejected {dict((r, n) for r, n in k.rejected.items() if n)}, "
              f"gated {dict((g, n) for g, n in k.gated.items() if n)}, {k.repeated} repeated, "
              f"read errors {p.errors}, reader restarts {p.restarts}", flush=True)


def _process_scheduling(cpus: tuple[int, ...] | None, lock: bool) -> list:
    """Process-wide, before the app's threads start (they inherit both): CPU affinity, and with
    real-time threads memory locked (onboard/app/realtime.py)."""
    from onboard.app import realtime
    out = []
    if cpus:
        out.append(realtime.set_affinity(cpus))
    if lock:
        out.append(realtime.lock_memory())
    return out


def _report_scheduling(process: list, threads: dict) -> None:
    """One line of what took effect; one warning line of what was refused (log: the journal)."""
    done = [o.text for o in process if o.ok] + [f"{name} {o.text}" for name, o in threads.items() if o.ok]
    refused = [o.text for o in process if not o.ok]
    by_reason: dict[str, list[str]] = {}
    for name, o in threads.items():
        if not o.ok:
            by_reason.setdefault(o.text, []).append(name)
    refused += [f"{', '.join(names)} at normal scheduling: {why}" for why, names in by_reason.items()]
    if done:
        print(f"pmon run: scheduling: {', '.join(done)}", flush=True)
    if refused:
        logging.getLogger("pmon.app").warning("pmon run: warning: %s", "; ".join(refused))


def _overruns(c) -> str:
    """' (overruns: guidance 2, planning 1)': the ticks over budget by the stage they overran in."""
    from onboard.app.contract import OVERRUN_STAGES
    parts = [f"{s} {c.get(f'overruns_{s}', 0)}" for s in OVERRUN_STAGES if c.get(f"overruns_{s}", 0)]
    return f" (overruns: {', '.join(parts)})" if parts else ""
