"""What one MAVLink component puts on a link, counted by kind: the check that the app in advisory
commands nothing (tests/app/test_advisory.py on the mock autopilot,
tests/firmware/test_ardupilot_advisory.py on ArduCopter's SITL). Fed the raw bytes a relay
passes towards the autopilot (``TcpProxy(tap=counter.feed)``), so it counts what reaches the
autopilot, whoever sent it, whatever the sender believes it sent.

The kinds (docs/OPERATING.md, "Advisory"):

- ``telemetry``: what the app tells and answers: HEARTBEAT, STATUSTEXT, DEBUG_FLOAT_ARRAY,
  NAMED_VALUE_FLOAT/INT, and its answers to a ground station (COMMAND_ACK, PARAM_VALUE);
- ``read``: requests that change nothing the vehicle does: PARAM_REQUEST_READ / LIST, and
  COMMAND_LONG / COMMAND_INT of MAV_CMD_SET_MESSAGE_INTERVAL or MAV_CMD_REQUEST_MESSAGE (which
  messages the autopilot streams on this link, and its origin);
- ``command``: everything else: setpoints, modes, arming, take-off, missions, parameter writes,
  RC overrides, any other command id, any message type not named above.
"""
from __future__ import annotations

import threading
from collections import Counter

from onboard.app.mavlink_connection import mavlink

TELEMETRY = frozenset({"HEARTBEAT", "STATUSTEXT", "DEBUG_FLOAT_ARRAY", "NAMED_VALUE_FLOAT", "NAMED_VALUE_INT",
                       "COMMAND_ACK", "PARAM_VALUE"})
READ_MESSAGES = frozenset({"PARAM_REQUEST_READ", "PARAM_REQUEST_LIST"})
READ_COMMANDS = frozenset({mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_CMD_REQUEST_MESSAGE})


def kind(msg) -> str:
    """``telemetry``, ``read`` or ``command`` (the module's list)."""
    mtype = msg.get_type()
    if mtype in TELEMETRY:
        return "telemetry"
    if mtype in READ_MESSAGES:
        return "read"
    if mtype in ("COMMAND_LONG", "COMMAND_INT") and msg.command in READ_COMMANDS:
        return "read"
    return "command"


class LinkCounter:
    """Counts the messages of component (``sysid``, ``compid``) in the bytes fed to it (any
    thread); ``sysid`` None: any system. ``by_kind``: kind -> count; ``by_type``: (kind, message
    type or ``COMMAND_LONG:<id>``) -> count; ``first_command_t``: the wall clock of the first
    command, from the feeder's clock (None: none)."""

    def __init__(self, compid: int, sysid: int | None = None, clock=None):
        self.compid, self.sysid = compid, sysid
        self._mav = mavlink.MAVLink(None)
        self._mav.robust_parsing = True
        self._lock = threading.Lock()
        self._clock = clock
        self.by_kind: Counter = Counter()
        self.by_type: Counter = Counter()
        self.bad = 0  # bytes the parser could not read as MAVLink
        self.first_command_t: float | None = None

    def feed(self, data: bytes) -> None:
        with self._lock:
            try:
                msgs = self._mav.parse_buffer(data) or []
            except Exception:  # a broken frame: counted, the stream goes on
                self.bad += 1
                return
            for m in msgs:
                if m.get_type() == "BAD_DATA":
                    self.bad += 1
                    continue
                if m.get_srcComponent() != self.compid or (self.sysid is not None and m.get_srcSystem() != self.sysid):
                    continue
                k = kind(m)
                name = m.get_type()
                if name in ("COMMAND_LONG", "COMMAND_INT"):
                    name = f"{name}:{m.command}"
                self.by_kind[k] += 1
                self.by_type[(k, name)] += 1
                if k == "command" and self.first_command_t is None and self._clock is not None:
                    self.first_command_t = self._clock()

    def snapshot(self) -> tuple[dict, dict]:
        """(by_kind, by_type) as they are now."""
        with self._lock:
            return dict(self.by_kind), dict(self.by_type)

    def commands(self) -> dict:
        """The commands counted so far, by type."""
        with self._lock:
            return {name: n for (k, name), n in self.by_type.items() if k == "command"}
