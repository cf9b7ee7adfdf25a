"""The onboard app's wire contract: its component id, its states, the actions it is commanded
with, the reasons it refuses, and the layout of what it publishes (docs/MAVLINK.md). The app
speaks it and the ground station (groundstation/protocol.py) reads it from here: one
declaration. Light module (the MAVLink dialect only), so a ground station imports it without
the app or the core."""
from __future__ import annotations

from enum import IntEnum

from onboard.app.mavlink_connection import COMP_ID as APP_COMPID  # noqa: F401  (191, the app's component)
from onboard.app.mavlink_connection import mavlink

# MAVLink command sent to component 191; param1 = action
MAV_CMD_PMON = mavlink.MAV_CMD_USER_1  # 31010


class State(IntEnum):
    IDLE = 0
    MONITORING = 1
    PAUSED = 2
    PILOT_OVERRIDE = 3
    FAULT = 4
    ADVISORY = 5  # tracks, plans and publishes its next waypoint; never commands the vehicle


class Action(IntEnum):
    START = 1
    PAUSE = 2
    RESUME = 3
    STOP = 4
    LAUNCH = 5  # GUIDED, arm, take off to h, then START
    ADVISE = 6  # to advisory: plan and publish, command nothing (from monitoring: as pause)


class Reason(IntEnum):
    """COMMAND_ACK.result_param2 when a command is refused (docs/MAVLINK.md)."""

    NONE = 0
    NOT_ARMED = 1
    NOT_FLYING = 2
    NO_SENSOR_DATA = 3
    NO_POSITION = 4
    NO_AUTOPILOT = 5
    UNKNOWN_ACTION = 6
    WRONG_STATE = 7
    ALREADY_FLYING = 8
    BUSY = 9


REASON_TEXT = {
    Reason.NOT_ARMED: "vehicle not armed",
    Reason.NOT_FLYING: "vehicle not flying",
    Reason.NO_SENSOR_DATA: "no DF data in the last 3 s",
    Reason.NO_POSITION: "no valid position or local origin yet",
    Reason.NO_AUTOPILOT: "no autopilot heartbeat",
    Reason.UNKNOWN_ACTION: "unknown action",
    Reason.WRONG_STATE: "not possible in this state",
    Reason.ALREADY_FLYING: "already flying: use start",
    Reason.BUSY: "launch in progress",
}

STATUS = {  # HEARTBEAT.system_status per app state
    State.IDLE: mavlink.MAV_STATE_STANDBY,
    State.MONITORING: mavlink.MAV_STATE_ACTIVE,
    State.PAUSED: mavlink.MAV_STATE_STANDBY,
    State.PILOT_OVERRIDE: mavlink.MAV_STATE_STANDBY,
    State.FAULT: mavlink.MAV_STATE_CRITICAL,
    State.ADVISORY: mavlink.MAV_STATE_STANDBY,
}

TGT_FIELDS = ("x_east_m", "y_north_m", "z_up_m", "vx_mps", "vy_mps", "vz_mps", "sigma_x_m",
              "sigma_y_m", "since_scan_s", "cov_xy_m2", "sigma_vx_mps", "sigma_vy_mps",
              "degenerate", "tick_time_s", "mode", "mode_p", "goal_index")
# PMON_TGT "mode": what the target most likely does (onboard/core/tracking/intent.py), "mode_p" its
# probability, "goal_index" its goal region's index in the scenario's goals (-1: none)
TGT_MODES = ("unknown", "goal", "stationary", "free", "elsewhere")  # by code; 0: the filter has no modes
STAT_FIELDS = ("state", "tick_rate_hz", "last_tick_time_s", "tick_ms", "next_e_m", "next_n_m",
               "next_u_m", "dgram_accepted", "dgram_rejected", "ticks", "ticks_skipped",
               "latency_ms", "autopilot_mode", "armed", "uav_e_m", "uav_n_m", "uav_u_m",
               "sum_trace", "ticks_late", "setpoints_refused", "warnings", "speed_limit_mps",
               "speed_plan_mps", "accel_limit_mps2", "accel_plan_mps2", "launch_phase",
               "kraken_frames", "kraken_rejected", "kraken_gated", "jerk_limit_mps3", "jerk_plan_mps3",
               "overruns", "overrun_stage", "advice_e_m", "advice_n_m", "advice_u_m")
# "advice_*": the newest tick's planned next point, planned from where the vehicle was (in any
# state while it flies; advisory publishes it and sends nothing); NaN: that tick planned nothing
ADVICE_FIELDS = ("advice_e_m", "advice_n_m", "advice_u_m")
# a KrakenSDR input's (onboard/app/kraken/source.py): frames used, lines and frames refused, sets gated
# empty (confidence, power, overdrive); NaN without one
KRAKEN_STAT_FIELDS = ("kraken_frames", "kraken_rejected", "kraken_gated")
# a tick's stages in order (onboard/app/tick/overrun.py); PMON_STAT "overrun_stage" is 1 + the index of
# the stage the newest overrun passed its budget in, 0 before any
OVERRUN_STAGES = ("wait", "update", "guidance", "prediction", "planning", "send")
# PMON_STAT "warnings" bits: conditions that hold now (docs/MAVLINK.md)
WARN_SPEED = 1  # the autopilot's horizontal speed limit is below what the planner's moves assume
WARN_ACCEL = 2  # ... its acceleration limit
