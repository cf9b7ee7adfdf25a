"""A program in a network namespace of its own, reached from the host's loopback through UDP relays.

For firmware that binds its UDP ports on all interfaces and sends to fixed loopback ports (PX4
SITL: INADDR_ANY, every instance's ground-station link to 127.0.0.1:14550): inside a namespace
whose only interface is loopback nothing outside the machine can reach it, and parallel
instances never meet on a port. The host side is UDP sockets on 127.0.0.1 that the caller binds
(port 0: the kernel's free port, no probing) and hands over as inherited file descriptors, so
they outlive a restart of the program (its clients keep their sockets and ports).

    python -m sim.firmware.netns --check                          # exit 0 if a namespace can be made here
    python -m sim.firmware.netns --parent PID --link FD,BIND,TARGET,PUSH[,PUSH...] ... -- PROGRAM ARGS...

Each ``--link`` joins one host socket (inherited fd ``FD``) to one inner socket bound to
127.0.0.1:``BIND`` in the namespace, which sends to 127.0.0.1:``TARGET`` there (the program's
port). A datagram from the program goes to every ``PUSH`` port on the host's 127.0.0.1 (clients
listening where the firmware would send: ``udpin:``) and to every host peer heard from in the
last ``PEER_TTL_S`` (clients that talk first: ``udpout:``); a datagram from any host peer goes
to the program. Datagrams are relayed whole, never parsed. Datagrams that queued on a host
socket while no relay ran (the program restarting) are dropped at start: nobody was listening.

The namespace is made with unshare(2): CLONE_NEWNET as root, else CLONE_NEWUSER | CLONE_NEWNET
(unprivileged user namespaces; the program then runs as the namespace's root, its files owned by
the caller). Loopback is brought up with an ioctl (no iproute2 needed). SIGTERM / SIGINT are
passed to the program; the relay ends when it exits, with its exit status. If the parent PID
goes away (the caller killed) the program is killed and the relay ends.
"""
from __future__ import annotations

import argparse
import ctypes
import errno
import fcntl
import os
import selectors
import signal
import socket
import struct
import subprocess
import sys
import time

CLONE_NEWNET = 0x40000000
CLONE_NEWUSER = 0x10000000
SIOCGIFFLAGS, SIOCSIFFLAGS, IFF_UP = 0x8913, 0x8914, 0x1
PEER_TTL_S = 120.0  # wall s: a talk-first client silent this long is no longer sent to
MAX_DATAGRAM = 65535
PR_SET_PDEATHSIG = 1


class NamespaceError(OSError):
    """No network namespace could be made (the message says why in one line)."""


def _libc():
    return ctypes.CDLL(None, use_errno=True)


def enter_new_netns() -> str:
    """Move this (single-threaded) process into a new network namespace with loopback up.
    Returns how: "netns" (as root) or "userns+netns"."""
    libc = _libc()
    how = "netns"
    if libc.unshare(CLONE_NEWNET) != 0:
        err = ctypes.get_errno()
        if err not in (errno.EPERM, errno.EACCES):
            raise NamespaceError(err, f"unshare(CLONE_NEWNET): {os.strerror(err)}")
        uid, gid = os.getuid(), os.getgid()
        if libc.unshare(CLONE_NEWUSER | CLONE_NEWNET) != 0:
            err = ctypes.get_errno()
            raise NamespaceError(err, f"unshare(CLONE_NEWNET) needs root and unshare(CLONE_NEWUSER) "
                                      f"failed too ({os.strerror(err)}): enable unprivileged user "
                                      f"namespaces (sysctl user.max_user_namespaces) or run as root")
        for path, text in (("/proc/self/setgroups", "deny"), ("/proc/self/uid_map", f"0 {uid} 1"),
                           ("/proc/self/gid_map", f"0 {gid} 1")):
            with open(path, "w") as f:
                f.write(text)
        how = "userns+netns"
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        ifr = struct.pack("16sh22x", b"lo", 0)
        flags = struct.unpack("16sh22x", fcntl.ioctl(s, SIOCGIFFLAGS, ifr))[1]
        fcntl.ioctl(s, SIOCSIFFLAGS, struct.pack("16sh22x", b"lo", flags | IFF_UP))
    return how


class Relay:
    """One host socket joined to one inner socket (see the module's docstring)."""

    def __init__(self, host: socket.socket, bind_port: int, target_port: int, push: list[int]):
        self.host = host
        self.inner = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.inner.bind(("127.0.0.1", bind_port))
        self.inner.setblocking(False)
        self.host.setblocking(False)
        self.target = ("127.0.0.1", target_port)
        self.push = [("127.0.0.1", p) for p in push]
        self.peers: dict[tuple, float] = {}  # talk-first clients: address -> wall s last heard
        self.counts = {"in": 0, "out": 0}

    def drain_host(self) -> int:
        n = 0
        while True:
            try:
                self.host.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return n
            except OSError:
                return n
            n += 1

    def from_host(self) -> None:
        for _ in range(256):
            try:
                data, addr = self.host.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # an ICMP error of an earlier send: nothing to relay
                continue
            if addr not in self.push:
                self.peers[addr] = time.monotonic()
            self.counts["in"] += 1
            try:
                self.inner.sendto(data, self.target)
            except OSError:  # the program's port not open yet (booting): dropped, as by the network
                pass

    def from_inner(self) -> None:
        now = time.monotonic()
        for addr in [a for a, t in self.peers.items() if now - t > PEER_TTL_S]:
            del self.peers[addr]
        for _ in range(256):
            try:
                data, _addr = self.inner.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                continue
            self.counts["out"] += 1
            for dest in (*self.push, *self.peers):
                try:
                    self.host.sendto(data, dest)
                except OSError:  # no listener there (yet): dropped
                    pass


def _parse_link(text: str) -> tuple[int, int, int, list[int]]:
    parts = [int(x) for x in text.split(",")]
    if len(parts) < 3:
        raise argparse.ArgumentTypeError(f"--link wants FD,BIND,TARGET[,PUSH...], got {text!r}")
    return parts[0], parts[1], parts[2], parts[3:]


def run(links: list[tuple[int, int, int, list[int]]], argv: list[str], parent: int | None) -> int:
    enter_new_netns()
    relays = []
    for fd, bind_port, target_port, push in links:
        host = socket.socket(fileno=fd)
        relays.append(Relay(host, bind_port, target_port, push))
    dropped = sum(r.drain_host() for r in relays)
    if dropped:
        print(f"sim.firmware.netns: dropped {dropped} datagrams queued while no relay ran", file=sys.stderr, flush=True)

    def pdeathsig():  # the program dies with the relay (this process is single-threaded)
        _libc().prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    child = subprocess.Popen(argv, stdin=subprocess.DEVNULL, preexec_fn=pdeathsig)
    pending: list[int] = []
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda s, _f: pending.append(s))
    sel = selectors.DefaultSelector()
    for r in relays:
        sel.register(r.host, selectors.EVENT_READ, r.from_host)
        sel.register(r.inner, selectors.EVENT_READ, r.from_inner)
    while child.poll() is None:
        while pending:
            child.send_signal(pending.pop(0))
        if parent is not None and os.getppid() != parent:
            child.kill()
            break
        for key, _ in sel.select(timeout=0.2):
            key.data()
    rc = child.wait()
    return rc if rc >= 0 else 128 - rc


def check() -> int:
    """Exit status 0 if a namespace with loopback up can be made here; else say why."""
    try:
        how = enter_new_netns()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
    except OSError as exc:
        print(f"sim.firmware.netns: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(how)
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    program: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, program = argv[:i], argv[i + 1:]
    ap = argparse.ArgumentParser(prog="python -m sim.firmware.netns", description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="only check that a namespace can be made")
    ap.add_argument("--parent", type=int, help="end (killing the program) when this PID is no longer the parent")
    ap.add_argument("--link", action="append", default=[], type=_parse_link, metavar="FD,BIND,TARGET[,PUSH...]")
    args = ap.parse_args(argv)
    if args.check:
        return check()
    if not program:
        ap.error("no program given after --")
    try:
        return run(args.link, program, args.parent)
    except OSError as exc:
        print(f"sim.firmware.netns: {exc}", file=sys.stderr)
        return 125


if __name__ == "__main__":
    sys.exit(main())
