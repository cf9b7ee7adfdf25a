"""Reading KrakenSDR's output documents: over HTTP or from a file, on a thread of its own.

KrakenSDR rewrites ``_share/DOA_value.html`` in place each frame (``seek(0)``, ``write``,
``truncate()``) and serves its ``_share`` folder on port 8081 (``php -S`` or ``miniserve``,
krakensdr_doa's ``gui_run.sh``); ``status.json`` beside it is rewritten each frame too. A
reader can therefore catch a document mid-rewrite: the new text's start over the old one's
end, lines that parse but mix two frames. So a document is taken only when two reads in a row
return the same bytes (``stable``): a torn read differs from the next read. An empty document
is never taken (``empty``): a writer that truncates, then writes (status.json, opened "w") and is
descheduled in between leaves it empty for as long as it waits, and two reads agree on it.

``DocumentPoller`` reads every ``poll_s`` (wall s), on thread ``pmon-kraken``, and queues each
new stable document (``queue``, bounded: ``queue_full`` counts what did not fit), parsed on
this thread (``prepare``), for the io thread (onboard/app/kraken/source.py). Nothing it reads can block the app: HTTP has a
total deadline per read (``timeout_s``, enforced on every receive: a server trickling its status
line, its headers or its body is cut off), one request per read on a kept-alive connection,
documents are capped at ``MAX_DOC_BYTES`` (``too_large``), a file must be a regular file
(onboard/files.py: a FIFO or /dev/zero is refused, not read). A failing source is retried with a
back-off doubling up to ``MAX_BACKOFF_S``, reconnecting each time; failures are counted by kind
(``errors``) and an episode of them is visible to the app (``down``, ``last_error``). Nothing it
reads can end the thread either: an exception is counted (``restarts``) and the reader restarted.
"""
from __future__ import annotations

import http.client
import math
import socket
import threading
import time
from collections import deque
from typing import Callable
from urllib.parse import urlsplit

from onboard.app.kraken.line import MAX_DOC_BYTES
from onboard.files import FileRefused, read_regular

MAX_STATUS_BYTES = 16384  # status.json is ~600 bytes
QUEUE_MAX = 64  # documents waiting for the io thread (~3 s of KrakenSDR's frames)
MAX_BACKOFF_S = 1.0
STABLE_TRIES = 4  # reads to get two equal ones in a row before giving up this poll
STABLE_GAP_S = 0.01  # between them (KrakenSDR's seek-write-truncate takes microseconds, a loaded host ms)


class FetchError(Exception):
    def __init__(self, kind: str, detail: str):
        super().__init__(f"{kind}: {detail}")
        self.kind = kind
        self.detail = detail


class _DeadlineSocket(socket.socket):
    """A socket whose every receive waits at most until ``deadline`` (monotonic s): http.client's
    own timeout is per receive, so a peer trickling its status line or sending ``100 Continue``
    after ``100 Continue`` would hold it for as long as it likes."""

    __slots__ = ("deadline", "_mono")

    def recv_into(self, buffer, nbytes=0, flags=0):
        left = self.deadline - self._mono()
        if left <= 0:
            raise TimeoutError("read deadline passed")
        self.settimeout(left)
        return super().recv_into(buffer, nbytes, flags)


class _Connection(http.client.HTTPConnection):
    """An HTTPConnection on a ``_DeadlineSocket``; ``begin(deadline)`` before each request."""

    deadline = math.inf

    def __init__(self, host: str, port: int, monotonic: Callable[[], float]):
        super().__init__(host, port)
        self._mono = monotonic

    def begin(self, deadline: float) -> None:
        self.deadline = deadline
        if self.sock is not None:  # kept alive: its timeout still the previous read's remainder
            self.sock.deadline = deadline
            self.sock.settimeout(max(deadline - self._mono(), 1e-3))

    def connect(self) -> None:
        err: OSError | None = None
        for af, kind, proto, _, addr in socket.getaddrinfo(self.host, self.port, 0, socket.SOCK_STREAM):
            sock = _DeadlineSocket(af, kind, proto)
            sock.deadline, sock._mono = self.deadline, self._mono
            try:
                sock.settimeout(max(self.deadline - self._mono(), 1e-3))
                sock.connect(addr)
            except OSError as exc:
                sock.close()
                err = exc
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.sock = sock
            return
        raise err if err is not None else OSError(f"{self.host}: no address")


class HttpSource:
    """GET one URL on a kept-alive connection, reconnecting after any failure. Each ``get`` is
    over within ``timeout_s`` (connecting, the status line, the headers, the body, and the one
    retry of a kept-alive connection the server had closed), whatever the server sends."""

    def __init__(self, url: str, cap: int, timeout_s: float = 1.0,
                 monotonic: Callable[[], float] = time.monotonic):
        u = urlsplit(url)
        if u.scheme != "http" or not u.hostname:
            raise ValueError(f"{url!r}: want http://HOST[:PORT]/PATH")
        if not url.isascii():  # http.client would raise UnicodeEncodeError at the first request
            raise ValueError(f"{url!r}: not ASCII (percent-encode its path and query)")
        self.url, self.host, self.port = url, u.hostname, u.port or 80
        self.path = (u.path or "/") + (f"?{u.query}" if u.query else "")
        self.cap, self.timeout_s, self._mono = cap, timeout_s, monotonic
        self.conn: _Connection | None = None
        self.requests = 0  # requests sent
        self.retries = 0  # ... of them again on a new connection, the kept-alive one having been closed

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def get(self) -> bytes:
        deadline = self._mono() + self.timeout_s
        reused = self.conn is not None
        try:
            return self._get(deadline)
        except FetchError as exc:
            self.close()
            if reused and exc.kind == "closed":  # the server closed the kept-alive connection: once more
                self.retries += 1
                try:
                    return self._get(deadline)
                except FetchError:
                    self.close()
                    raise
            raise

    def _get(self, deadline: float) -> bytes:
        try:
            if self.conn is None:
                self.conn = _Connection(self.host, self.port, self._mono)
            self.conn.begin(deadline)
            self.requests += 1
            self.conn.request("GET", self.path, headers={"Cache-Control": "no-cache"})
            resp = self.conn.getresponse()
            length = resp.getheader("Content-Length")
            if resp.status != 200:
                raise FetchError("http_status", f"HTTP {resp.status} {resp.reason[:40]!r} for {self.url}")
            if length is not None and not (length.isascii() and length.isdigit()):
                raise FetchError("bad_http", f"{self.url}: Content-Length {length[:20]!r} is not a number")
            if length is not None and int(length) > self.cap:
                raise FetchError("too_large", f"{length} bytes > {self.cap}")
            chunks, total = [], 0
            while True:
                b = resp.read1(min(16384, self.cap + 1 - total))
                if not b:
                    break
                chunks.append(b)
                total += len(b)
                if total > self.cap:
                    raise FetchError("too_large", f"more than {self.cap} bytes")
            if length is not None and not resp.chunked and total != int(length):  # the server closed mid-body
                raise FetchError("bad_http", f"{self.url}: {total} of {length} bytes")
            resp.close()  # read whole: the connection is free for the next request (read1 leaves it busy)
            if resp.will_close:
                self.close()
            return b"".join(chunks)
        except FetchError:
            raise
        except ConnectionRefusedError:
            raise FetchError("connection_refused", f"{self.host}:{self.port} refused the connection") from None
        except (TimeoutError, socket.timeout):
            raise FetchError("timeout", f"{self.url}: not read within {self.timeout_s:g} s") from None
        except (http.client.RemoteDisconnected, ConnectionResetError, BrokenPipeError) as exc:
            raise FetchError("closed", f"{self.url}: {type(exc).__name__}") from None
        except http.client.HTTPException as exc:
            raise FetchError("bad_http", f"{self.url}: {type(exc).__name__} {str(exc)[:60]!r}") from None
        except OSError as exc:
            raise FetchError("network", f"{self.url}: {exc.strerror or exc}") from None


class FileSource:
    """Read one regular file whole (KrakenSDR on this computer: its _share folder)."""

    def __init__(self, path: str, cap: int):
        self.path = path[len("file://"):] if path.startswith("file://") else path
        self.url, self.cap = path, cap

    def close(self) -> None:
        pass

    def get(self) -> bytes:
        try:
            return read_regular(self.path, self.cap)
        except FileRefused as exc:
            kind = "too_large" if "more than" in str(exc) else "file"
            raise FetchError(kind, str(exc)) from None


def source_for(url: str, cap: int, timeout_s: float = 1.0):
    return HttpSource(url, cap, timeout_s) if url.startswith("http://") else FileSource(url, cap)


def status_url_for(url: str, status_url: str | None) -> str | None:
    """``status_url`` resolved: ``auto`` is status.json in the folder of ``url``, None none."""
    if status_url is None:
        return None
    if status_url != "auto":
        return status_url
    base = url.split("?", 1)[0]
    return base[:base.rfind("/") + 1] + "status.json"


class DocumentPoller:
    """Poll the DoA document (and the status document) every ``poll_s``; queue new stable ones
    as ``(kind, bytes, local_s)`` with kind ``doa`` or ``status``."""

    def __init__(self, url: str, status_url: str | None, poll_s: float, queue_max: int = QUEUE_MAX,
                 timeout_s: float = 1.0, monotonic: Callable[[], float] = time.monotonic,
                 prepare: dict[str, Callable[[bytes], object]] | None = None):
        self.sources = {"doa": source_for(url, MAX_DOC_BYTES, timeout_s)}
        if status_url:
            self.sources["status"] = source_for(status_url, MAX_STATUS_BYTES, timeout_s)
        self.url = url
        self.poll_s = float(poll_s)
        self.queue_max = queue_max
        self._mono = monotonic
        self.prepare = dict(prepare or {})  # kind -> what this thread makes of a new document (parse it)
        self.queue: deque[tuple[str, object, float]] = deque()
        self._last: dict[str, bytes | None] = {k: None for k in self.sources}
        self.reads = 0
        self.documents = 0  # new stable documents queued
        self.unstable = 0  # polls whose document changed under every read
        self.empty = 0  # polls that found the document empty (between a writer's truncate and write)
        self.queue_full = 0
        self.errors: dict[str, int] = {}  # "doa connection_refused" -> count
        self.last_error: dict[str, str] = {}  # kind -> its newest failure
        self.down = {k: False for k in self.sources}  # in an episode of failures
        self.restarts = 0  # times the reader raised and was restarted (_run)
        self.crash: str | None = None  # the newest such error
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> "DocumentPoller":
        self._thread = threading.Thread(target=self._run, name="pmon-kraken", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        for s in self.sources.values():
            s.close()

    def pop(self, n: int) -> list[tuple[str, object, float]]:
        out = []
        while self.queue and len(out) < n:
            out.append(self.queue.popleft())
        return out

    def _run(self) -> None:
        """The reader, restarted (its connections closed, after ``MAX_BACKOFF_S``) if it raises:
        whatever a peer sends, this thread does not end before ``stop``. Each restart is counted
        (``restarts``) and the newest one's cause kept (``crash``) for the app to say."""
        while not self._stop.is_set():
            try:
                self._schedule()
            except Exception as exc:  # a reader that fails on input must not end
                self.restarts += 1
                self.crash = f"{type(exc).__name__}: {str(exc)[:80]}"
                for s in self.sources.values():
                    s.close()
                self._stop.wait(MAX_BACKOFF_S)

    def _schedule(self) -> None:
        """Each source on its own schedule: every ``poll_s``, or after failures a back-off
        doubling up to ``MAX_BACKOFF_S`` (a missing status.json never slows the DoA's reads)."""
        due = {kind: self._mono() for kind in self.sources}
        failures = dict.fromkeys(self.sources, 0)
        while not self._stop.is_set():
            for kind in self.sources:
                if self._mono() < due[kind]:
                    continue
                ok = self.poll(kind)
                failures[kind] = 0 if ok else failures[kind] + 1
                wait = self.poll_s if ok else min(self.poll_s * 2 ** failures[kind], max(MAX_BACKOFF_S, self.poll_s))
                due[kind] = self._mono() + wait
            self._stop.wait(max(min(due.values()) - self._mono(), 0.0))

    def poll(self, kind: str) -> bool:
        """One read of ``kind``'s source; False when it failed."""
        src = self.sources[kind]
        try:
            a = self._read(src)
            if a == self._last[kind]:
                self.down[kind] = False
                return True
            for _ in range(STABLE_TRIES):  # a torn read differs from the next one
                self._stop.wait(STABLE_GAP_S)  # ... a little later than KrakenSDR's rewrite takes
                b = self._read(src)
                if a == b:
                    break
                a = b
            else:
                self.unstable += 1
                return True
        except FetchError as exc:
            key = f"{kind} {exc.kind}"
            self.errors[key] = self.errors.get(key, 0) + 1
            self.last_error[kind] = f"{src.url}: {exc}"
            self.down[kind] = True
            return False
        self.down[kind] = False
        if not a:  # truncated, not yet rewritten (a writer descheduled between the two): no document
            self.empty += 1
            return True
        self._last[kind] = a
        if len(self.queue) >= self.queue_max:
            self.queue_full += 1
            return True
        fn = self.prepare.get(kind)
        self.queue.append((kind, a if fn is None else fn(a), self._mono()))
        self.documents += 1
        return True

    def _read(self, src) -> bytes:
        self.reads += 1
        return src.get()
