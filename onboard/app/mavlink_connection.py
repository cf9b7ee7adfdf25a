"""The app's MAVLink 2 connection: pymavlink, one I/O lock, a tlog of both directions, and a
reconnect that never blocks the caller.

URLs as pymavlink takes them: ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``tcp:HOST:PORT``,
``tcpin:HOST:PORT``, or a serial device ``/dev/ttyUSB0`` with ``baud``.

A stream link (TCP, serial) can drop: the autopilot reboots, a cable or a telemetry bridge
restarts. pymavlink's own ``autoreconnect`` reconnects inside whichever call saw the error,
sleeping there between attempts, and is not thread-safe (two threads reconnecting at once
raise AttributeError from inside pymavlink: the app's watchdog died of it when an ArduPilot
SITL restarted). So here the link is marked down on the first error, every send and receive
returns at once while it is down (sends are counted, not queued: a setpoint is only good when
fresh), and a daemon thread opens a new connection once a second and swaps it in under the
lock. Users learn of it from ``up`` and, for the autopilot, from its heartbeats stopping and
coming back; they re-request their message rates then.
"""
from __future__ import annotations

import contextlib
import io
import struct
import threading
import time

from onboard.app.mavlink2 import mavlink, mavutil

COMP_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191
RECONNECT_S = 1.0  # wall seconds between attempts to reopen a dropped stream link
LINK_ID = 1  # the signing link id this end stamps: one per connection (MAVLink 2 signing)


class _PeerGone(Exception):
    """Raised from pymavlink's disconnect hooks instead of its blocking reconnect."""


def param_name(raw) -> str:
    """A PARAM_* message's param_id as text (pymavlink gives str or bytes, NUL-padded)."""
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


def _header_of_unknown(msg, buf: bytes) -> None:
    """pymavlink 2.4.50 leaves a message its dialect does not define (PX4's EVENT) without its
    header: its source read 0/0. Read it from the frame, so such a message is routed by its
    sender as every other one."""
    if len(buf) >= 10 and buf[0] == mavlink.PROTOCOL_MARKER_V2:
        msg._header = mavlink.MAVLink_header(msg.get_msgId(), buf[2], buf[3], buf[1], buf[4], buf[5], buf[6])
    elif len(buf) >= 6 and buf[0] == mavlink.PROTOCOL_MARKER_V1:
        msg._header = mavlink.MAVLink_header(msg.get_msgId(), 0, 0, buf[1], buf[2], buf[3], buf[4])


def _is_stream(url: str) -> bool:
    return not url.startswith(("udp:", "udpin:", "udpout:", "udpbcast:"))


class Link:
    """A pymavlink connection the app's threads share.

    ``recv()`` is for one reader thread; ``send()`` is safe from any thread. Every message
    received or sent is appended to the tlog (8-byte big-endian UNIX microseconds + the raw
    packet: the format mavlogdump.py and MAVProxy read). ``wait_for_peer``: a TCP peer that
    refuses at start (an autopilot still booting) is retried in the background instead of
    failing the constructor.
    """

    def __init__(self, url: str, baud: int = 57600, tlog_path: str | None = None,
                 source_system: int = 1, source_component: int = COMP_ID,
                 signing_key: bytes | None = None, wait_for_peer: bool = False,
                 unsigned_from: tuple[tuple[int, int], ...] = ()):
        self.url = url
        self.baud = baud
        self._source = [source_system, source_component]
        self._key = signing_key
        self._unsigned_from = tuple(unsigned_from)  # senders taken unsigned (signing.configure)
        self.signing = signing_key is not None
        self._lock = threading.Lock()
        self._tlog = open(tlog_path, "wb") if tlog_path else None
        self.sent = 0
        self.received = 0
        self.send_errors = 0
        self._closed = False
        self._reconnector: threading.Thread | None = None
        self.conn = None
        try:
            self.conn = self._open()
        except ConnectionRefusedError:
            if not (wait_for_peer and _is_stream(url)):
                raise
            self._mark_down()
        self._mav = self.conn.mav if self.conn is not None else self._encoder()

    # ----- opening
    def _open(self):
        with contextlib.redirect_stdout(io.StringIO()):  # pymavlink prints its attempts
            conn = mavutil.mavlink_connection(
                self.url, baud=self.baud, source_system=self._source[0],
                source_component=self._source[1], dialect="ardupilotmega", autoreconnect=False,
                retries=0)
        if getattr(conn, "WIRE_PROTOCOL_VERSION", "2.0") != "2.0":
            raise RuntimeError("pymavlink loaded MAVLink 1; import mavutil from onboard.app.mavlink2")
        conn.mav.robust_parsing = True

        def gone(*_):
            raise _PeerGone()
        # pymavlink calls these on EOF / reset; its own versions reconnect (blocking) or do
        # nothing and leave a dead socket
        conn.handle_disconnect = gone
        conn.handle_eof = gone
        if self._key is not None:  # unsigned / wrongly signed packets become BAD_DATA
            from onboard.app.signing import apply
            apply(conn, self._key, LINK_ID, self._unsigned_from)
        return conn

    def _encoder(self) -> mavlink.MAVLink:
        """A protocol object to encode with while no connection exists yet."""
        mav = mavlink.MAVLink(None, srcSystem=self._source[0], srcComponent=self._source[1])
        mav.robust_parsing = True
        return mav

    def _adopt(self, new) -> None:
        """Carry the protocol state of the old connection over to a reopened one (under the
        lock): our system id, the packet sequence, and the signing clock and replay stamps, so
        no timestamp goes backwards and no old packet is accepted again."""
        old = self._mav
        new.mav.srcSystem, new.mav.srcComponent = self._source
        new.mav.seq = old.seq
        if self._key is not None and getattr(old, "signing", None) is not None:
            s_old, s_new = old.signing, new.mav.signing
            s_new.timestamp = max(s_new.timestamp, s_old.timestamp)
            s_new.stream_timestamps.update(s_old.stream_timestamps)
        self.conn, self._mav = new, new.mav

    @property
    def mav(self) -> mavlink.MAVLink:
        """Message constructors (``link.mav.heartbeat_encode(...)``); send with ``send``."""
        return self._mav

    @property
    def up(self) -> bool:
        return self.conn is not None

    def set_source_system(self, sysid: int) -> None:
        with self._lock:
            self._source[0] = sysid
            self._mav.srcSystem = sysid

    # ----- dropping and reopening
    def _mark_down(self) -> None:
        """Close a dropped stream link and start reopening it (caller holds the lock, or is
        the constructor)."""
        conn, self.conn = self.conn, None
        if conn is not None:
            with contextlib.suppress(Exception):
                conn.close()
        if self._reconnector is None and not self._closed:
            self._reconnector = threading.Thread(target=self._reconnect_loop, name="mavlink-reconnect",
                                                 daemon=True)
            self._reconnector.start()

    def _reconnect_loop(self) -> None:
        while not self._closed:
            time.sleep(RECONNECT_S)
            try:
                new = self._open()
            except Exception:  # refused, reset, device absent: try again later
                continue
            with self._lock:
                if self._closed:
                    with contextlib.suppress(Exception):
                        new.close()
                    return
                self._adopt(new)
                self._reconnector = None
            return

    # ----- I/O
    def _log(self, buf: bytes) -> None:
        if self._tlog is not None:
            self._tlog.write(struct.pack(">Q", int(time.time() * 1e6)) + bytes(buf))

    def send(self, msg) -> bool:
        with self._lock:
            if self.conn is None:
                self.send_errors += 1
                return False
            try:
                self.conn.mav.send(msg)
            except (_PeerGone, OSError):
                self.send_errors += 1
                if _is_stream(self.url):
                    self._mark_down()
                return False
            except (ValueError, struct.error):
                self.send_errors += 1
                return False
            self.sent += 1
            self._log(msg.get_msgbuf())
            return True

    def fileno(self) -> int | None:
        conn = self.conn
        fd = getattr(conn, "fd", None) if conn is not None else None
        return fd if isinstance(fd, int) and fd >= 0 else None

    def recv(self):
        """The next parsed message or None (non-blocking; None while the link is down).
        BAD_DATA is returned too.

        On UDP every datagram carries whole frames, so a partial frame left in the parser when a
        datagram is used up can never complete: it is dropped before the next datagram, or a
        garbage datagram (a stray 0xFD and a large length) would swallow the good ones after it.
        """
        with self._lock:
            conn = self.conn
            if conn is None:
                return None
            try:
                if isinstance(conn, mavutil.mavudp):
                    mav = conn.mav
                    msg = mav.parse_char(b"") if mav.buf_len() else None  # frames already buffered
                    if msg is not None:
                        conn.post_message(msg)
                    else:
                        mav.buf, mav.buf_index = bytearray(), 0
                        mav.expected_length = mavlink.HEADER_LEN_V1 + 2
                        msg = conn.recv_msg()
                else:
                    msg = conn.recv_msg()
            except (_PeerGone, OSError):
                if _is_stream(self.url):
                    self._mark_down()
                return None
            except (ValueError, struct.error):
                return None
            if msg is not None:
                self.received += 1
                buf = msg.get_msgbuf()
                if buf:
                    self._log(buf)
                    if isinstance(msg, mavlink.MAVLink_unknown):
                        _header_of_unknown(msg, bytes(buf))
            return msg

    def close(self) -> None:
        with self._lock:
            self._closed = True
            if self.conn is not None:
                with contextlib.suppress(Exception):
                    self.conn.close()
                self.conn = None
            if self._tlog is not None:
                self._tlog.close()
                self._tlog = None
