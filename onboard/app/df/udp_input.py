"""DF datagram input: the UDP socket, who may send on it, how fast, and the thread that reads it.

Threat: anyone who can reach the DF port can send datagrams. Parsing one costs the io thread
tens of microseconds (JSON, checks, the app lock); reading one costs a few. So the reader
(thread ``pmon-df``) only reads, filters and queues, and the io thread parses what was queued:

* **Source filter.** A datagram is taken only from an accepted source: the ``--df-from`` list
  (``HOST`` = any port of that host, ``HOST:PORT`` = that sender only), or, without a list,
  the first peer whose datagram parses as a valid DF datagram (``lock``; the io thread decides,
  since only it parses). Garbage cannot take the lock; a stranger's *valid* datagram sent before
  the DF's can, which is why a network with strangers on it wants ``--df-from``. Everything else
  is dropped unparsed (``dropped["foreign_source"]``), its address kept for one report
  (``foreign``, at most ``MAX_FOREIGN`` addresses).
* **Per-source rate limit.** A token bucket per accepted source (``rate_hz`` datagrams/s, burst
  ``rate_hz`` = 1 s): an accepted source that floods loses its own excess
  (``dropped["rate_limited"]``), good or bad; it cannot make the io thread parse more than
  ``rate_hz`` datagrams/s from it. A DF sends one datagram per channel per scan (~1/s each).
  Before the lock every sender has a bucket (``MAX_PENDING_SOURCES``, least recently used
  evicted).
* **Drained at line rate.** The reader blocks in ``select`` and then reads until the socket is
  empty, with a receive buffer as large as the kernel allows (``RCVBUF_BYTES``, capped by
  ``net.core.rmem_max``). Reading, filtering and queueing a datagram costs ~4 us of one core
  (3.8-4.0 us at 20 000 foreign datagrams/s, bench/df_flood.py), so such a flood takes ~8 % of a
  core and never reaches the parser: the kernel buffer does not fill (0 kernel drops measured),
  the DF's datagrams are not lost. The queue to the io thread is bounded (``queue_max``; beyond it
  ``dropped["queue_full"]``): the io thread parses at most a budget per loop iteration, so its
  periodic jobs always run.

Why a thread and not ``connect()``: a connected UDP socket would make the kernel drop other
senders, but unseen: an operator whose DF was locked out by an early stranger would see only
"no DF data". Here every refusal is counted and the first from each address is reported.

The reader keeps its own counters (one writer: this thread); the app reads them.
"""
from __future__ import annotations

import ipaddress
import select
import socket
import threading
import time
from collections import OrderedDict, deque
from dataclasses import dataclass
from typing import Callable

from onboard.app.df.datagram import MAX_BYTES

RCVBUF_BYTES = 4 << 20  # asked for; Linux doubles it and caps it at net.core.rmem_max
DEFAULT_RATE_HZ = 1000.0  # datagrams/s per accepted source (a DF sends n_targets x its scan rate)
QUEUE_MAX = 4096  # datagrams waiting for the io thread
MAX_FOREIGN = 16  # foreign addresses remembered for a report
MAX_PENDING_SOURCES = 64  # senders with a bucket before the lock
DROP_REASONS = ("foreign_source", "rate_limited", "queue_full")


@dataclass(frozen=True)
class Source:
    """An accepted sender: ``port`` None = any port of ``host``."""

    host: str
    port: int | None = None

    def matches(self, addr: tuple[str, int]) -> bool:
        return addr[0] == self.host and (self.port is None or addr[1] == self.port)

    def __str__(self) -> str:
        return self.host if self.port is None else f"{self.host}:{self.port}"


def parse_sources(text: str) -> tuple[Source, ...]:
    """``--df-from``: comma-separated ``HOST`` or ``HOST:PORT`` (IPv4 addresses, the form the
    socket reports senders in). ValueError with a one-line message naming the bad item."""
    if not text.strip():
        raise ValueError("empty list")
    out = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            raise ValueError(f"empty item in {text!r}")
        host, sep, port = item.partition(":")
        try:
            host = str(ipaddress.IPv4Address(host))
        except ValueError:
            raise ValueError(f"{item!r}: want an IPv4 address, optionally :PORT") from None
        if not sep:
            out.append(Source(host))
            continue
        if not (port.isascii() and port.isdigit()) or not 1 <= int(port) <= 65535:
            raise ValueError(f"{item!r}: port must be 1..65535")
        out.append(Source(host, int(port)))
    return tuple(out)


class _Bucket:
    __slots__ = ("tokens", "last")

    def __init__(self, burst: float, now: float):
        self.tokens, self.last = burst, now


class DfInput:
    """The DF port: ``start()`` the reader, ``pop()`` from the io thread, ``stop()``."""

    def __init__(self, host: str, port: int, sources: tuple[Source, ...] = (),
                 rate_hz: float = DEFAULT_RATE_HZ, queue_max: int = QUEUE_MAX,
                 monotonic: Callable[[], float] = time.monotonic):
        if not rate_hz > 0:
            raise ValueError(f"DF rate limit must be > 0 datagrams/s, got {rate_hz}")
        self.sources = tuple(sources)
        self.rate_hz = float(rate_hz)
        self.queue_max = queue_max
        self._mono = monotonic
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:  # room for a burst while this thread waits for the CPU: queued, not dropped unseen
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        except OSError:
            pass
        try:
            self.sock.bind((host, port))
        except BaseException:
            self.sock.close()
            raise
        self.sock.setblocking(False)
        self.port = self.sock.getsockname()[1]
        self.locked: Source | None = None  # the first valid peer (no --df-from)
        self.queue: deque[tuple[bytes, tuple[str, int]]] = deque()
        self.received = 0  # datagrams read from the socket
        self.queued = 0
        self.dropped = {r: 0 for r in DROP_REASONS}
        self.foreign: dict[tuple[str, int], int] = {}  # first MAX_FOREIGN refused senders -> count
        self._buckets: OrderedDict[object, _Bucket] = OrderedDict()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ----- the io thread's side
    def accepts(self, addr: tuple[str, int]) -> bool:
        """Is ``addr`` an accepted source now (before the lock without a list: anyone)."""
        return self._source_of(addr) is not None

    def lock(self, addr: tuple[str, int]) -> bool:
        """Accept only ``addr`` from now on (the first valid peer); True if this locked it."""
        if self.sources or self.locked is not None:
            return False
        self.locked = Source(addr[0], addr[1])
        return True

    def pop(self, n: int) -> list[tuple[bytes, tuple[str, int]]]:
        """Up to ``n`` queued (datagram, sender), oldest first."""
        out = []
        q = self.queue
        while q and len(out) < n:
            out.append(q.popleft())
        return out

    @property
    def thread_id(self) -> int | None:
        """The reader thread's native id (its CPU time: /proc/self/task/ID/stat), None if not started."""
        return self._thread.native_id if self._thread is not None else None

    @property
    def dropped_total(self) -> int:
        return sum(self.dropped.values())

    # ----- reader thread
    def start(self) -> "DfInput":
        self._thread = threading.Thread(target=self._run, name="pmon-df", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self.sock.close()

    def _source_of(self, addr: tuple[str, int]):
        """The bucket key of an accepted sender, None for a foreign one."""
        if self.sources:
            for s in self.sources:
                if s.matches(addr):
                    return s
            return None
        locked = self.locked
        if locked is not None:
            return locked if locked.matches(addr) else None
        return addr  # before the lock: each sender on its own

    def _run(self) -> None:
        sock = self.sock
        size = MAX_BYTES + 1  # a longer datagram is cut to this and parsed as too_large
        while not self._stop.is_set():
            try:
                readable, _, _ = select.select([sock], [], [], 0.1)
            except (OSError, ValueError):
                return  # closed under us: stop() is running
            if not readable:
                continue
            now = self._mono()
            while True:  # until the socket is empty: the kernel buffer never fills behind us
                try:
                    data, addr = sock.recvfrom(size)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    break
                self.received += 1
                self._admit(data, addr, now)

    def _admit(self, data: bytes, addr: tuple[str, int], now: float) -> None:
        key = self._source_of(addr)
        if key is None:
            self.dropped["foreign_source"] += 1
            if addr in self.foreign or len(self.foreign) < MAX_FOREIGN:
                self.foreign[addr] = self.foreign.get(addr, 0) + 1
            return
        b = self._buckets.get(key)
        if b is None:
            b = self._buckets[key] = _Bucket(self.rate_hz, now)
            while len(self._buckets) > MAX_PENDING_SOURCES:
                self._buckets.popitem(last=False)
        else:
            self._buckets.move_to_end(key)
            b.tokens = min(self.rate_hz, b.tokens + (now - b.last) * self.rate_hz)
            b.last = now
        if b.tokens < 1.0:
            self.dropped["rate_limited"] += 1
            return
        b.tokens -= 1.0
        if len(self.queue) >= self.queue_max:
            self.dropped["queue_full"] += 1
            return
        self.queue.append((data, addr))
        self.queued += 1
