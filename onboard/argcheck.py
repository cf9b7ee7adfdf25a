"""Command-line arguments checked at the edge: one line naming what is wrong, exit 2.

``OneLineParser`` is argparse with its usage dump replaced by one line (``prog: error: ...``),
so every refusal of every program (pmon and its subcommands, python -m sim.mock.autopilot,
python -m sim.stack.sitl_stack) is a single line on stderr, exit 2. The ``type=`` converters below raise
argparse.ArgumentTypeError with the reason; ``check_*`` functions return the value or raise
ValueError with a message naming the option, for values checked after parsing.

Why these checks exist: without them a negative ``--seed`` reached numpy, a port of 70000
reached ``bind()`` (OverflowError), ``nonsense://x`` reached pymavlink (ValueError from
``int('//x')``), ``²`` passed ``str.isdigit()`` and failed ``int()``, and a speedup of 0 or NaN
reached the mock's clock: each a traceback, or a process that never did anything.
"""
from __future__ import annotations

import argparse
import ipaddress
import math
import os
import re
import stat
import sys
import tempfile
from typing import NoReturn

MAVLINK_SCHEMES = ("udpin", "udpout", "udp", "udpbcast", "tcp", "tcpin")
_URL = re.compile(r"(?P<scheme>[a-z]+):(?P<host>[^:/\s]+):(?P<port>[0-9]+)", re.ASCII)


class OneLineParser(argparse.ArgumentParser):
    """argparse, whose errors are one line on stderr (no usage block), exit 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message.splitlines()[0] if message else 'bad arguments'}\n")


class Version(argparse.Action):
    """``--version``: the installed distribution's version, read only when asked (importlib.metadata
    is not loaded for a flight program's start)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show the installed version and exit"):
        super().__init__(option_strings, dest, nargs=0, default=default, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from importlib import metadata
        try:
            version = metadata.version("passive-monitor")
        except metadata.PackageNotFoundError:
            version = "(not installed)"
        print(f"{parser.prog} {version}")
        parser.exit(0)


def _port(text: str, lo: int) -> int:
    if not (text.isascii() and text.isdigit()) or not lo <= int(text) <= 65535:
        raise ValueError(f"port must be {lo}..65535, got {text!r}")
    return int(text)


_LABEL = r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?"
_HOST_NAME = re.compile(rf"{_LABEL}(?:\.{_LABEL})*\.?", re.ASCII)


def host_name(text: str) -> str:
    """An IP address literal or a DNS name in RFC 1123's syntax. Anything else is refused here,
    not handed to the resolver: a malformed option ("tcp:127.0.0.1", "999.1.1.1") must not
    become a DNS query that leaves the machine."""
    try:
        ipaddress.ip_address(text)
        return text
    except ValueError:
        pass
    labels = text.rstrip(".").split(".")
    if len(text) > 253 or not _HOST_NAME.fullmatch(text) or all(x.isdigit() for x in labels):
        raise ValueError(f"{text!r} is not an IP address or a host name")
    return text


def host_port(text: str, any_port: bool = False) -> tuple[str, int]:
    """``HOST:PORT`` (port 1..65535; 0 too with ``any_port``, for a socket to bind); HOST by
    ``host_name``."""
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise ValueError(f"want HOST:PORT, got {text!r}")
    return host_name(host), _port(port, 0 if any_port else 1)


def mavlink_url(text: str) -> str:
    """A pymavlink connection string: ``SCHEME:HOST:PORT`` (schemes ``MAVLINK_SCHEMES``; port 0
    only where the socket binds: udpin, tcpin) or the path of a serial device (a character
    device: pymavlink opens any other existing file as a log to replay, and *executes* one whose
    path ends in .elf or contains /bin/; a path with a colon it takes for a UDP address)."""
    if text.startswith("/") and ":" not in text:
        try:
            mode = os.stat(text).st_mode
        except OSError as exc:
            raise ValueError(f"{text}: {exc.strerror or exc}") from None
        if not stat.S_ISCHR(mode):
            raise ValueError(f"{text}: not a serial device")
        return text
    m = _URL.fullmatch(text)
    if m is None or m["scheme"] not in MAVLINK_SCHEMES:
        raise ValueError(f"want {'|'.join(MAVLINK_SCHEMES)}:HOST:PORT or a serial device /dev/..., got {text!r}")
    _port(m["port"], 0 if m["scheme"] in ("udpin", "tcpin") else 1)
    host_name(m["host"])
    return text


def checked(fn, *args):
    """An argparse ``type=`` from a checker raising ValueError."""
    def convert(text: str):
        try:
            return fn(text, *args)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    convert.__name__ = getattr(fn, "__name__", "value")
    return convert


def _number(text: str, lo: float, hi: float, lo_open: bool) -> float:
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"want a number, got {text!r}") from None
    if not math.isfinite(v) or (v <= lo if lo_open else v < lo) or v > hi:
        raise ValueError(f"must be in {'(' if lo_open else '['}{lo:g}, {hi:g}], got {text!r}")
    return v


def _integer(text: str, lo: int, hi: int) -> int:
    if not re.fullmatch(r"[+-]?[0-9]{1,30}", text.strip(), re.ASCII):
        raise ValueError(f"want an integer, got {text!r}")
    v = int(text)
    if not lo <= v <= hi:
        raise ValueError(f"must be >= {lo}, got {text!r}" if hi >= 2**62 else f"must be in {lo}..{hi}, got {text!r}")
    return v


def number(lo: float, hi: float, lo_open: bool = False):
    """``type=``: a finite float in [lo, hi] (or (lo, hi])."""
    return checked(_number, lo, hi, lo_open)


def integer(lo: int, hi: int):
    """``type=``: an integer in [lo, hi]."""
    return checked(_integer, lo, hi)


SEED = integer(0, 2**63 - 1)  # numpy refuses negative seeds
PORT = checked(lambda text: _port(text, 1))
PORT_BIND = checked(_port, 0)  # 0: any free port
HOST_PORT = checked(host_port)
HOST_PORT_BIND = checked(host_port, True)
MAVLINK_URL = checked(mavlink_url)
SPEEDUP = number(0.0, 1000.0, lo_open=True)


def param_item(text: str) -> tuple[str, float]:
    """``NAME=VALUE`` (an argparse type): an autopilot parameter set at boot (mock or SITL), the
    name upper-cased, the value a finite number (a NaN would reach the firmware's parameter)."""
    name, sep, value = text.partition("=")
    try:
        v = float(value)
    except ValueError:
        v = math.nan
    if not sep or not name.strip() or not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"want NAME=VALUE with a finite number, got {text!r}")
    return name.strip().upper(), v


def writable_path(text: str) -> str:
    """A file to write: its directory exists and is writable, it is not a directory itself
    (checked before anything starts: a thread that opens it later would die with a traceback)."""
    parent = os.path.dirname(os.path.abspath(text)) or "."
    if os.path.isdir(text):
        raise ValueError(f"{text}: is a directory")
    if not os.path.isdir(parent):
        raise ValueError(f"{text}: no directory {parent}")
    if not os.access(parent, os.W_OK) or (os.path.exists(text) and not os.access(text, os.W_OK)):
        raise ValueError(f"{text}: not writable")
    return text


def writable_dir(text: str) -> str:
    """A directory to write into (made if missing, parents too): not a file, and the nearest
    existing directory on its path writable (checked before a long run, not after it)."""
    if os.path.exists(text) and not os.path.isdir(text):
        raise ValueError(f"{text}: exists and is not a directory")
    probe = os.path.abspath(text)
    while not os.path.exists(probe):
        probe = os.path.dirname(probe)
    if not os.path.isdir(probe) or not os.access(probe, os.W_OK):
        raise ValueError(f"{text}: {probe} is not a writable directory")
    try:  # access() says yes to root everywhere, and to pseudo-filesystems (/proc): try one
        os.rmdir(tempfile.mkdtemp(prefix=".pmon-probe-", dir=probe))
    except OSError as err:
        raise ValueError(f"{text}: cannot make a directory in {probe} ({err.strerror})") from None
    return text


def readable_file(text: str, max_bytes: int = 1 << 20) -> str:
    """A regular file this process can read (not a directory, FIFO or device: checked without
    blocking, onboard/files.py), for a file a thread opens later (a certificate, a key)."""
    from onboard.files import read_regular
    read_regular(text, max_bytes)
    return text


OUT_FILE = checked(writable_path)
IN_FILE = checked(readable_file)
OUT_DIR = checked(writable_dir)


def fail(prog: str, message: str) -> int:
    """Print ``prog: message`` (one line) to stderr; the exit code 2, to return."""
    print(f"{prog}: {message.splitlines()[0] if message else 'error'}", file=sys.stderr)
    return 2
