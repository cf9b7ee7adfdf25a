"""The mock autopilot's routing, as ArduPilot's MAVLink_routing::check_and_forward: each link
read and parsed, routes learned per (sysid, compid), messages forwarded to the links of their
target and handed locally to the handler of its type (the parts' ``handlers()``); and the
tests' fault injection on links (cut, drop). ``MockAutopilot``'s router: it dispatches to the
parts (sim/mock/context.py)."""
from __future__ import annotations

import logging
from typing import Callable

from onboard.app.mavlink2 import mavlink
from sim.mock.context import Handler, MockContext, Part
from sim.mock.links import _Link

log = logging.getLogger("sim.mock.autopilot")


class Router:
    """The routes learned, as (sysid, compid, link), and the handler of every message type
    handled locally (``handlers``: the parts' tables, and a HEARTBEAT that needs nothing)."""

    def __init__(self, ctx: MockContext, parts: tuple[Part, ...]):
        self.ctx = ctx
        self.routes: set[tuple[int, int, _Link]] = set()
        self.handlers: dict[str, Handler] = {"HEARTBEAT": self._on_heartbeat}
        for part in parts:
            self.handlers.update(part.handlers())

    def watch(self, mtype: str, see: Callable[[object], None]) -> None:
        """``see(msg)`` before the handler of each ``mtype`` message handled locally."""
        handle = self.handlers[mtype]

        def watched(link: _Link, msg) -> None:
            see(msg)
            handle(link, msg)
        self.handlers[mtype] = watched

    def forget(self, link: _Link) -> None:
        """A closed link's routes."""
        self.routes = {r for r in self.routes if r[2] is not link}

    # ----- fault injection (tests)
    def links_of(self, compid: int) -> list[_Link]:
        return [link for s, c, link in self.routes if c == compid]

    def cut(self, compid: int, seconds: float) -> int:
        links = self.links_of(compid)
        for link in links:
            link.muted_until = self.ctx.copter.t + seconds
            link.muted = True
        return len(links)

    def drop(self, compid: int) -> int:
        links = self.links_of(compid)
        for link in links:
            link.close()
        return len(links)

    def read(self, link: _Link) -> None:
        data = link.receive()
        if not data or link.muted:
            return
        rejected = link.parser.signing.reject_count
        try:
            msgs = link.parser.parse_buffer(data) or []
        except Exception:  # pymavlink raises on some malformed frames even when robust
            self.ctx.count("bad_data")
            return
        finally:
            if link.parser.signing.reject_count != rejected:
                self.ctx.count("signing_rejected", link.parser.signing.reject_count - rejected)
        for msg in msgs:
            try:
                self._on_message(link, msg)
            except Exception:
                self.ctx.count("handler_errors")
                log.exception("error handling %s", getattr(msg, "get_type", lambda: "?")())

    # ----- routing (ArduPilot's MAVLink_routing::check_and_forward)
    def _on_message(self, link: _Link, msg) -> None:
        ctx = self.ctx
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            ctx.count("bad_data")
            return
        if isinstance(msg, mavlink.MAVLink_unknown) or mtype.startswith("UNKNOWN"):
            ctx.count("unknown_msgid")  # CRC cannot be checked: ArduPilot drops these
            return
        ctx.count("rx")
        link.active = True
        sysid, compid = msg.get_srcSystem(), msg.get_srcComponent()
        if (sysid, compid) == (ctx.sysid, ctx.compid):
            ctx.count("loopback")  # our own packets echoed back: ignore
            return
        if sysid != 0:
            self.routes.add((sysid, compid, link))
        if mtype in ("RADIO", "RADIO_STATUS"):
            self._handle(link, msg)
            return
        raw = msg.get_msgbuf()
        if mtype == "HEARTBEAT":
            for other in ctx.links:
                if (other is not link and other.active
                        and (sysid, compid, other) not in self.routes):
                    other.write(raw)
                    ctx.count("forwarded")
            self._handle(link, msg)
            return
        tsys = getattr(msg, "target_system", -1)
        tcomp = getattr(msg, "target_component", -1)
        bcast_sys = tsys in (0, -1)
        bcast_comp = tcomp in (0, -1)
        match_sys = bcast_sys or tsys == ctx.sysid
        local = match_sys and (bcast_comp or tcomp == ctx.compid)
        if local and not bcast_sys and not bcast_comp:
            self._handle(link, msg)
            return
        sent_to: set[int] = set()
        for rsys, rcomp, other in list(self.routes):
            if other is link or id(other) in sent_to:
                continue
            if bcast_sys or (rsys == tsys and (bcast_comp or rcomp == tcomp or not match_sys)):
                other.write(raw)
                sent_to.add(id(other))
                ctx.count("forwarded")
        if not sent_to and match_sys:
            local = True
        if local:
            self._handle(link, msg)

    # ----- local handling
    def _handle(self, link: _Link, msg) -> None:
        handler = self.handlers.get(msg.get_type())
        if handler is None:
            self.ctx.count("ignored")
            return
        handler(link, msg)

    def _on_heartbeat(self, link: _Link, msg) -> None:
        pass  # routes are learned in _on_message; GCS failsafe is not modelled
