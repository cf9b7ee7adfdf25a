"""The planner's speed, acceleration and jerk against the autopilot's limits (docs/MAVLINK.md).

Vehicle motion (the flight policy): the planner flies at the autopilot's limits, capped by the
scenario's ``planning.speed_max_mps`` / ``accel_max_mps2`` / ``jerk_max_mps3`` (what the airframe
can fly; a jerk of 0 stays 0: the acceleration steps): a change of any rebuilds the core setup (``planner``, read by onboard/app/tick/core_side.py), and no plan
is faster than the autopilot flies. The jump model (the paper's policy) asks for its grid's
rings each tick whatever the autopilot's limit: below it the vehicle lags its setpoints, a
warning that holds until the limits or PMON_REACH change: PMON_STAT carries it every second
(``pmon gcs status`` shows it), and it is said when it first holds and again whenever
monitoring starts. Which parameters hold the limits is the autopilot profile's
(``limit_params``). io thread, under the app lock.
"""
from __future__ import annotations

import logging
import math

from onboard.app.contract import WARN_SPEED
from onboard.app.mavlink_connection import mavlink
from onboard.app.params import ParamTable
from onboard.app.autopilot.vehicle import Vehicle
from onboard.policy import vehicle_motion

log = logging.getLogger("pmon.app")


class PlanLimits:
    def __init__(self, scenario, params: ParamTable, vehicle: Vehicle, say):
        self.scenario = scenario  # the base scenario (planning, uav, dynamics)
        self.params = params
        self.vehicle = vehicle
        self.say = say
        # (speed m/s, accel m/s^2, jerk m/s^3) the vehicle-motion planner flies at; None until the
        # autopilot's limits are read (the scenario's then)
        self.planner: tuple[float, float, float] | None = None
        # (speed m/s, accel m/s^2, jerk m/s^3) the planner assumes (PMON_STAT; NaN: none assumed)
        self.plan = (math.nan, math.nan, math.nan)
        self.warnings = 0  # WARN_* bits that hold now (PMON_STAT)
        self.warning: str | None = None  # the same in words, while it holds

    def check(self) -> None:
        """Compare the limits read so far with what the planner assumes; say what changed."""
        names = self.vehicle.profile.limit_params
        if not names:
            return
        if self.scenario.planning.motion == "vehicle":
            self._plan_at_vehicle_limits()
        else:
            self._check_jumps(names[0][0])

    def _plan_at_vehicle_limits(self) -> None:
        v = self.vehicle
        m = vehicle_motion(self.scenario.planning, v.speed_limit_mps or math.inf, v.accel_limit_mps2 or math.inf,
                           v.jerk_limit_mps3 or math.inf)
        planner = (m.speed_max_mps, m.accel_max_mps2, m.jerk_max_mps3)
        if planner != self.planner:
            self.planner = self.plan = planner
            self.say(plan_text(*planner))
        self.warnings, self.warning = 0, None

    def _check_jumps(self, speed_name: str) -> None:
        """The paper's jump: the largest ring asked for, per tick (no acceleration assumed)."""
        sc, have = self.scenario, self.vehicle.speed_limit_mps
        reach = min(sc.uav.n_radial * sc.uav.step_m, self.params.settings.app.reach_m)
        need = reach / sc.dynamics.dt_s
        self.plan = (need, math.nan, math.nan)
        short = have is not None and have < need - 1e-6  # not read yet, or enough: no warning
        text = f"{speed_name} {have:g} m/s < {need:g} planned" if short else None
        changed = text != self.warning
        self.warnings, self.warning = (WARN_SPEED if short else 0), text
        if changed and text is not None:
            log.warning("autopilot %s = %g m/s is below the planner's steps (PMON_REACH) = %g m/s: "
                        "the vehicle will lag the setpoints", speed_name, have, need)
            self.say(text, mavlink.MAV_SEVERITY_WARNING)


def plan_text(speed_mps: float, accel_mps2: float, jerk_mps3: float) -> str:
    """What the vehicle-motion planner flies at, in words (a jerk of 0: the acceleration steps)."""
    jerk = f"{jerk_mps3:g} m/s^3" if jerk_mps3 > 0.0 else "acceleration steps"
    return f"planning at {speed_mps:g} m/s, {accel_mps2:g} m/s^2, {jerk}"
