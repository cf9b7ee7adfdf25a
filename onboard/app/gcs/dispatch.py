"""MAVLink in: each message dispatched by ``msg.get_type()`` to the parts that handle its type
(their ``handlers()``, onboard/app/part.py: MAVProxy's module contract), and who may be obeyed.

- HEARTBEAT from anyone goes to its handlers (the autopilot side picks its autopilot and
  ignores the rest).
- Messages from the autopilot (its system and component) feed the autopilot side; every one
  stamped with ``time_boot_ms`` is a clock sample first.
- Messages for the app (``FOR_APP``: target system 0 or the vehicle's, component 0 or 191):
  parameter reads are answered to anyone; commands and parameter writes (``WRITES``) must be
  addressed to 191 and come from a configured ground station (``gcs_sysids``), else they are
  ignored, counted and said once per stranger (no ACK: nothing to tell a stranger).
- Anything else is not the app's business and is dropped unread.

Handlers run contained by the io loop, per message (an exception costs its own message only).
io thread, under the app lock.
"""
from __future__ import annotations

from typing import Callable

from onboard.app.context import AppContext
from onboard.app.contract import Reason
from onboard.app.mavlink_connection import COMP_ID, Link, mavlink
from onboard.app.part import Handler, Part

ANY_SOURCE = frozenset({"HEARTBEAT"})  # handled from anyone
FOR_APP = frozenset({"COMMAND_LONG", "COMMAND_INT", "PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET"})
WRITES = frozenset({"COMMAND_LONG", "COMMAND_INT", "PARAM_SET"})  # addressed to 191, from a GCS only
# every other type is handled from the autopilot only


def ack(link: Link, msg, result: int, reason: Reason = Reason.NONE) -> None:
    """COMMAND_ACK for a COMMAND_LONG/INT; ``reason`` (result_param2) says why it was refused."""
    link.send(link.mav.command_ack_encode(
        msg.command, result, 0, int(reason), msg.get_srcSystem(), msg.get_srcComponent()))


class Commands(Part):
    """The app's commands: PMON_STAT at once when asked for with MAV_CMD_REQUEST_MESSAGE
    (``publish_stat``), every other COMMAND_LONG to ``on_command`` (the state machine:
    MAV_CMD_PMON), COMMAND_INT refused."""

    def __init__(self, link: Link, publish_stat: Callable[[], None], on_command: Handler):
        self.link = link
        self.publish_stat = publish_stat
        self.on_command = on_command

    def handlers(self) -> dict[str, Handler]:
        return {"COMMAND_LONG": self.on_command_long, "COMMAND_INT": self.on_command_int}

    def on_command_long(self, msg) -> None:
        if msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE and int(msg.param1) == \
                mavlink.MAVLINK_MSG_ID_DEBUG_FLOAT_ARRAY:
            ack(self.link, msg, mavlink.MAV_RESULT_ACCEPTED)  # PMON_STAT at once
            self.publish_stat()
            return
        self.on_command(msg)

    def on_command_int(self, msg) -> None:
        ack(self.link, msg, mavlink.MAV_RESULT_UNSUPPORTED, Reason.UNKNOWN_ACTION)


class Router:
    """``autopilot``: the autopilot side (who the autopilot is, its clock samples); ``parts``:
    the app's parts, whose ``handlers()`` make ``handlers`` (type -> the parts' handlers, in the
    parts' order); ``ctx``: the counters, the voice and the config's ``gcs_sysids``."""

    def __init__(self, ctx: AppContext, autopilot, parts: list[Part]):
        self.vehicle = autopilot.vehicle
        self.observe_time = autopilot.observe_time
        self.gcs_sysids = ctx.cfg.gcs_sysids
        self.counters = ctx.counters
        self.say = ctx.say
        self.handlers: dict[str, list[Handler]] = {}
        for part in parts:
            for mtype, handler in part.handlers().items():
                self.handlers.setdefault(mtype, []).append(handler)

    def handle(self, msg) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self.counters.add("mavlink_bad_data")
            return
        handlers = self.handlers.get(mtype)
        if handlers and mtype in ANY_SOURCE:
            self._run(handlers, msg)
            return
        v = self.vehicle
        if v.sysid is None:
            return
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        if (src_sys, src_comp) == (v.sysid, v.compid):
            self.observe_time(msg)
            if handlers and mtype not in FOR_APP:
                self._run(handlers, msg)
            return
        if handlers and mtype in FOR_APP and self._for_app(msg, mtype, src_sys):
            self._run(handlers, msg)

    @staticmethod
    def _run(handlers: list[Handler], msg) -> None:
        for handler in handlers:
            handler(msg)

    def _for_app(self, msg, mtype: str, src_sys: int) -> bool:
        """Addressed to the app, and (a write) from a configured ground station."""
        tsys = getattr(msg, "target_system", None)
        tcomp = getattr(msg, "target_component", None)
        if tsys is None or tsys not in (0, self.vehicle.sysid) or tcomp not in (0, COMP_ID):
            return False
        if mtype not in WRITES:
            return True
        if tcomp != COMP_ID:
            return False
        if src_sys not in self.gcs_sysids:
            self.counters.add("rejected_sysid")
            self.say(f"{mtype} from sysid {src_sys} ignored: not a configured GCS",
                     mavlink.MAV_SEVERITY_WARNING, once=f"sysid{src_sys}")
            return False
        return True
