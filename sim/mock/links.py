"""The mock autopilot's MAVLink endpoints and links (UDP in/out, TCP servers), loopback only, each
with its own parser, sequence numbers and stream rates. No protocol logic: sim/mock/autopilot.py."""
from __future__ import annotations

import ipaddress
import math
import socket
from dataclasses import dataclass
from typing import Mapping, Optional

from onboard.app.mavlink2 import mavlink


# --------------------------------------------------------------------------- links

def _check_loopback(host: str) -> None:
    """Only loopback addresses: the mock must never talk to the network."""
    try:
        infos = socket.getaddrinfo(host, None, socket.AF_INET)
    except socket.gaierror as exc:
        raise ValueError(f"cannot resolve {host!r}: {exc}") from exc
    for info in infos:
        if not ipaddress.ip_address(info[4][0]).is_loopback:
            raise ValueError(f"{host!r} is not a loopback address")


@dataclass(frozen=True)
class Endpoint:
    """A MAVLink endpoint: kind 'udpout' (send to host:port), 'udpin' (listen) or 'tcpin'."""

    kind: str
    host: str
    port: int

    @staticmethod
    def parse(text: str) -> "Endpoint":
        """Parse 'udpout:127.0.0.1:14550', 'udpin:...', 'tcpin:...' (also 'udp:'/'tcp:')."""
        kind, _, rest = text.partition(":")
        host, _, port = rest.rpartition(":")
        kind = {"udp": "udpout", "tcp": "tcpin"}.get(kind, kind)
        if kind not in ("udpout", "udpin", "tcpin") or not host or not port.isdigit():
            raise ValueError(f"bad endpoint {text!r}; want udpout|udpin|tcpin:HOST:PORT")
        return Endpoint(kind, host, int(port))

    def __str__(self) -> str:
        return f"{self.kind}:{self.host}:{self.port}"


class _Sink:
    """File-like adapter so pymavlink's MAVLink.send writes through a link."""

    def __init__(self, link: "_Link"):
        self.link = link

    def write(self, data: bytes) -> None:
        self.link.write(data)


class _Link:
    """One MAVLink channel: its own parser, sequence numbers and stream rates."""

    MAX_PENDING = 256 * 1024

    def __init__(self, name: str, sysid: int, compid: int, intervals: Mapping[str, float]):
        self.name = name
        self.parser = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.parser.robust_parsing = True
        self.out = mavlink.MAVLink(_Sink(self), srcSystem=sysid, srcComponent=compid)
        self.intervals = dict(intervals)  # message name -> interval (sim s); 0 = off
        self.next_due: dict[str, float] = {}
        self.active = False  # has received a valid packet (ArduPilot's active channel)
        self.closed = False
        self.tx_errors = 0
        self.muted_until = -math.inf  # fault injection: sim time until which the link is dead
        self.muted = False
        self.port_index = 0  # the endpoint it belongs to (its SRn_ stream rates)

    def fileno(self) -> int:
        raise NotImplementedError

    def receive(self) -> bytes:
        raise NotImplementedError

    def write(self, data: bytes) -> None:
        raise NotImplementedError

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True

    def send(self, msg) -> None:
        self.out.send(msg)


class _UdpLink(_Link):
    def __init__(self, ep: Endpoint, sysid: int, compid: int, intervals: Mapping[str, float]):
        super().__init__(str(ep), sysid, compid, intervals)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if ep.kind == "udpin":
                self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self.sock.bind((ep.host, ep.port))
                self.peer: Optional[tuple] = None  # learned from the last sender
            else:
                self.sock.bind(("127.0.0.1", 0))
                self.peer = (ep.host, ep.port)
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.udpin = ep.kind == "udpin"
        self.local = self.sock.getsockname()

    def fileno(self) -> int:
        return self.sock.fileno()

    def receive(self) -> bytes:
        chunks = []
        while True:
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                continue  # ICMP port unreachable from an earlier send: peer not up yet
            if self.udpin:
                self.peer = addr
            chunks.append(data)
        return b"".join(chunks)

    def write(self, data: bytes) -> None:
        if self.peer is None or self.closed or self.muted:
            return
        try:
            self.sock.sendto(data, self.peer)
        except OSError:
            self.tx_errors += 1

    def close(self) -> None:
        super().close()
        self.sock.close()


class _TcpLink(_Link):
    def __init__(self, sock: socket.socket, name: str, sysid: int, compid: int,
                 intervals: Mapping[str, float]):
        super().__init__(name, sysid, compid, intervals)
        self.sock = sock
        self.sock.setblocking(False)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.pending = bytearray()
        self.dropped = 0

    def fileno(self) -> int:
        return self.sock.fileno()

    def receive(self) -> bytes:
        try:
            data = self.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            data = b""
        if not data:
            self.close()
        return data

    def write(self, data: bytes) -> None:
        if self.closed or self.muted:
            return
        if len(self.pending) + len(data) > self.MAX_PENDING:
            self.dropped += 1  # like ArduPilot with no txspace: drop, never block
            return
        self.pending += data
        self.flush()

    def flush(self) -> None:
        while self.pending and not self.closed:
            try:
                sent = self.sock.send(self.pending)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.close()
                return
            del self.pending[:sent]

    def close(self) -> None:
        if not self.closed:
            super().close()
            self.sock.close()


class _TcpListener:
    def __init__(self, ep: Endpoint, index: int = 0):
        self.index = index  # the endpoint's position: its "serial port" (SRn_ rates)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.sock.bind((ep.host, ep.port))
            self.sock.listen(4)
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.local = self.sock.getsockname()

    def fileno(self) -> int:
        return self.sock.fileno()

    def accept(self) -> Optional[tuple[socket.socket, tuple]]:
        try:
            return self.sock.accept()
        except (BlockingIOError, InterruptedError, OSError):
            return None

    def close(self) -> None:
        self.sock.close()
