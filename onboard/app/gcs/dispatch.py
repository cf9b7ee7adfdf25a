"""MAVLink in: one table from message type to handler (MAVProxy's module contract: dispatch on
``msg.get_type()``), and who may be obeyed.

- HEARTBEAT from anyone goes to the autopilot side (it picks its autopilot and ignores the rest).
- Messages from the autopilot (its system and component) feed the autopilot side; every one
  stamped with ``time_boot_ms`` is a clock sample first.
- Messages for the app (target system 0 or the vehicle's, component 0 or 191): parameter reads
  are answered to anyone; commands and parameter writes (``WRITES``) must be addressed to 191
  and come from a configured ground station (``gcs_sysids``), else they are ignored, counted
  and said once per stranger (no ACK: nothing to tell a stranger).
- Anything else is not the app's business and is dropped unread.

Handlers run contained by the io loop (an exception costs its own message only). io thread,
under the app lock.
"""
from __future__ import annotations

from typing import Callable

from onboard.app.contract import Reason
from onboard.app.counters import Counters
from onboard.app.mavlink_connection import COMP_ID, Link, mavlink

Handler = Callable[[object], None]
WRITES = frozenset({"COMMAND_LONG", "COMMAND_INT", "PARAM_SET"})  # addressed to 191, from a GCS only


def ack(link: Link, msg, result: int, reason: Reason = Reason.NONE) -> None:
    """COMMAND_ACK for a COMMAND_LONG/INT; ``reason`` (result_param2) says why it was refused."""
    link.send(link.mav.command_ack_encode(
        msg.command, result, 0, int(reason), msg.get_srcSystem(), msg.get_srcComponent()))


class Router:
    """``autopilot``: the autopilot side; ``machine``: the state machine (MAV_CMD_PMON);
    ``params``: the parameter server; ``publish_stat``: PMON_STAT at once (asked for with
    MAV_CMD_REQUEST_MESSAGE)."""

    def __init__(self, link: Link, autopilot, machine, params, publish_stat: Callable[[], None],
                 gcs_sysids: tuple[int, ...], counters: Counters, say):
        self.link = link
        self.vehicle = autopilot.vehicle
        self.observe_time = autopilot.observe_time
        self.publish_stat = publish_stat
        self.gcs_sysids = gcs_sysids
        self.counters = counters
        self.say = say
        self.any_source: dict[str, Handler] = {"HEARTBEAT": autopilot.on_heartbeat}
        self.from_autopilot: dict[str, Handler] = {
            "GLOBAL_POSITION_INT": autopilot.on_global_position_int,
            "SYSTEM_TIME": autopilot.on_system_time,
            "SYS_STATUS": autopilot.on_sys_status,
            "STATUSTEXT": autopilot.on_statustext,
            "EXTENDED_SYS_STATE": autopilot.on_extended_sys_state,
            "GPS_GLOBAL_ORIGIN": autopilot.on_gps_global_origin,
            "COMMAND_ACK": autopilot.on_command_ack,
            "PARAM_VALUE": autopilot.on_param_value,
            "UNKNOWN_410": autopilot.on_event,  # PX4's EVENT, not in pymavlink 2.4.50's dialects
        }
        self.for_app: dict[str, Handler] = {
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "PARAM_REQUEST_LIST": params.on_request_list,
            "PARAM_REQUEST_READ": params.on_request_read,
            "PARAM_SET": params.on_set,
        }
        self.on_command = machine.on_command

    def handle(self, msg) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            self.counters.add("mavlink_bad_data")
            return
        handler = self.any_source.get(mtype)
        if handler is not None:
            handler(msg)
            return
        v = self.vehicle
        if v.sysid is None:
            return
        src_sys, src_comp = msg.get_srcSystem(), msg.get_srcComponent()
        if (src_sys, src_comp) == (v.sysid, v.compid):
            self.observe_time(msg)
            handler = self.from_autopilot.get(mtype)
            if handler is not None:
                handler(msg)
            return
        handler = self.for_app.get(mtype)
        if handler is not None and self._for_app(msg, mtype, src_sys):
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

    def _on_command_long(self, msg) -> None:
        if msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE and int(msg.param1) == \
                mavlink.MAVLINK_MSG_ID_DEBUG_FLOAT_ARRAY:
            ack(self.link, msg, mavlink.MAV_RESULT_ACCEPTED)  # PMON_STAT at once
            self.publish_stat()
            return
        self.on_command(msg)

    def _on_command_int(self, msg) -> None:
        ack(self.link, msg, mavlink.MAV_RESULT_UNSUPPORTED, Reason.UNKNOWN_ACTION)
