"""The app's MAVLink 2 connection: pymavlink, one send lock, a tlog of both directions.

URLs as pymavlink takes them: ``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``tcp:HOST:PORT``,
``tcpin:HOST:PORT``, or a serial device ``/dev/ttyUSB0`` with ``baud``.
"""
from __future__ import annotations

import os
import struct
import threading
import time

# pymavlink picks MAVLink 1 or 2 from this variable when a dialect is loaded.
os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

COMP_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191


class Link:
    """A pymavlink connection the app's threads share.

    ``recv()`` is for one reader thread; ``send()`` is safe from any thread. Every message
    received or sent is appended to the tlog (8-byte big-endian UNIX microseconds + the raw
    packet: the format mavlogdump.py and MAVProxy read).
    """

    def __init__(self, url: str, baud: int = 57600, tlog_path: str | None = None,
                 source_system: int = 1, source_component: int = COMP_ID,
                 signing_key: bytes | None = None, link_id: int = 1):
        self.url = url
        self.conn = mavutil.mavlink_connection(
            url, baud=baud, source_system=source_system, source_component=source_component,
            dialect="ardupilotmega", autoreconnect=True)
        if getattr(self.conn, "WIRE_PROTOCOL_VERSION", "2.0") != "2.0":
            raise RuntimeError("pymavlink loaded MAVLink 1; set MAVLINK20=1 before importing it")
        self.conn.mav.robust_parsing = True
        self.signing = signing_key is not None
        if signing_key is not None:  # unsigned / wrongly signed packets become BAD_DATA
            from onboard.app.signing import apply
            apply(self.conn, signing_key, link_id)
        self._lock = threading.Lock()
        self._tlog = open(tlog_path, "wb") if tlog_path else None
        self.sent = 0
        self.received = 0
        self.send_errors = 0

    @property
    def mav(self) -> mavlink.MAVLink:
        """Message constructors (``link.mav.heartbeat_encode(...)``); send with ``send``."""
        return self.conn.mav

    def set_source_system(self, sysid: int) -> None:
        with self._lock:
            self.conn.mav.srcSystem = sysid

    def _log(self, buf: bytes) -> None:
        if self._tlog is not None:
            self._tlog.write(struct.pack(">Q", int(time.time() * 1e6)) + bytes(buf))

    def send(self, msg) -> bool:
        with self._lock:
            try:
                self.conn.mav.send(msg)
            except (OSError, ValueError, struct.error):
                self.send_errors += 1
                return False
            self.sent += 1
            self._log(msg.get_msgbuf())
            return True

    def fileno(self) -> int | None:
        fd = getattr(self.conn, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def recv(self):
        """The next parsed message or None (non-blocking). BAD_DATA is returned too.

        On UDP every datagram carries whole frames, so a partial frame left in the parser when a
        datagram is used up can never complete: it is dropped before the next datagram, or a
        garbage datagram (a stray 0xFD and a large length) would swallow the good ones after it.
        """
        try:
            if isinstance(self.conn, mavutil.mavudp):
                mav = self.conn.mav
                msg = mav.parse_char(b"") if mav.buf_len() else None  # frames already buffered
                if msg is not None:
                    self.conn.post_message(msg)
                else:
                    mav.buf, mav.buf_index = bytearray(), 0
                    mav.expected_length = mavlink.HEADER_LEN_V1 + 2
                    msg = self.conn.recv_msg()
            else:
                msg = self.conn.recv_msg()
        except (OSError, ValueError, struct.error):
            return None
        if msg is not None:
            self.received += 1
            with self._lock:
                buf = msg.get_msgbuf()
                if buf:
                    self._log(buf)
        return msg

    def close(self) -> None:
        with self._lock:
            try:
                self.conn.close()
            except OSError:
                pass
            if self._tlog is not None:
                self._tlog.close()
                self._tlog = None
