"""``pmon gcs hub``: one telemetry link, shared. The hub owns the vehicle link (the same
``--connect``, ``--sysid``, ``--signing-key`` as every ``pmon gcs`` command) and serves:

* MAVLink ground stations on UDP, as MAVProxy's ``--out`` does: every packet the vehicle sends
  goes to every client, every packet a client sends goes to the vehicle, byte for byte (its
  system id, sequence and signature kept). ``--serve udp:HOST:PORT`` listens (clients send
  first: ``pmon gcs --connect udpout:HOST:PORT``, MAVProxy ``--master=udpout:...``, Mission
  Planner's UDPCl); ``--out udp:HOST:PORT`` sends to a client that listens (QGroundControl and
  Mission Planner listen on 14550).
* The targets as traffic (ADSB_VEHICLE, groundstation/adsb.py) to those clients only, one per
  target per tick; never to the vehicle (an ADSB_VEHICLE in our address block coming back
  from a client is dropped, not forwarded).
* The targets and the UAV as CoT to TAK (``--tak URL``, groundstation/tak.py).
* The live view (``--view PORT``, groundstation/view.py) from the same link.

Every PMON_TGT is checked before it becomes an output (groundstation/estimates.py); refusals
are counted by reason and printed when the hub stops. One thread does all the link I/O; TAK
has its own (pytak, asyncio), fed through a bounded queue.
"""
from __future__ import annotations

import datetime as dt
import json
import math
import select
import socket
import sys
import time
from collections import Counter

from groundstation import adsb as A
from groundstation.gcs_commands import Outcome
from groundstation.estimates import OutputEstimate, check
from groundstation.hub_options import HubConfig, config_from_args
from groundstation.errors import GcsError
from groundstation.gcs_link import GcsLink
from groundstation.ports import bound_by
from onboard.app.mavlink_connection import mavlink

PEER_TIMEOUT_S = 30.0  # a --serve client not heard for this long gets nothing more
MIN_INTERVAL_S = 0.1  # per target: at most 10 outputs a second whatever arrives (a flood)
UAV_PERIOD_S = 1.0  # the UAV's CoT track
CHECK_S = 0.25  # how often lost targets and the view's quiet time are looked at
HUB_LINK_ID = 156  # the signing link id of the hub's own messages (its ADSB_VEHICLE stream)
UNSIGNED_WARNING = ("hub: UNSIGNED: every client of the hub commands the vehicle (arm, modes, the app's "
                    "commands); give --signing-key to allow only clients with the key (docs/SAFETY.md)")


class Endpoint:
    """One UDP socket of the hub's clients: ``serve`` learns its peers from what they send;
    ``out`` sends to one fixed address (and hears its answers on the same socket)."""

    def __init__(self, host: str, port: int, serve: bool, signing_key: bytes | None = None):
        self.serve = serve
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)
        try:
            if serve:
                self.sock.bind((host, port))
            else:
                self.sock.connect((host, port))
        except OSError as exc:
            self.sock.close()
            who = bound_by("udp", port) if serve else None
            raise GcsError(f"hub: cannot {'serve on' if serve else 'send to'} udp {host}:{port}: "
                           f"{exc.strerror or exc}" + (f" (held by {who})" if who else ""), 1) from exc
        self.name = f"{'serve' if serve else 'out'} udp:{host}:{port}"
        self.address = self.sock.getsockname() if serve else (host, port)
        self.peers: dict[tuple, float] = {}
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.rx = self.tx = self.bad = 0
        # with a key: the peers (an --out client: True) that sent a packet whose signature checks
        # (not a replay); the hub's own messages go to them only. Clients' packets are still
        # passed on as they came, signed or not: the vehicle decides, as on a direct link.
        self.authorised: set = set()
        if signing_key is not None:
            from onboard.app.signing import configure
            configure(self.parser, signing_key, 0, sign_outgoing=False)
            self.parser.signing.allow_unsigned_callback = lambda mav, msg_id: True

    def send(self, buf: bytes, now: float, authorised_only: bool = False) -> None:
        try:
            if self.serve:
                for addr, seen in list(self.peers.items()):
                    if now - seen > PEER_TIMEOUT_S:
                        del self.peers[addr]
                        self.authorised.discard(addr)
                        continue
                    if not authorised_only or addr in self.authorised:
                        self.sock.sendto(buf, addr)
                        self.tx += 1
            elif not authorised_only or True in self.authorised:
                self.sock.send(buf)
                self.tx += 1
        except OSError:  # a client that went away (ECONNREFUSED on a connected socket): not ours to fail
            pass

    def receive(self, now: float, limit: int = 1000) -> list:
        """Whole MAVLink frames from the clients (BAD_DATA counted and dropped)."""
        out = []
        for _ in range(limit):
            try:
                data, addr = self.sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break
            if self.serve:
                self.peers[addr] = now
            self.parser.buf, self.parser.buf_index = bytearray(), 0  # a datagram holds whole frames
            try:
                msgs = self.parser.parse_buffer(data) or []
            except Exception:
                self.bad += 1
                continue
            for m in msgs:
                if m.get_type() == "BAD_DATA":
                    self.bad += 1
                else:
                    self.rx += 1
                    out.append(m)
                    if m.get_signed():
                        self.authorised.add(addr if self.serve else True)
        return out

    def close(self) -> None:
        self.sock.close()


class HubLink(GcsLink):
    """The hub's vehicle link: every message, before GcsLink keeps what concerns the vehicle,
    goes to ``on_raw`` (forwarded to the clients as it came)."""

    on_raw = None

    def _on(self, msg) -> None:
        if self.on_raw is not None and msg.get_type() != "BAD_DATA":
            self.on_raw(msg)
        super()._on(msg)


def write_raw(link, buf: bytes) -> bool:
    """A client's packet to the vehicle as it came (onboard.app.mavlink_connection.Link encodes only its own
    messages: this takes the same lock its send and receive take)."""
    with link._lock:
        conn = link.conn
        if conn is None:
            return False
        try:
            conn.write(bytes(buf))
            return True
        except (OSError, ValueError):
            return False


class TargetOutputs:
    """PMON_TGT -> checked estimate -> ADSB_VEHICLE and CoT, one per target per tick; lost
    targets expire. ``emit_adsb(frames)`` and ``emit_cot(bytes)`` are the hub's senders."""

    def __init__(self, frame, cfg: HubConfig, emit_adsb, emit_cot, clock=time.monotonic,
                 utcnow=lambda: dt.datetime.now(dt.timezone.utc), signing_key: bytes | None = None):
        self.frame, self.cfg = frame, cfg
        self.signing_key = signing_key
        self.emit_adsb, self.emit_cot = emit_adsb, emit_cot
        self.clock, self.utcnow = clock, utcnow
        self.refused: Counter = Counter()
        self.adsb_sent = 0
        self.cot_sent = 0
        self.rate_limited = 0
        self.lost = 0
        self._last: dict[int, tuple[OutputEstimate, float]] = {}  # index -> (estimate, local s)
        self._mav: dict[int, mavlink.MAVLink] = {}

    def on_estimate(self, msg, sysid: int) -> OutputEstimate | None:
        est, why = check(msg, self.frame)
        if est is None:
            self.refused[why] += 1
            return None
        now = self.clock()
        prev = self._last.get(est.index)
        if prev is not None and prev[0].tick_time_s == est.tick_time_s:
            return None  # the same tick again (a repeat): drawn already
        if prev is not None and now - prev[1] < MIN_INTERVAL_S:
            self.rate_limited += 1
            return None
        if est.age_s >= self.cfg.lost_after_s:
            if prev is not None:
                self._expire(est.index, sysid, est)
            else:
                self.refused["lost (no DF scan for lost_after_s)"] += 1
            return None
        self._last[est.index] = (est, now)
        if self.cfg.adsb:
            mav = self._mav.get(sysid) or self._mav.setdefault(sysid, self._encoder(sysid))
            msgs = A.messages(mav, est, self.cfg.circles)
            self.emit_adsb(A.pack(mav, msgs))
            self.adsb_sent += len(msgs)
        if self.emit_cot is not None:
            from groundstation.tak import target_event, to_bytes
            self.emit_cot(to_bytes(target_event(est, sysid, self.utcnow(), self.cfg.lost_after_s,
                                                self.cfg.stale_s)))
            self.cot_sent += 1
        return est

    def _encoder(self, sysid: int):
        mav = A.encoder(sysid)
        if self.signing_key is not None:  # a signing ground station drops what is not signed
            from onboard.app.signing import configure
            configure(mav, self.signing_key, HUB_LINK_ID)
        return mav

    def check_lost(self, sysid: int | None) -> list[int]:
        """Targets whose estimates stopped (app or link gone) or whose data aged past
        ``lost_after_s``: no more ADSB (the tools drop them by their own timeout), a last CoT
        that is stale at once."""
        now = self.clock()
        gone = [j for j, (est, at) in self._last.items()
                if est.age_s + (now - at) >= self.cfg.lost_after_s]
        for j in gone:
            self._expire(j, sysid, self._last[j][0])
        return gone

    def _expire(self, j: int, sysid: int | None, est: OutputEstimate) -> None:
        self._last.pop(j, None)
        self.lost += 1
        if self.emit_cot is not None and sysid is not None:
            from groundstation.tak import lost_event, to_bytes
            self.emit_cot(to_bytes(lost_event(est, sysid, self.utcnow())))
            self.cot_sent += 1

    @property
    def active(self) -> list[int]:
        return sorted(self._last)


class Hub:
    def __init__(self, gl: HubLink, sc, cfg: HubConfig, signing_key: bytes | None = None):
        """``signing_key``: the link's (``--signing-key``): the hub's own messages are signed with
        it and sent only to clients that have sent a packet signed with it."""
        from onboard.app.autopilot.pose import Frame
        self.gl, self.sc, self.cfg = gl, sc, cfg
        self.signing_key = signing_key
        o = sc.origin
        self.frame = Frame(o.lat_deg, o.lon_deg, o.alt_m)
        self.endpoints: list[Endpoint] = []
        self.tak = None
        self.view = None
        self.view_state = None
        self.forwarded_up = self.forwarded_down = 0
        self.echoes_dropped = 0
        self._uav_at = -math.inf
        try:
            for host, port in cfg.serve:
                self.endpoints.append(Endpoint(host, port, True, signing_key))
            for host, port in cfg.out:
                self.endpoints.append(Endpoint(host, port, False, signing_key))
            if cfg.tak_url:
                try:
                    from groundstation.tak import TakSender, config
                except ImportError as exc:
                    raise GcsError(f"hub: --tak needs pytak and takproto ({exc.name} is missing): "
                                   "pip install 'passive-monitor[gcs]'", 2) from exc
                try:
                    self.tak = TakSender(config(cfg.tak_url, cfg.tak_proto, cfg.tak_tls))
                except (SyntaxError, ValueError) as exc:
                    raise GcsError(f"hub: --tak {cfg.tak_url}: {exc}", 2) from exc
            if cfg.view_port is not None:
                from groundstation.view import ViewServer, ViewState
                try:
                    self.view = ViewServer(sc, cfg.view_port).start()
                except OSError as exc:
                    who = bound_by("tcp", cfg.view_port)
                    raise GcsError(f"hub: view: cannot serve on 127.0.0.1:{cfg.view_port}: "
                                   f"{exc.strerror or exc}" + (f" (held by {who})" if who else ""), 1) from exc
                self.view_state = ViewState(gl, sc, self.view.bus.publish)
        except BaseException:
            self.close()
            raise
        self.targets = TargetOutputs(self.frame, cfg, self._to_clients,
                                     self.tak.put if self.tak is not None else None, signing_key=signing_key)
        gl.on_raw = self._from_vehicle
        gl.on_message(self._on_message)

    # ----- routing
    def _from_vehicle(self, msg) -> None:
        if msg.get_type() == "DEBUG_FLOAT_ARRAY" and msg.name == "PMON_TGT" and \
                msg.get_srcSystem() != self.gl.v.sysid:
            self.targets.refused["from another system"] += 1  # forwarded as it is, never drawn
        buf = msg.get_msgbuf()
        now = time.monotonic()
        for ep in self.endpoints:
            ep.send(buf, now)
        self.forwarded_down += 1

    def _to_clients(self, frames: list[bytes]) -> None:
        """The hub's own messages: with a key, signed and to authorised clients only."""
        now = time.monotonic()
        for buf in frames:
            for ep in self.endpoints:
                ep.send(buf, now, authorised_only=self.signing_key is not None)

    def _from_clients(self, now: float) -> None:
        for ep in self.endpoints:
            for m in ep.receive(now):
                if m.get_type() == "ADSB_VEHICLE" and A.is_ours(m.ICAO_address):
                    self.echoes_dropped += 1  # a target reflected by a client never reaches the autopilot
                    continue
                if write_raw(self.gl.link, m.get_msgbuf()):
                    self.forwarded_up += 1

    def _on_message(self, mtype: str, msg) -> None:
        if mtype == "PMON_TGT" and self.gl.v.sysid is not None:
            self.targets.on_estimate(msg, self.gl.v.sysid)
        elif mtype == "GLOBAL_POSITION_INT" and self.tak is not None and \
                msg.get_srcComponent() == self.gl.v.autopilot_comp:
            now = time.monotonic()
            if now - self._uav_at >= UAV_PERIOD_S:
                from groundstation.tak import to_bytes, uav_event
                gps = self.gl.v.get("GPS_RAW_INT")
                eph = gps.eph / 100.0 if gps is not None and gps.eph not in (0, 65535) else None
                ev = uav_event(msg, self.gl.v.sysid, dt.datetime.now(dt.timezone.utc), 3 * UAV_PERIOD_S, eph)
                if ev is not None:
                    self._uav_at = now
                    self.tak.put(to_bytes(ev))

    # ----- the loop
    def run(self, duration: float | None = None, stop=None, on_ready=None) -> None:
        if on_ready is not None:
            on_ready(self)
        if self.view is not None:
            self.view.bus.publish(self.view_state.snapshot())
        t0 = last_check = time.monotonic()
        socks = [ep.sock for ep in self.endpoints]
        while (duration is None or time.monotonic() - t0 < duration) and not (stop and stop.is_set()):
            fds = list(socks)
            fd = self.gl.link.fileno()
            if fd is not None:
                fds.append(fd)
            try:
                select.select(fds, [], [], 0.05)
            except (OSError, ValueError):
                time.sleep(0.05)
            now = time.monotonic()
            self.gl.pump()
            self._from_clients(now)
            if now - last_check >= CHECK_S:
                last_check = now
                self.targets.check_lost(self.gl.v.sysid)
                if self.view is not None:
                    from groundstation.view import QUIET_S
                    if now - max(self.view_state.stat_at, self.view.bus.published_at) >= QUIET_S:
                        self.view.bus.publish(self.view_state.snapshot())

    def summary(self) -> dict:
        t = self.targets
        return {"link": self.gl.url, "vehicle": self.gl.v.sysid,
                "clients": {ep.name: {"peers": len(ep.peers) if ep.serve else 1, "rx": ep.rx, "tx": ep.tx,
                                      "bad": ep.bad, "signed": len(ep.authorised)} for ep in self.endpoints},
                "signed": self.signing_key is not None,
                "forwarded_to_vehicle": self.forwarded_up, "forwarded_to_clients": self.forwarded_down,
                "adsb_sent": t.adsb_sent, "cot_sent": t.cot_sent, "targets_lost": t.lost,
                "estimates_refused": dict(t.refused), "estimates_rate_limited": t.rate_limited,
                "echoed_targets_dropped": self.echoes_dropped,
                "tak": None if self.tak is None else {"url": self.tak.url, "sent": self.tak.sent,
                                                      "dropped": self.tak.dropped, "connects": self.tak.connects,
                                                      "errors": self.tak.errors, "last_error": self.tak.last_error},
                "view": None if self.view is None else self.view.url}

    def close(self) -> None:
        for ep in self.endpoints:
            ep.close()
        if self.tak is not None:
            self.tak.close()
        if self.view is not None:
            self.view.close()


def serve(gl: HubLink, sc, cfg: HubConfig, duration: float | None, as_json: bool, console,
          signing_key: bytes | None = None) -> Outcome:
    hub = Hub(gl, sc, cfg, signing_key)
    try:
        lines = [f"hub: vehicle {gl.v.sysid} on {gl.url}"]
        if signing_key is None and hub.endpoints:
            lines.append(UNSIGNED_WARNING)
        lines += [f"  MAVLink clients: {ep.name}" + (" (connect with udpout:%s:%d)" % ep.address if ep.serve else "")
                  for ep in hub.endpoints]
        if cfg.adsb and hub.endpoints:
            lines.append("  targets as ADSB_VEHICLE" + (" with 1-sigma circles" if cfg.circles else "")
                         + f", lost after {cfg.lost_after_s:g} s without a DF scan")
        if hub.tak is not None:
            lines.append(f"  CoT to {cfg.tak_url}" + (" (TAK protobuf)" if cfg.tak_proto else ""))
        if hub.view is not None:
            lines.append(f"  view: {hub.view.url}")
        if as_json:
            console.file.write(json.dumps({"hub": hub.summary()}) + "\n")
            console.file.flush()
            if signing_key is None and hub.endpoints:
                print(UNSIGNED_WARNING, file=sys.stderr, flush=True)
        else:
            console.print("\n".join(lines) + "\n  (Ctrl-C stops)", soft_wrap=True, highlight=False)
        try:
            hub.run(duration)
        except KeyboardInterrupt:
            pass
        s = hub.summary()
    finally:
        hub.close()
    refused = sum(s["estimates_refused"].values())
    text = (f"hub: stopped; {s['forwarded_to_clients']} messages to clients, {s['forwarded_to_vehicle']} to the "
            f"vehicle, {s['adsb_sent']} ADSB_VEHICLE, {s['cot_sent']} CoT, {refused} estimates refused"
            + (f" ({', '.join(f'{k}: {v}' for k, v in s['estimates_refused'].items())})" if refused else ""))
    return Outcome(text, s)


def run_cli(args, key, sc, console) -> Outcome:
    """``pmon gcs hub``: options checked, the link opened and the vehicle found, then served."""
    from groundstation.errors import UsageError
    try:
        cfg = config_from_args(args)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    with HubLink(args.connect, args.timeout, args.sysid, signing_key=key,
                 autopilot_unsigned=getattr(args, "autopilot_unsigned", False)) as gl:
        gl.connect()
        return serve(gl, sc, cfg, args.duration, args.json, console, signing_key=key)
