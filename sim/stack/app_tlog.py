"""The app's own tlog read back (what it saw of its autopilot; how fast it gave way to a pilot), and
which autopilot mode is the app's: sim/stack/procedure.py's Mission and tests/firmware/test_conformance.py
use them.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np

from onboard.app.contract import MAV_CMD_PMON
from onboard.app.mavlink_connection import mavlink
from onboard.app.gcs.statustext import Reassembler

GUIDED = 4  # ArduCopter's custom_mode
PX4_OFFBOARD = 6  # PX4's main mode (custom_mode bits 16-23)


def app_mode(autopilot: str) -> Callable[[int], bool]:
    """Whether a HEARTBEAT custom_mode is the mode the app flies in (GUIDED; PX4's OFFBOARD)."""
    if autopilot == "px4":
        return lambda m: m is not None and (m >> 16) & 0xFF == PX4_OFFBOARD
    return lambda m: m == GUIDED


def takeover_reactions(tlog: Path, modes: list[tuple], in_app_mode: Callable[[int], bool] = app_mode("ardupilot")
                       ) -> list[float]:
    """See ``Mission.takeover_reactions``; ``modes``: (autopilot s, custom_mode, armed) changes;
    ``in_app_mode``: whether a custom_mode is the app's (``app_mode``)."""
    from onboard.app.mavlink2 import mavutil

    episodes = []  # (left GUIDED, back in GUIDED or inf), autopilot s
    for i, (t0, mode, _) in enumerate(modes):
        if t0 is None or in_app_mode(mode) or i == 0 or not in_app_mode(modes[i - 1][1]):
            continue
        back = next((t for t, m, _ in modes[i + 1:] if in_app_mode(m) and t is not None), math.inf)
        episodes.append((t0, back))
    sent: list[float] = []  # the app's setpoints, its clock
    told: list[float] = []  # autopilot time when an operator's command reached the app (resume ...)
    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    t = None
    while (m := conn.recv_match()) is not None:
        mtype = m.get_type()
        if mtype == "SET_POSITION_TARGET_LOCAL_NED":
            sent.append(m.time_boot_ms / 1000.0)
        elif hasattr(m, "time_boot_ms") and m.get_srcComponent() == 1:
            t = m.time_boot_ms / 1000.0
        elif mtype == "COMMAND_LONG" and m.command == MAV_CMD_PMON and t is not None \
                and m.target_component == mavlink.MAV_COMP_ID_ONBOARD_COMPUTER:
            told.append(t)
    # setpoints after the operator's resume are the app's way back in (PX4: streamed before
    # OFFBOARD is asked for), not a late reaction: an episode ends there
    out = []
    for a, b in episodes:
        end = min(b, min((x for x in told if x > a), default=math.inf))
        last = max((x for x in sent if a <= x < end), default=None)
        out.append(0.0 if last is None else last - a)
    return out

def app_view(tlog: Path) -> dict:
    """What the app saw of its autopilot, from the app's own tlog: the comparison
    tests/firmware/test_conformance.py makes between the mock and ArduPilot.

    - ``rates_hz``: messages from the autopilot per autopilot second while the app monitored;
    - ``unasked``: message types it sent that the app never asked for (by id or stream);
    - ``acks``: per command the app sent, its distinct results in order (repeats collapsed);
    - ``landed``, ``prearm``, ``modes``: distinct values in order (EXTENDED_SYS_STATE,
      SYS_STATUS's pre-arm bit, HEARTBEAT custom_mode);
    - ``no_fix_positions``: GLOBAL_POSITION_INTs with lat = lon = 0 (before the GPS fix);
    - ``origin_t``, ``armed_t``: autopilot s when the EKF origin came and when it armed;
    - ``app_said``: the app's own STATUSTEXTs without "PMON: " and any " (...)" detail, repeats
      collapsed.
    """
    from onboard.app.mavlink2 import mavutil

    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    asked = {mavlink.MAVLINK_MSG_ID_HEARTBEAT}
    out: dict = {"acks": {}, "landed": [], "prearm": [], "modes": [], "app_said": [],
                 "no_fix_positions": 0, "origin_t": None, "armed_t": None, "unasked": set()}
    timed: list[tuple[float, str]] = []  # (autopilot s, type) of every autopilot message
    monitored: list[float] = []  # autopilot s of the app's heartbeats saying "monitoring"
    chunks = Reassembler(clock=lambda: 0.0)  # a recording: a text is whole when its last chunk is
    t = None
    while (m := conn.recv_match()) is not None:
        mtype = m.get_type()
        src = (m.get_srcSystem(), m.get_srcComponent())
        if src[1] == mavlink.MAV_COMP_ID_ONBOARD_COMPUTER:  # sent by the app
            if mtype == "COMMAND_LONG" and m.command in (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
                                                         mavlink.MAV_CMD_REQUEST_MESSAGE):
                asked.add(int(m.param1))
            elif mtype == "STATUSTEXT":  # whole: a long text comes in chunks
                for text in chunks.feed(m):
                    _add_distinct(out["app_said"], text.removeprefix("PMON: ").split(" (")[0].strip())
            elif mtype == "HEARTBEAT" and m.custom_mode == 1 and t is not None:  # monitoring
                monitored.append(t)
            continue
        if src != (1, 1) or mtype == "BAD_DATA":
            continue
        if hasattr(m, "time_boot_ms"):
            t = m.time_boot_ms / 1000.0
        if m.get_msgId() not in asked and mtype not in ("COMMAND_ACK", "STATUSTEXT", "PARAM_VALUE"):
            out["unasked"].add(mtype)
        if t is not None:
            timed.append((t, mtype))
        _autopilot_said(out, m, mtype, t)
    out["rates_hz"], out["monitoring_s"] = _monitoring_rates(monitored, timed)
    out["unasked"] = sorted(out["unasked"])
    return out


def _add_distinct(seq: list, value) -> None:
    """Append ``value`` unless it repeats the last (``app_view``'s distinct values in order)."""
    if not seq or seq[-1] != value:
        seq.append(value)


def _autopilot_said(out: dict, m, mtype: str, t: float | None) -> None:
    """Into ``app_view``'s ``out``: what autopilot message ``m`` (its type, at autopilot s ``t``)
    tells of acks, landed state, pre-arm, mode, arming, fix and origin."""
    if mtype == "COMMAND_ACK":
        _add_distinct(out["acks"].setdefault(mavlink.enums["MAV_CMD"][m.command].name, []),
                      mavlink.enums["MAV_RESULT"][m.result].name.removeprefix("MAV_RESULT_"))
    elif mtype == "EXTENDED_SYS_STATE":
        _add_distinct(out["landed"],
                      mavlink.enums["MAV_LANDED_STATE"][m.landed_state].name.removeprefix("MAV_LANDED_STATE_"))
    elif mtype == "SYS_STATUS" and m.onboard_control_sensors_present & mavlink.MAV_SYS_STATUS_PREARM_CHECK:
        _add_distinct(out["prearm"], bool(m.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK))
    elif mtype == "HEARTBEAT":
        _add_distinct(out["modes"], m.custom_mode)
        if m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED and out["armed_t"] is None:
            out["armed_t"] = t
    elif mtype == "GLOBAL_POSITION_INT" and m.lat == 0 and m.lon == 0:
        out["no_fix_positions"] += 1
    elif mtype == "GPS_GLOBAL_ORIGIN" and out["origin_t"] is None:
        out["origin_t"] = t


def _monitoring_rates(monitored: list[float], timed: list[tuple[float, str]]) -> tuple[dict, float]:
    """Messages per autopilot second by type (``timed``: (autopilot s, type)) over the longest
    stretch of monitoring (``monitored``: the app's heartbeats saying so, 1 Hz of its own clock:
    a gap of over three of them ends a stretch), and that stretch's length (s)."""
    gap = 3.0 * float(np.median(np.diff(monitored))) if len(monitored) > 2 else 2.0
    best, start = (0.0, 0.0), None
    for a, b in zip(monitored, monitored[1:] + [math.inf]):
        start = a if start is None else start
        if b - a > gap:
            best = max(best, (a - start, start), key=lambda x: x[0])
            start = None
    span, t0 = best
    counts: dict[str, int] = {}
    for tm, mtype in timed:
        if t0 <= tm <= t0 + span:
            counts[mtype] = counts.get(mtype, 0) + 1
    rates = {k: round(v / span, 2) for k, v in sorted(counts.items())} if span > 0 else {}
    return rates, round(span, 1)
