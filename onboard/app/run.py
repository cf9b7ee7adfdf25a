"""``pmon run``: the onboard app as a process (companion computer)."""
from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mavlink", default="tcp:127.0.0.1:5760",
                   help="autopilot connection as pymavlink takes it: udpin:HOST:PORT, "
                   "udpout:HOST:PORT, tcp:HOST:PORT, or a serial device (with --baud) "
                   "(default tcp:127.0.0.1:5760, ArduPilot SITL's first port)")
    p.add_argument("--baud", type=int, default=921600, help="serial baud rate (default 921600)")
    p.add_argument("--df", default="127.0.0.1:14600", metavar="HOST:PORT",
                   help="UDP address to receive DF datagrams on; port 0 picks a free one "
                   "(default 127.0.0.1:14600)")
    p.add_argument("--df-from", metavar="HOST[:PORT],...",
                   help="accept DF datagrams only from these senders (HOST: any port of it); default: "
                   "the first sender whose datagram is valid (docs/DATAGRAM.md, who may send)")
    p.add_argument("--df-rate", type=float, default=None, metavar="N",
                   help="DF datagrams/s accepted per sender; the excess is dropped unparsed (default 1000)")
    p.add_argument("--scenario", default="paper", help="YAML file or built-in name (default paper)")
    p.add_argument("--sysid", type=int, help="vehicle system id (default: the first autopilot heard)")
    p.add_argument("--auto-launch", action="store_true",
                   help="by itself: GUIDED, arm, take off to h, start monitoring (SITL/demo only)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="initial PMON_* parameter; repeatable")
    p.add_argument("--runlog", help="JSONL run log, one line per tick")
    p.add_argument("--tlog", help="MAVLink telemetry log (both directions), mavlogdump.py reads it")
    p.add_argument("--gcs-sysid", type=int, action="append", metavar="SYSID",
                   help="system id of a ground station allowed to command the app and write its "
                   "parameters; repeatable (default 255)")
    p.add_argument("--signing-key", metavar="FILE",
                   help="MAVLink 2 signing key file (64 hex chars, mode 0600): sign every message, "
                   "drop unsigned or wrongly signed ones (docs/MAVLINK.md, Signing)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--quiet", action="store_true", help="print only errors")


def run(args) -> int:
    from onboard.app.app import AppConfig, OnboardApp
    from onboard.app.signing import KeyFileError
    from onboard.config import ConfigError, load_scenario

    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="%(message)s", stream=sys.stdout)
    host, _, port = args.df.rpartition(":")
    if not host or not port.isdigit() or not 0 <= int(port) < 65536:
        print(f"pmon run: --df wants HOST:PORT, got {args.df!r}", file=sys.stderr)
        return 2
    if args.sysid is not None and not 1 <= args.sysid <= 255:
        print(f"pmon run: --sysid must be in 1..255, got {args.sysid}", file=sys.stderr)
        return 2
    gcs = tuple(args.gcs_sysid or (255,))
    bad = [g for g in gcs if not 1 <= g <= 255]
    if bad:
        print(f"pmon run: --gcs-sysid must be in 1..255, got {bad[0]}", file=sys.stderr)
        return 2
    from onboard.app.df_input import DEFAULT_RATE_HZ, parse_sources
    try:
        sources = parse_sources(args.df_from) if args.df_from is not None else ()
    except ValueError as exc:
        print(f"pmon run: {exc}", file=sys.stderr)
        return 2
    rate = DEFAULT_RATE_HZ if args.df_rate is None else args.df_rate
    if not 1.0 <= rate <= 1e6:  # NaN fails too
        print(f"pmon run: --df-rate must be in 1..1000000 datagrams/s, got {args.df_rate}", file=sys.stderr)
        return 2
    try:  # a bad scenario refuses to start, with one error naming the field
        sc = load_scenario(args.scenario)
    except ConfigError as exc:
        print(f"pmon run: {exc}", file=sys.stderr)
        return 2
    cfg = AppConfig(args.mavlink, host, int(port), args.baud, args.sysid, args.auto_launch,
                    args.seed, args.runlog, args.tlog, gcs_sysids=gcs, signing_key_path=args.signing_key,
                    df_sources=sources, df_rate_hz=rate)
    try:
        app = OnboardApp(cfg, sc)
    except KeyFileError as exc:
        print(f"pmon run: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"pmon run: cannot open {args.mavlink} or the DF port {args.df}: {exc}", file=sys.stderr)
        return 2
    for item in args.param:
        name, _, value = item.partition("=")
        try:
            refused = app.params.set(name.strip().upper(), float(value))
        except ValueError:
            refused = f"{item!r}: value is not a number"
        if refused:
            print(f"pmon run: --param {refused}", file=sys.stderr)
            app.stop()
            return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"pmon run: mavlink {args.mavlink}, DF datagrams on udp {host}:{app.sensor_port}", flush=True)
    app.start()
    try:
        while not stop.wait(0.2):
            pass
    finally:
        app.stop()
        c = app.counters
        print(f"pmon run: stopped: {c.get('ticks', 0)} ticks, {c.get('ticks_skipped', 0)} skipped, "
              f"{c.get('ticks_late', 0)} late, datagrams {app.scans.accepted} accepted "
              f"{app.scans.rejected_total} rejected {app.df.dropped_total} dropped unparsed", flush=True)
    return 0
