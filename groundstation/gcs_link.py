"""The ground station's MAVLink connection: finding the vehicle, the latest telemetry, commands
retried until acknowledged, and the app's parameters.

One thread (the caller's): every wait pumps the socket. The connection itself is the onboard
app's ``Link`` (same URLs, MAVLink 2, optional tlog of both directions, optional MAVLink 2
signing with a key from ``onboard.app.signing.load_key``), opened as sysid 255, component
MISSIONPLANNER (190).
"""
from __future__ import annotations

import contextlib
import io
import math
import select
import socket
import struct
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

from groundstation import protocol as P
from groundstation.errors import FAILED, TIMEOUT, GcsError
from groundstation.ports import in_use_hint, silent_link_hint
from onboard.app.mavlink_connection import Link, mavlink
from onboard.app.gcs.statustext import Reassembler

RETRY_S = 0.4  # resend an unacknowledged command after this long (loopback answers in ms)
GRACE_S = 0.3  # after a refusal, how long to wait for the STATUSTEXT that says why


@dataclass(frozen=True)
class Ack:
    result: str  # ACCEPTED, DENIED, ... or "OBSERVED" (ACK lost, the effect was seen)
    reason_code: int
    attempts: int
    elapsed_s: float
    texts: tuple[str, ...]  # STATUSTEXTs of the target component while the command ran

    @property
    def ok(self) -> bool:
        return self.result in ("ACCEPTED", "OBSERVED")


class Vehicle:
    """The latest of everything heard, by (message type, source component)."""

    def __init__(self):
        self.sysid: int | None = None
        self.autopilot_comp: int | None = None
        self.last: dict[tuple[str, int], object] = {}
        self.seen_at: dict[tuple[str, int], float] = {}
        self.targets: dict[int, P.TargetEstimate] = {}
        self.texts: deque = deque(maxlen=200)  # (local time, compid, severity, text)
        self.n_stat = 0
        # the autopilot's armed bit as its HEARTBEATs changed it: [local s, autopilot s (its next
        # time_boot_ms; None until one came), armed], the first heartbeat's state included (what
        # a refusal is explained with: an auto-disarm, on the autopilot's clock)
        self.armed_changes: deque = deque(maxlen=50)

    def note_heartbeat(self, now: float, msg) -> bool:
        """(before it is stored as the latest) An autopilot HEARTBEAT; True when its armed bit
        changed (its time on the autopilot's clock is then wanted: ``note_boot``)."""
        armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        if self.armed_changes and self.armed_changes[-1][2] == armed:
            return False
        self.armed_changes.append([now, None, armed])
        return True

    def note_boot(self, boot_s: float) -> None:
        """The autopilot's time_boot_ms in a message of its: the newest armed change's time if
        it has none (the first message after it)."""
        if self.armed_changes and self.armed_changes[-1][1] is None:
            self.armed_changes[-1][1] = boot_s

    def get(self, mtype: str, comp: int | None = None):
        return self.last.get((mtype, self.autopilot_comp if comp is None else comp))

    @property
    def armed(self) -> bool | None:
        hb = self.get("HEARTBEAT")
        return None if hb is None else bool(hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    @property
    def mode(self) -> int | None:
        hb = self.get("HEARTBEAT")
        return None if hb is None else hb.custom_mode

    @property
    def profile(self):
        """The autopilot's profile (onboard/app/autopilot/profiles.py), by its HEARTBEAT."""
        from onboard.app.autopilot.profiles import UNKNOWN, profile_for
        hb = self.get("HEARTBEAT")
        return UNKNOWN if hb is None else profile_for(hb.autopilot)

    @property
    def mode_name(self) -> str:
        """The autopilot's mode in its firmware's names (ArduCopter's, PX4's)."""
        hb = self.get("HEARTBEAT")
        return "unknown" if hb is None else self.profile.mode_name(hb.custom_mode)

    @property
    def landed_state(self) -> int | None:
        m = self.get("EXTENDED_SYS_STATE")
        return None if m is None else m.landed_state

    @property
    def app_state(self) -> str | None:
        st = self.app_status
        hb = self.get("HEARTBEAT", P.APP_COMPID)
        if hb is not None and self.seen_at.get(("HEARTBEAT", P.APP_COMPID), 0) >= \
                self.seen_at.get(("PMON_STAT", P.APP_COMPID), 0):
            return P.app_state_name(hb.custom_mode)
        return None if st is None else st.state

    @property
    def app_status(self) -> P.AppStatus | None:
        m = self.last.get(("PMON_STAT", P.APP_COMPID))
        return None if m is None else P.AppStatus.from_msg(m)


class GcsLink:
    def __init__(self, url: str, timeout: float = 5.0, sysid: int | None = None,
                 tlog_path: str | None = None, signing_key: bytes | None = None,
                 autopilot_unsigned: bool = False):
        """``signing_key``: 32 bytes (``onboard.app.signing.load_key``): every packet sent is
        signed, and received ones are accepted only with a good signature; ``autopilot_unsigned``:
        except the autopilot's own (component 1 of ``sysid``, default 1: PX4 cannot sign), while
        the app's, which the autopilot forwards, must still be signed."""
        self.url = url
        self.timeout = timeout
        self.want_sysid = sysid
        try:
            _probe_tcp(url, timeout)
            with contextlib.redirect_stdout(io.StringIO()):  # pymavlink prints its retries
                unsigned = ((sysid or 1, mavlink.MAV_COMP_ID_AUTOPILOT1),) if autopilot_unsigned else ()
                self.link = Link(url, tlog_path=tlog_path, source_system=P.GCS_SYSID,
                                 source_component=P.GCS_COMPID, signing_key=signing_key, unsigned_from=unsigned)
        except (OSError, ConnectionError) as exc:
            raise GcsError(f"cannot open {url}: {exc.strerror or exc}{in_use_hint(url)}{silent_link_hint(url)}",
                           TIMEOUT) from exc
        self.v = Vehicle()
        self.received = 0
        self._hb_local = -math.inf
        self._listeners: list[Callable] = []
        self.t0 = time.monotonic()
        self._seq: int | None = None  # the autopilot's last packet sequence number
        self.autopilot_packets = 0
        self.autopilot_lost = 0
        self._statustexts = Reassembler()  # MAVLink 2 STATUSTEXT chunks (onboard/app/gcs/statustext.py)

    def packet_loss_pct(self) -> float:
        """Packets lost from the autopilot component, by its sequence numbers. (Components it
        routes, like the onboard app, show gaps for every message not routed to us: not loss.)"""
        n = self.autopilot_packets + self.autopilot_lost
        return 100.0 * self.autopilot_lost / n if n else 0.0

    # ----------------------------------------------------------------- plumbing
    def close(self) -> None:
        self.link.close()

    def __enter__(self) -> "GcsLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def on_message(self, fn: Callable) -> None:
        self._listeners.append(fn)

    def send(self, msg) -> None:
        self.link.send(msg)

    def pump(self, wait_s: float = 0.0) -> None:
        """Read whatever has arrived (waiting up to wait_s for the first bytes)."""
        now = time.monotonic()
        if now - self._hb_local >= 1.0:  # a GCS heartbeat: the autopilot then routes to us
            self._hb_local = now
            self.send(self.link.mav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                     0, 0, mavlink.MAV_STATE_ACTIVE))
        fd = self.link.fileno()
        if wait_s > 0:
            if fd is not None:
                try:
                    select.select([fd], [], [], wait_s)
                except (OSError, ValueError):
                    time.sleep(wait_s)
            else:
                time.sleep(min(wait_s, 0.01))
        for _ in range(2000):
            msg = self.link.recv()
            if msg is None:
                break
            self._on(msg)

    def _on(self, msg) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            return
        self.received += 1
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        v = self.v
        if v.sysid is None and mtype == "HEARTBEAT" and self.want_sysid in (None, src) and (
                P.is_autopilot_heartbeat(msg) or comp == P.APP_COMPID):
            v.sysid = src
            if P.is_autopilot_heartbeat(msg):
                v.autopilot_comp = comp
        if v.sysid is None or src != v.sysid:
            return
        if v.autopilot_comp is None and P.is_autopilot_heartbeat(msg):
            v.autopilot_comp = comp
        if comp == v.autopilot_comp:
            seq = msg.get_seq()
            if self._seq is not None:
                self.autopilot_lost += (seq - self._seq - 1) % 256
            self._seq = seq
            self.autopilot_packets += 1
        now = time.monotonic()
        if mtype == "DEBUG_FLOAT_ARRAY":
            if msg.name == "PMON_TGT":
                est = P.TargetEstimate.from_msg(msg)
                v.targets[est.index] = est
            elif msg.name == "PMON_STAT":
                v.n_stat += 1
            mtype = msg.name
        elif mtype == "STATUSTEXT":  # chunks of a long text: listeners get it whole, once
            texts = self._statustexts.feed(msg)
            if not texts:
                return
            msg.text = texts[-1]
            v.texts.extend((now, comp, msg.severity, t) for t in texts)
        elif comp == v.autopilot_comp:
            boot_ms = getattr(msg, "time_boot_ms", None)  # the autopilot's clock (a SITL's runs faster)
            if isinstance(boot_ms, int):
                v.note_boot(boot_ms / 1000)
            if mtype == "HEARTBEAT" and v.note_heartbeat(now, msg):
                self.request(mavlink.MAVLINK_MSG_ID_SYSTEM_TIME)  # its time_boot_ms: when, on its clock
        v.last[(mtype, comp)] = msg
        v.seen_at[(mtype, comp)] = now
        for fn in self._listeners:
            fn(mtype, msg)

    def wait_for(self, pred: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while True:
            self.pump()
            if pred():
                return True
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            self.pump(min(left, 0.05))

    # ----------------------------------------------------------------- the vehicle
    def connect(self) -> "GcsLink":
        """Wait for the vehicle (the first autopilot heard, or --sysid); exit 3 if none."""
        asked = False

        def found() -> bool:
            nonlocal asked
            if self.v.sysid is not None and self.v.autopilot_comp is not None:
                return True
            if not asked and self.received:  # udpin: we can only talk once we heard something
                asked = True
                # ask for a heartbeat now rather than wait up to a second for the next one
                self._command_long(0, 0, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, mavlink.MAVLINK_MSG_ID_HEARTBEAT)
            return False
        self.pump()
        if not self.wait_for(found, self.timeout):
            if self.v.sysid is not None:  # only the app answered (a link to the companion alone)
                return self
            who = f"vehicle {self.want_sysid} not" if self.want_sysid else "no vehicle"
            what = 'no MAVLink at all' if not self.received else 'other traffic only'
            what += silent_link_hint(self.url)  # a one-client TCP port another process holds
            if self.link.signing and self.link.mav.signing.reject_count:
                what = (f"{self.link.mav.signing.reject_count} packets failed the signature check: "
                        "wrong --signing-key, or the vehicle does not sign (an autopilot that cannot, "
                        "PX4, needs --autopilot-unsigned)")
            raise GcsError(f"{who} heard on {self.url} within {self.timeout:g} s ({what})", TIMEOUT)
        return self

    def _signing_hint(self) -> str:
        """Why the vehicle may be ignoring us: it signs and we do not."""
        if not self.link.signing and self.link.mav.signing.sig_count:
            return "; the vehicle signs its MAVLink and drops unsigned commands: give --signing-key"
        return ""

    def request(self, *msg_ids: int) -> None:
        """MAV_CMD_REQUEST_MESSAGE to the autopilot (answered at once; ACKs are ignored)."""
        for mid in msg_ids:
            self._command_long(self.v.sysid, self.v.autopilot_comp or 1,
                               mavlink.MAV_CMD_REQUEST_MESSAGE, 0, mid)

    def stream(self, msg_id: int, hz: float) -> None:
        """MAV_CMD_SET_MESSAGE_INTERVAL on this link: what ArduPilot sends only when asked
        (EXTENDED_SYS_STATE is in no default stream; a SITL's links start with none)."""
        self._command_long(self.v.sysid, self.v.autopilot_comp or 1,
                           mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 1e6 / hz)

    def _command_long(self, sysid, comp, cmd, confirmation, *params) -> None:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self.send(self.link.mav.command_long_encode(sysid, comp, cmd, confirmation, *p))

    def autopilot_param(self, name: str, timeout: float) -> float | None:
        """One of the autopilot's parameters (PARAM_REQUEST_READ, resent every RETRY_S), None
        without an answer within ``timeout`` s."""
        v, got = self.v, []

        def listen(mtype, msg):
            if mtype == "PARAM_VALUE" and msg.get_srcComponent() == v.autopilot_comp and msg.param_id == name:
                got.append(v.profile.param_value(msg))
        self.on_message(listen)
        deadline = time.monotonic() + timeout
        try:
            while not got and time.monotonic() < deadline:
                self.send(self.link.mav.param_request_read_encode(v.sysid, v.autopilot_comp or 1, name.encode(), -1))
                self.wait_for(lambda: bool(got), min(RETRY_S, max(deadline - time.monotonic(), 0.0)))
        finally:
            self._listeners.remove(listen)
        return got[-1] if got else None

    def texts_since(self, t: float, comp: int) -> list[str]:
        return [text for (at, c, _sev, text) in self.v.texts if at >= t and c == comp]

    def command(self, comp: int | None, cmd: int, *params: float,
                done: Callable[[], bool] | None = None, name: str = "command") -> Ack:
        """COMMAND_LONG until its COMMAND_ACK, resent every RETRY_S with confirmation + 1.

        ``done``: the command's effect as seen in telemetry. If the ACK of an earlier copy was
        lost, a later copy may be refused (a second take-off while climbing): the effect being
        there then means success, and the command was executed once.
        """
        v = self.v
        comp = v.autopilot_comp if comp is None else comp
        if v.sysid is None or comp is None:
            raise GcsError(f"{name}: no autopilot heard on {self.url}", TIMEOUT)
        t0 = time.monotonic()
        deadline = t0 + self.timeout
        ack = None
        attempts = 0

        def match(confirm_after: float):
            m = v.last.get(("COMMAND_ACK", comp))
            if m is None or v.seen_at[("COMMAND_ACK", comp)] < confirm_after or m.command != cmd:
                return None
            if getattr(m, "target_system", 0) not in (0, P.GCS_SYSID) or \
                    getattr(m, "target_component", 0) not in (0, P.GCS_COMPID):
                return None
            return m

        while time.monotonic() < deadline:
            sent_at = time.monotonic()
            self._command_long(v.sysid, comp, cmd, min(attempts, 255), *params)
            attempts += 1
            resend = min(deadline, sent_at + RETRY_S)
            while time.monotonic() < resend:
                self.pump(0.02)
                ack = match(sent_at)
                if ack is not None and ack.result == mavlink.MAV_RESULT_IN_PROGRESS:
                    resend = deadline  # running: wait for the final answer, do not resend
                    ack = None
                    continue
                if ack is not None:
                    break
            if ack is not None:
                break
            if done is not None and done():
                return Ack("OBSERVED", 0, attempts, time.monotonic() - t0, tuple(self.texts_since(t0, comp)))
        if ack is None:
            raise GcsError(f"{name}: no answer from the {'onboard app' if comp == P.APP_COMPID else 'autopilot'}"
                           f" within {self.timeout:g} s ({attempts} attempts){self._signing_hint()}", TIMEOUT)
        result = P.RESULTS.get(ack.result, str(ack.result))
        reason = int(getattr(ack, "result_param2", 0) or 0)
        if ack.result != mavlink.MAV_RESULT_ACCEPTED:
            if attempts > 1 and done is not None and self.wait_for(done, 1.0):
                return Ack("OBSERVED", 0, attempts, time.monotonic() - t0, tuple(self.texts_since(t0, comp)))
            self.wait_for(lambda: bool(self.texts_since(t0, comp)), GRACE_S)
        return Ack(result, reason, attempts, time.monotonic() - t0, tuple(self.texts_since(t0, comp)))

    # ----------------------------------------------------------------- app parameters
    def params_list(self, timeout: float | None = None) -> dict[str, float]:
        """PARAM_REQUEST_LIST to the app; missing indices are asked for one by one; waits at most
        ``timeout`` s (default: the link's)."""
        timeout = self.timeout if timeout is None else timeout
        got: dict[int, tuple[str, float]] = {}
        count = [None]

        def listen(mtype, msg):
            if mtype == "PARAM_VALUE" and msg.get_srcComponent() == P.APP_COMPID:
                got[msg.param_index] = (msg.param_id, msg.param_value)
                count[0] = msg.param_count
        self.on_message(listen)
        try:
            deadline = time.monotonic() + timeout
            self.send(self.link.mav.param_request_list_encode(self.v.sysid, P.APP_COMPID))
            while time.monotonic() < deadline:
                if self.wait_for(lambda: count[0] is not None and len(got) >= count[0],
                                 min(RETRY_S, deadline - time.monotonic())):
                    return {name: value for _, (name, value) in sorted(got.items())}
                if count[0] is None:
                    self.send(self.link.mav.param_request_list_encode(self.v.sysid, P.APP_COMPID))
                else:
                    for i in range(count[0]):
                        if i not in got:
                            self.send(self.link.mav.param_request_read_encode(
                                self.v.sysid, P.APP_COMPID, b"", i))
        finally:
            self._listeners.remove(listen)
        raise GcsError(f"params: the onboard app did not answer within {timeout:g} s "
                       f"({len(got)} of {count[0] or '?'} parameters){self._signing_hint()}", TIMEOUT)

    def param_exchange(self, name: str, value: float | None = None) -> float:
        """Read (value None) or set one app parameter; returns the value the app holds.
        Unknown names and refused values come back as a STATUSTEXT: raised as GcsError."""
        got: list[float] = []

        def listen(mtype, msg):
            if mtype == "PARAM_VALUE" and msg.get_srcComponent() == P.APP_COMPID and msg.param_id == name:
                got.append(msg.param_value)
        self.on_message(listen)
        t0 = time.monotonic()
        deadline = t0 + self.timeout
        what = "get" if value is None else "set"
        try:
            while time.monotonic() < deadline:
                if value is None:
                    self.send(self.link.mav.param_request_read_encode(self.v.sysid, P.APP_COMPID,
                                                                      name.encode(), -1))
                else:
                    self.send(self.link.mav.param_set_encode(self.v.sysid, P.APP_COMPID, name.encode(),
                                                             value, mavlink.MAV_PARAM_TYPE_REAL32))
                end = min(deadline, time.monotonic() + RETRY_S)
                while time.monotonic() < end:
                    self.pump(0.02)
                    texts = [t for t in self.texts_since(t0, P.APP_COMPID) if name in t]
                    if any("unknown parameter" in t for t in texts):
                        raise GcsError(f"unknown parameter {name} (params list shows them)", FAILED)
                    if got:
                        if value is None or _same(got[-1], value):
                            return got[-1]
                        # refused (the value is unchanged) or rounded (integer parameter)
                        self.wait_for(lambda: any(name in t for t in self.texts_since(t0, P.APP_COMPID)),
                                      GRACE_S)
                        texts = [t for t in self.texts_since(t0, P.APP_COMPID) if name in t]
                        if texts:
                            raise GcsError(f"params set {name} refused: {texts[-1].removeprefix('PMON: ')}",
                                           FAILED)
                        return got[-1]
        finally:
            self._listeners.remove(listen)
        raise GcsError(f"params {what} {name}: no answer from the onboard app within {self.timeout:g} s"
                       f"{self._signing_hint()}", TIMEOUT)


def _probe_tcp(url: str, timeout: float) -> None:
    """A refused TCP port fails at once (pymavlink would retry, sleeping, printing)."""
    kind, _, rest = url.partition(":")
    host, _, port = rest.rpartition(":")
    if kind == "tcp" and port.isdigit():
        socket.create_connection((host, int(port)), timeout=timeout).close()


def _same(a: float, b: float) -> bool:
    """Equal as float32 (the wire type)."""
    return struct.pack("<f", a) == struct.pack("<f", b)
