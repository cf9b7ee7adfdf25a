"""A lossy UDP link between a ground station and the mock autopilot, losing chosen packets."""
from __future__ import annotations

import socket
import threading


class AckDropper:
    """UDP relay GCS <-> mock autopilot that drops chosen packets towards the GCS: a lossy link
    whose losses are the ones that matter (the first acknowledgement of a command)."""

    def __init__(self, autopilot_port: int, drop, drop_up=lambda msgid, payload: False):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.up = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.up.bind(("127.0.0.1", 0))
        self.up.settimeout(0.05)
        self.ap = ("127.0.0.1", autopilot_port)
        self.drop = drop  # (msgid, srccomp, payload) -> bool, towards the GCS
        self.drop_up = drop_up  # (msgid, payload) -> bool, towards the vehicle
        self.dropped: list = []
        self.gcs = None
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=f, daemon=True) for f in (self._fwd, self._back)]
        for t in self._threads:
            t.start()

    @property
    def port(self) -> int:
        return self.sock.getsockname()[1]

    def _fwd(self):
        while not self._stop.is_set():
            try:
                data, self.gcs = self.sock.recvfrom(65535)
                if data[:1] == b"\xfd" and len(data) >= 10 and \
                        self.drop_up(int.from_bytes(data[7:10], "little"), data[10:10 + data[1]]):
                    self.dropped.append("up")
                    continue
                self.up.sendto(data, self.ap)
            except (socket.timeout, OSError):
                pass

    def _back(self):
        while not self._stop.is_set():
            try:
                data, _ = self.up.recvfrom(65535)
            except (socket.timeout, OSError):
                continue
            if data[:1] == b"\xfd" and len(data) >= 10:
                msgid = int.from_bytes(data[7:10], "little")
                if self.drop(msgid, data[6], data[10:10 + data[1]]):
                    self.dropped.append(msgid)
                    continue
            if self.gcs is not None:
                self.sock.sendto(data, self.gcs)

    def close(self):
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        self.sock.close()
        self.up.close()
