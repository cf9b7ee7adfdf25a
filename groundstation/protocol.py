"""The onboard app's wire contract as a ground station sees it (docs/MAVLINK.md), decoded into
frozen dataclasses.

The numbers are repeated here rather than imported from ``onboard.app.app``: that module pulls
in the whole core (~0.5 s of imports per CLI call). tests/test_gcs.py checks they match.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from onboard.app.mavlink_connection import mavlink  # sets MAVLINK20 before pymavlink loads

GCS_SYSID = 255
GCS_COMPID = mavlink.MAV_COMP_ID_MISSIONPLANNER  # 190
APP_COMPID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191
APP_COMMAND = mavlink.MAV_CMD_USER_1  # param1 = action

ACTIONS = {"start": 1, "pause": 2, "resume": 3, "stop": 4, "launch": 5}
APP_STATES = ("idle", "monitoring", "paused", "pilot override", "fault")
# COMMAND_ACK.result_param2 of the app's refusals
REASONS = {1: "vehicle not armed", 2: "vehicle not flying", 3: "no DF data in the last 3 s",
           4: "no valid position or local origin yet", 5: "no autopilot heartbeat",
           6: "unknown action", 7: "not possible in this state", 8: "already flying: use start",
           9: "launch in progress"}

# ArduCopter modes the CLI commands (HEARTBEAT.custom_mode)
GUIDED, LOITER, RTL, LAND, BRAKE = 4, 5, 6, 9, 17


def mode_names() -> list[str]:
    """ArduCopter's flight mode names, as pymavlink maps them."""
    from pymavlink import mavutil
    return sorted(mavutil.mode_mapping_acm.values())


def mode_number(name: str) -> int | None:
    """ArduCopter's custom_mode for a mode name (any case), or None."""
    from pymavlink import mavutil
    return {v: k for k, v in mavutil.mode_mapping_acm.items()}.get(name.strip().upper())

RESULTS = {k: e.name.removeprefix("MAV_RESULT_") for k, e in mavlink.enums["MAV_RESULT"].items()
           if e.name != "MAV_RESULT_ENUM_END"}


def app_state_name(code: float | int | None) -> str:
    if code is None or not math.isfinite(code) or not 0 <= int(code) < len(APP_STATES):
        return "unknown"
    return APP_STATES[int(code)]


def _num(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


@dataclass(frozen=True)
class TargetEstimate:
    """One PMON_TGT: the app's estimate of one target (mission ENU frame, m, m/s)."""

    index: int
    x: float
    y: float
    vx: float
    vy: float
    sigma_x: float
    sigma_y: float
    cov_xy: float
    since_detection_s: float | None  # None: never detected
    degenerate: bool
    tick_time_s: float

    @staticmethod
    def from_msg(msg) -> "TargetEstimate":
        d = msg.data
        return TargetEstimate(int(msg.array_id), d[0], d[1], d[3], d[4], d[6], d[7], d[9],
                              None if d[8] == -1 else d[8], bool(d[12]), d[13])

    @property
    def name(self) -> str:
        return f"T{self.index + 1}"


# PMON_STAT "warnings" bits (onboard/app/app.py WARN_*) and launch phases (onboard/app/launch.py)
WARN_SPEED, WARN_ACCEL = 1, 2
LAUNCH_PHASES = ("waiting for the autopilot to be ready", "switching to GUIDED", "arming",
                 "taking off", "climbing", "starting")


@dataclass(frozen=True)
class AppStatus:
    """One PMON_STAT: the app's state and health."""

    state: str
    tick_rate_hz: float
    last_tick_time_s: float | None
    tick_ms: float | None
    next_enu: tuple[float, float, float] | None  # current setpoint
    datagrams_accepted: int
    datagrams_rejected: int
    ticks: int
    ticks_skipped: int
    ticks_late: int
    setpoints_refused: int
    latency_ms: float | None
    uav_enu: tuple[float, float, float] | None
    warnings: tuple[str, ...] = ()  # conditions that hold now, in words
    launch_phase: str | None = None  # None: no launch sequence running
    limits: str | None = None  # the planner's speed and acceleration and the autopilot's, in words

    @staticmethod
    def from_msg(msg) -> "AppStatus":
        d = msg.data
        nxt = tuple(d[4:7]) if all(math.isfinite(v) for v in d[4:7]) else None
        uav = tuple(d[14:17]) if all(math.isfinite(v) for v in d[14:17]) else None
        bits = _int(d[20])
        warnings = []
        if bits & WARN_SPEED:
            warnings.append(f"autopilot speed limit {_fmt(d[21])} m/s < {_fmt(d[22])} m/s planned: "
                            "the vehicle lags its setpoints")
        if bits & WARN_ACCEL:
            warnings.append(f"autopilot acceleration limit {_fmt(d[23])} m/s^2 < {_fmt(d[24])} m/s^2 planned")
        phase = _int(d[25], -1)
        limits = None
        if math.isfinite(d[22]):
            accel = f", {_fmt(d[24])} m/s^2" if math.isfinite(d[24]) else ""
            limits = (f"planned at {_fmt(d[22])} m/s{accel} (autopilot {_fmt(d[21])} m/s, "
                      f"{_fmt(d[23])} m/s^2)")
        return AppStatus(app_state_name(d[0]), d[1], _num(d[2]), _num(d[3]), nxt, _int(d[7]), _int(d[8]),
                         _int(d[9]), _int(d[10]), _int(d[18]), _int(d[19]), _num(d[11]), uav,
                         tuple(warnings), LAUNCH_PHASES[phase] if 0 <= phase < len(LAUNCH_PHASES) else None,
                         limits)


def _int(x: float, default: int = 0) -> int:
    """A count from a float field; a non-finite or absurd value (a hostile or broken peer) is
    ``default``, never an exception."""
    return int(x) if math.isfinite(x) and abs(x) < 2**53 else default


def _fmt(x: float) -> str:
    return f"{x:g}" if math.isfinite(x) else "?"


def is_autopilot_heartbeat(msg) -> bool:
    return msg.get_type() == "HEARTBEAT" and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and \
        msg.type not in (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER)
