"""What the app tells the ground (docs/MAVLINK.md): its HEARTBEAT (the app state in
custom_mode), STATUSTEXT "PMON: ...", PMON_STAT and PMON_TGT (DEBUG_FLOAT_ARRAY, laid out by
onboard/app/contract.py's STAT_FIELDS and TGT_FIELDS), and the event list it keeps of what it
said. io thread and worker under the app lock; ``alarm`` (the watchdog) without it."""
from __future__ import annotations

import logging
import math
from collections import deque
from typing import Callable

import numpy as np

from onboard.app.contract import STAT_FIELDS, STATUS, TGT_FIELDS, State
from onboard.app.mavlink_connection import Link, mavlink
from onboard.app.gcs.statustext import send_statustext
from onboard.app.part import Job, Part
from onboard.app.autopilot.vehicle import Vehicle

log = logging.getLogger("pmon.app")
DEBUG_ARRAY_LEN = 58  # DEBUG_FLOAT_ARRAY.data


class Publisher(Part):
    """``state()``: the app state now; ``status()``: PMON_STAT's values by STAT_FIELDS name."""

    def __init__(self, link: Link, clock, vehicle: Vehicle, state: Callable[[], State],
                 status: Callable[[], dict[str, float]]):
        self.link = link
        self.clock = clock
        self.vehicle = vehicle
        self._state = state
        self._status = status
        self.events: deque[tuple[float | None, str]] = deque(maxlen=500)  # (autopilot t, text)
        self._said: set[str] = set()
        self.heartbeat_local = -math.inf  # local s of the last periodic heartbeat
        self.stat_local = -math.inf  # ... and PMON_STAT

    # ----- STATUSTEXT
    def say(self, text: str, severity: int = mavlink.MAV_SEVERITY_INFO, once: str | None = None) -> None:
        """STATUSTEXT 'PMON: ...' (and the event list/log). ``once``: a key said only once."""
        if once is not None:
            if once in self._said:
                return
            self._said.add(once)
        full = f"PMON: {text}"
        self.events.append((self.clock.now(), full))
        log.info(full)
        if self.vehicle.sysid is not None:
            send_statustext(self.link, severity, full)  # chunked past 50 characters

    def said(self, key: str) -> bool:
        return key in self._said

    def mark_said(self, key: str) -> None:
        self._said.add(key)

    def forget(self, prefix: str) -> None:
        """Let the ``once`` keys starting with ``prefix`` be said again."""
        self._said = {k for k in self._said if not k.startswith(prefix)}

    def alarm(self, text: str) -> None:
        """A critical report from the watchdog: no app lock (the stuck thread may hold it)."""
        full = f"PMON: {text}"
        self.events.append((None, full))
        log.error(full)
        if self.vehicle.sysid is not None:
            send_statustext(self.link, mavlink.MAV_SEVERITY_CRITICAL, full)

    # ----- HEARTBEAT, PMON_STAT, PMON_TGT
    def heartbeat(self) -> None:
        state = self._state()
        self.link.send(self.link.mav.heartbeat_encode(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID,
            mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(state), STATUS[state]))

    def jobs(self) -> tuple[Job, ...]:
        return (Job("periodic heartbeat", lambda local, now: self.beat(local)),)

    def beat(self, local: float) -> None:
        """The periodic job: HEARTBEAT and PMON_STAT at 1 Hz once the autopilot is known."""
        if self.vehicle.sysid is None or local - self.heartbeat_local < 1.0:
            return
        self.heartbeat_local = local
        self.heartbeat()
        if local - self.stat_local >= 1.0:
            self.publish_stat(local)

    def publish_stat(self, local: float | None = None) -> None:
        status = self._status()
        self._debug_array("PMON_STAT", 0, [status[f] for f in STAT_FIELDS], self.clock.now())
        if local is not None:
            self.stat_local = local

    def publish_target(self, index: int, values: dict[str, float], t: float) -> None:
        self._debug_array("PMON_TGT", index, [values[f] for f in TGT_FIELDS], t)

    def _debug_array(self, name: str, array_id: int, values, t: float | None) -> None:
        data = [float(v) if np.isfinite(v) else float("nan") for v in values][:DEBUG_ARRAY_LEN]
        data += [0.0] * (DEBUG_ARRAY_LEN - len(data))
        usec = int((t or 0.0) * 1e6)
        self.link.send(self.link.mav.debug_float_array_encode(usec, name.encode(), array_id, data))
