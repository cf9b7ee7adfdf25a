"""The mock autopilot's routing, as ArduPilot's MAVLink_routing::check_and_forward: each link
read and parsed, routes learned per (sysid, compid), messages forwarded to the links of their
target and handed to the local handler (``_on_<message>``); and the tests' fault injection on
links (cut, drop). A mixin of ``MockAutopilot``."""
from __future__ import annotations

import logging

from onboard.app.mavlink2 import mavlink
from sim.mock.links import _Link

log = logging.getLogger("sim.mock.autopilot")


class Routing:
    """Methods of ``MockAutopilot`` (its state is set up in ``MockAutopilot.__init__``)."""
    # ----- fault injection (tests)
    def _links_of(self, compid: int) -> list[_Link]:
        return [link for s, c, link in self._routes if c == compid]

    def cut_link(self, compid: int, seconds: float) -> int:
        """The link(s) a component is reached on go dead both ways for ``seconds`` of
        autopilot time (a radio out of range): nothing is read or written, the TCP connection
        stays up. Returns the number of links cut."""
        with self._lock:
            links = self._links_of(compid)
            for link in links:
                link.muted_until = self.copter.t + seconds
                link.muted = True
            return len(links)

    def drop_link(self, compid: int) -> int:
        """Close the link(s) of a component (a TCP client must reconnect)."""
        with self._lock:
            links = self._links_of(compid)
            for link in links:
                link.close()
            return len(links)

    def _read_link(self, link: _Link) -> None:
        data = link.receive()
        if not data or link.muted:
            return
        rejected = link.parser.signing.reject_count
        try:
            msgs = link.parser.parse_buffer(data) or []
        except Exception:  # pymavlink raises on some malformed frames even when robust
            self._count("bad_data")
            return
        finally:
            if link.parser.signing.reject_count != rejected:
                self._count("signing_rejected", link.parser.signing.reject_count - rejected)
        for msg in msgs:
            try:
                self._on_message(link, msg)
            except Exception:
                self._count("handler_errors")
                log.exception("error handling %s", getattr(msg, "get_type", lambda: "?")())

    # ----- routing (ArduPilot's MAVLink_routing::check_and_forward)
    def _on_message(self, link: _Link, msg) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self._count("bad_data")
            return
        if isinstance(msg, mavlink.MAVLink_unknown) or mtype.startswith("UNKNOWN"):
            self._count("unknown_msgid")  # CRC cannot be checked: ArduPilot drops these
            return
        self._count("rx")
        link.active = True
        sysid, compid = msg.get_srcSystem(), msg.get_srcComponent()
        if (sysid, compid) == (self.sysid, self.compid):
            self._count("loopback")  # our own packets echoed back: ignore
            return
        if sysid != 0:
            self._routes.add((sysid, compid, link))
        if mtype in ("RADIO", "RADIO_STATUS"):
            self._handle(link, msg)
            return
        raw = msg.get_msgbuf()
        if mtype == "HEARTBEAT":
            for other in self._links:
                if (other is not link and other.active
                        and (sysid, compid, other) not in self._routes):
                    other.write(raw)
                    self._count("forwarded")
            self._handle(link, msg)
            return
        tsys = getattr(msg, "target_system", -1)
        tcomp = getattr(msg, "target_component", -1)
        bcast_sys = tsys in (0, -1)
        bcast_comp = tcomp in (0, -1)
        match_sys = bcast_sys or tsys == self.sysid
        local = match_sys and (bcast_comp or tcomp == self.compid)
        if local and not bcast_sys and not bcast_comp:
            self._handle(link, msg)
            return
        sent_to: set[int] = set()
        for rsys, rcomp, other in list(self._routes):
            if other is link or id(other) in sent_to:
                continue
            if bcast_sys or (rsys == tsys and (bcast_comp or rcomp == tcomp or not match_sys)):
                other.write(raw)
                sent_to.add(id(other))
                self._count("forwarded")
        if not sent_to and match_sys:
            local = True
        if local:
            self._handle(link, msg)

    # ----- local handling
    def _handle(self, link: _Link, msg) -> None:
        handler = getattr(self, "_on_" + msg.get_type().lower(), None)
        if handler is None:
            self._count("ignored")
            return
        handler(link, msg)
