"""The onboard app's wire contract as a ground station sees it (docs/MAVLINK.md), decoded into
frozen dataclasses. The numbers and layouts are the app's own (onboard/app/contract.py, a light
module: no core, no app); the words for them and the decoding are here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from onboard.app import contract as C
from onboard.app.autopilot.profiles import ARDUPILOT, PX4
from onboard.app.autopilot.launch import PHASES
from onboard.app.mavlink_connection import mavlink

GCS_SYSID = 255
GCS_COMPID = mavlink.MAV_COMP_ID_MISSIONPLANNER  # 190
APP_COMPID = C.APP_COMPID  # 191
APP_COMMAND = C.MAV_CMD_PMON  # param1 = action

ACTIONS = {a.name.lower(): int(a) for a in C.Action}
APP_STATES = tuple(s.name.lower().replace("_", " ") for s in C.State)  # by value
# COMMAND_ACK.result_param2 of the app's refusals
REASONS = {int(r): text for r, text in C.REASON_TEXT.items()}

# ArduCopter modes the CLI commands (HEARTBEAT.custom_mode)
GUIDED, LOITER, RTL, LAND, BRAKE = (ARDUPILOT.mode_number(m) for m in ("GUIDED", "LOITER", "RTL", "LAND", "BRAKE"))


def mode_names(firmware: str = "ArduPilot") -> list[str]:
    """A firmware's flight mode names (ArduCopter's as pymavlink maps them; PX4's)."""
    return (PX4 if firmware == "PX4" else ARDUPILOT).mode_names()


def mode_number(name: str) -> int | None:
    """ArduCopter's custom_mode for a mode name (any case), or None."""
    return ARDUPILOT.mode_number(name)


def known_mode(name: str) -> bool:
    """A mode name some firmware the ground station knows has (checked again against the
    vehicle's once connected)."""
    return ARDUPILOT.mode_number(name) is not None or PX4.mode_number(name) is not None


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
    mode: str = "unknown"  # what it most likely does (contract.TGT_MODES)
    mode_p: float = math.nan  # ... with this probability
    goal_index: int = -1  # the goal region it heads for, as an index into the scenario's goals

    @staticmethod
    def from_msg(msg) -> "TargetEstimate":
        d = dict(zip(C.TGT_FIELDS, msg.data))
        since = d["since_scan_s"]
        code, gi = d["mode"], d["goal_index"]
        mode = C.TGT_MODES[int(code)] if math.isfinite(code) and 0 <= code < len(C.TGT_MODES) else "unknown"
        return TargetEstimate(int(msg.array_id), d["x_east_m"], d["y_north_m"], d["vx_mps"], d["vy_mps"],
                              d["sigma_x_m"], d["sigma_y_m"], d["cov_xy_m2"], None if since == -1 else since,
                              bool(d["degenerate"]), d["tick_time_s"], mode, d["mode_p"],
                              int(gi) if mode == "goal" and math.isfinite(gi) and 0 <= gi < 1024 else -1)

    def mode_text(self, goal_names: tuple[str, ...] = ()) -> str:
        """``heading for G 0.95``, ``stationary 0.93``, ``-`` (no modes)."""
        if self.mode == "unknown" or not math.isfinite(self.mode_p):
            return "-"
        what = self.mode
        if self.mode == "goal":
            what = "heading for " + (goal_names[self.goal_index] if 0 <= self.goal_index < len(goal_names)
                                     else f"goal {self.goal_index + 1}")
        return f"{what} {self.mode_p:.2f}"

    @property
    def name(self) -> str:
        return f"T{self.index + 1}"


WARN_SPEED, WARN_ACCEL = C.WARN_SPEED, C.WARN_ACCEL  # PMON_STAT "warnings" bits
# the launch sequence's phases (onboard/app/autopilot/launch.py) in words, by PMON_STAT launch_phase
_PHASE_WORDS = {"ready": "waiting for the autopilot to be ready", "mode": "switching to the launch mode",
                "arm": "arming", "takeoff": "taking off", "climb": "climbing", "start": "starting"}
LAUNCH_PHASES = tuple(_PHASE_WORDS[p] for p in PHASES)


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
    limits: str | None = None  # the planner's speed, acceleration, jerk and the autopilot's, in words
    # a KrakenSDR input's frames used, lines and frames refused, sets gated; None: no KrakenSDR input
    kraken: tuple[int, int, int] | None = None
    overruns: int = 0  # ticks over their budget (PMON_BUDGET)
    overrun_stage: str | None = None  # the stage the newest overran in (C.OVERRUN_STAGES); None: none yet
    # the newest tick's planned next point (advisory's advice; while monitoring, what is flown);
    # None: that tick planned nothing, or an app older than the field
    advice_enu: tuple[float, float, float] | None = None

    @staticmethod
    def from_msg(msg) -> "AppStatus":
        d = dict(zip(C.STAT_FIELDS, msg.data))
        nxt = tuple(d[k] for k in ("next_e_m", "next_n_m", "next_u_m"))
        uav = tuple(d[k] for k in ("uav_e_m", "uav_n_m", "uav_u_m"))
        speed, speed_plan = d["speed_limit_mps"], d["speed_plan_mps"]
        accel, accel_plan = d["accel_limit_mps2"], d["accel_plan_mps2"]
        bits = _int(d["warnings"])
        warnings = []
        if bits & WARN_SPEED:
            warnings.append(f"autopilot speed limit {_fmt(speed)} m/s < {_fmt(speed_plan)} m/s planned: "
                            "the vehicle lags its setpoints")
        if bits & WARN_ACCEL:
            warnings.append(f"autopilot acceleration limit {_fmt(accel)} m/s^2 < {_fmt(accel_plan)} m/s^2 planned")
        phase = _int(d["launch_phase"], -1)
        limits = None
        if math.isfinite(speed_plan):
            jerk, jerk_plan = d["jerk_limit_mps3"], d["jerk_plan_mps3"]
            accel_text = f", {_fmt(accel_plan)} m/s^2" if math.isfinite(accel_plan) else ""
            if math.isfinite(accel_plan) and math.isfinite(jerk_plan):  # 0: the plan's acceleration steps
                accel_text += f", {_fmt(jerk_plan)} m/s^3" if jerk_plan > 0.0 else ", acceleration steps"
            # the autopilot's jerk where it shapes one (ArduPilot; not PX4's OFFBOARD: NaN)
            jerk_text = f", {_fmt(jerk)} m/s^3" if math.isfinite(jerk) and jerk > 0.0 else ""
            limits = (f"planned at {_fmt(speed_plan)} m/s{accel_text} (autopilot {_fmt(speed)} m/s, "
                      f"{_fmt(accel)} m/s^2{jerk_text})")
        return AppStatus(app_state_name(d["state"]), d["tick_rate_hz"], _num(d["last_tick_time_s"]),
                         _num(d["tick_ms"]), nxt if all(math.isfinite(v) for v in nxt) else None,
                         _int(d["dgram_accepted"]), _int(d["dgram_rejected"]), _int(d["ticks"]),
                         _int(d["ticks_skipped"]), _int(d["ticks_late"]), _int(d["setpoints_refused"]),
                         _num(d["latency_ms"]), uav if all(math.isfinite(v) for v in uav) else None,
                         tuple(warnings), LAUNCH_PHASES[phase] if 0 <= phase < len(LAUNCH_PHASES) else None,
                         limits, _kraken(d), _int(d.get("overruns", 0.0)), _stage(d.get("overrun_stage", 0.0)),
                         _point(d, C.ADVICE_FIELDS))


def _point(d: dict, names: tuple[str, ...]) -> tuple[float, float, float] | None:
    """Three fields as an ENU point; None when one is not finite (NaN: none)."""
    p = tuple(d.get(k, math.nan) for k in names)
    return p if all(math.isfinite(v) for v in p) else None


def _stage(x: float) -> str | None:
    """PMON_STAT's overrun_stage in words (0, unknown or an older app's reserved 0: None)."""
    code = _int(x)
    return C.OVERRUN_STAGES[code - 1] if 1 <= code <= len(C.OVERRUN_STAGES) else None


def _kraken(d: dict) -> tuple[int, int, int] | None:
    """The KrakenSDR counts, None when the app has no KrakenSDR input (NaN) or is older than them."""
    values = [d.get(k, math.nan) for k in C.KRAKEN_STAT_FIELDS]
    return tuple(_int(v) for v in values) if all(math.isfinite(v) for v in values) else None


def _int(x: float, default: int = 0) -> int:
    """A count from a float field; a non-finite or absurd value (a hostile or broken peer) is
    ``default``, never an exception."""
    return int(x) if math.isfinite(x) and abs(x) < 2**53 else default


def _fmt(x: float) -> str:
    return f"{x:g}" if math.isfinite(x) else "?"


def is_autopilot_heartbeat(msg) -> bool:
    return msg.get_type() == "HEARTBEAT" and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID and \
        msg.type not in (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER)
