"""The mock ArduCopter's flight side: its modes, boot and the flight state machine around the
kinematic model (sim/mock/multicopter.py), on its parameters (sim/mock/copter_params.py). No I/O:
sim/mock/autopilot.py speaks MAVLink for it."""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import IntEnum
from typing import Optional

import numpy as np
import pymap3d

from onboard.app.mavlink2 import mavlink
from sim.mock import multicopter
from sim.mock.copter_params import Params
from sim.mock.multicopter import Setpoint, Vec3, VehicleState, limits_from_params

FIRMWARE = "ArduCopter V4.5.7 (pmon mock)"
FW_VERSION = (4 << 24) | (5 << 16) | (7 << 8) | 255  # major.minor.patch, type OFFICIAL

MAGIC_FORCE_ARM = 2989.0
MAGIC_FORCE_DISARM = 21196.0


class Mode(IntEnum):
    """ArduCopter flight mode numbers (HEARTBEAT.custom_mode)."""

    STABILIZE = 0
    ACRO = 1
    ALT_HOLD = 2
    AUTO = 3
    GUIDED = 4
    LOITER = 5
    RTL = 6
    CIRCLE = 7
    LAND = 9
    DRIFT = 11
    SPORT = 13
    FLIP = 14
    AUTOTUNE = 15
    POSHOLD = 16
    BRAKE = 17
    THROW = 18
    AVOID_ADSB = 19
    GUIDED_NOGPS = 20
    SMART_RTL = 21


# Modes the mock flies; others are refused like a mode that fails its init checks.
FLOWN_MODES = {
    Mode.STABILIZE, Mode.ALT_HOLD, Mode.GUIDED, Mode.LOITER, Mode.RTL,
    Mode.LAND, Mode.POSHOLD, Mode.BRAKE,
}
ARMABLE_MODES = {Mode.STABILIZE, Mode.ALT_HOLD, Mode.GUIDED, Mode.LOITER, Mode.POSHOLD}
TAKEOFF_MODES = {Mode.GUIDED, Mode.LOITER, Mode.POSHOLD}  # has_user_takeoff(must_navigate)
HOLD_MODES = {Mode.STABILIZE, Mode.ALT_HOLD, Mode.LOITER, Mode.POSHOLD, Mode.BRAKE}
# autopilot s from an accepted take-off to the climb (landed_state ON_GROUND until then): 3.3 s
# measured on ArduCopter 4.4 SITL (GUIDED, stock parameters: 42.2 s accepted, 45.5 s TAKEOFF)
TAKEOFF_SPOOL_S = 3.3


@dataclass(frozen=True)
class BootTimeline:
    """When ArduCopter is ready after boot, autopilot s, as measured on ArduCopter 4.4 SITL with
    stock parameters (the binary in ../shared/ardupilot): a GPS fix at 8.6 s (GLOBAL_POSITION_INT
    has lat = lon = 0 before), the EKF origin at 18.6 s (GPS_GLOBAL_ORIGIN and HOME_POSITION sent
    to every link unasked, none before), a position estimate good enough to arm at 42.6 s (an
    ARM before is refused, MAV_RESULT_FAILED, "Arm: Need Position Estimate"; SYS_STATUS's
    pre-arm bit unhealthy; "PreArm: Need Position Estimate" every 30 s) - except for one second
    from 24.0 s when the pre-arm bit reads healthy while arming is still refused (seen in three
    of three runs sampled often enough: 23-24 s, 24.0-25.0 s). ``scaled`` keeps the proportions
    for tests that need the behaviour but not the wait."""

    gps_s: float = 8.6
    origin_s: float = 18.6
    ready_s: float = 42.6
    blip_s: tuple[float, float] = (24.0, 25.0)  # pre-arm bit healthy, arming still refused

    @classmethod
    def scaled(cls, ready_s: float) -> "BootTimeline":
        k = max(ready_s, 0.0) / cls.ready_s
        return cls(cls.gps_s * k, cls.origin_s * k, cls.ready_s * k, (24.0 * k, 25.0 * k))


# --------------------------------------------------------------------------- flight logic

@dataclass(frozen=True)
class GuidedTarget:
    """GUIDED sub-mode target, in local NED (ArduPilot's ModeGuided::SubMode)."""

    kind: str  # "pos" | "posvel" | "vel" | "accel"
    pos: Optional[Vec3] = None
    vel: Optional[Vec3] = None
    acc: Optional[Vec3] = None
    yaw: Optional[float] = None
    yaw_rate: Optional[float] = None
    updated_s: float = 0.0


class Copter:
    """ArduCopter-like flight state machine around the kinematic model.

    No I/O: commands return MAV_RESULT values, `tick(dt)` advances the sim by dt
    seconds, and `events` collects (severity, text) STATUSTEXTs for the shell to send.
    """

    def __init__(self, home: tuple[float, float, float], params: Params,
                 rng: Optional[np.random.Generator], pos_noise: float = 0.02,
                 boot: BootTimeline = BootTimeline()):
        self.origin = home  # local NED origin (EKF origin) = home at boot
        self.home = home
        self.home_ned: Vec3 = (0.0, 0.0, 0.0)
        self.params = params
        self.rng = rng
        self.pos_noise = pos_noise
        self.limits = limits_from_params(params, pos_noise)
        self.state = VehicleState()
        self.t = 0.0
        self.mode = Mode.STABILIZE
        self.armed = False
        self.land_complete = True
        self.landed_since = 0.0
        self.takeoff_z: Optional[float] = None  # NED z of an active user takeoff
        self.hold_pos: Vec3 = (0.0, 0.0, 0.0)
        self.guided: Optional[GuidedTarget] = None
        self.fixed_yaw: Optional[float] = None  # CONDITION_YAW
        self.speed: dict[str, float] = {}  # DO_CHANGE_SPEED overrides (m/s)
        self.rtl_phase = "climb"
        self.rtl_z = 0.0
        self.rtl_loiter_start = 0.0
        self.battery_used_mah = 0.0
        self.events: list[tuple[int, str]] = []
        self.boot = boot
        self._prearm_said = 0.0
        self.spool_until: Optional[float] = None  # take-off accepted, climbing from then

    # ----- boot (BootTimeline)
    @property
    def gps_ok(self) -> bool:
        return self.t >= self.boot.gps_s

    @property
    def origin_set(self) -> bool:
        return self.t >= self.boot.origin_s

    @property
    def position_ok(self) -> bool:
        return self.t >= self.boot.ready_s

    @property
    def prearm_bit(self) -> bool:
        """SYS_STATUS's pre-arm bit: healthy when arming passes, and during the blip."""
        return self.position_ok or self.boot.blip_s[0] <= self.t < self.boot.blip_s[1]

    # ----- helpers
    def text(self, severity: int, msg: str) -> None:
        self.events.append((severity, msg))

    def params_changed(self) -> None:
        self.limits = limits_from_params(self.params, self.pos_noise)

    def ned_from_geodetic(self, lat: float, lon: float, alt_amsl: float) -> Vec3:
        n, e, d = pymap3d.geodetic2ned(lat, lon, alt_amsl, *self.origin)
        return (float(n), float(e), float(d))

    def geodetic_from_ned(self, ned: Vec3) -> tuple[float, float, float]:
        lat, lon, alt = pymap3d.ned2geodetic(ned[0], ned[1], ned[2], *self.origin)
        return (float(lat), float(lon), float(alt))

    def alt_above_home(self) -> float:
        return self.home_ned[2] - self.state.pos[2]

    def landed_state(self) -> int:
        if self.land_complete or self.spool_until is not None:
            return mavlink.MAV_LANDED_STATE_ON_GROUND
        if self.mode == Mode.LAND or (self.mode == Mode.RTL and self.rtl_phase == "land"):
            return mavlink.MAV_LANDED_STATE_LANDING
        if self.takeoff_z is not None:
            return mavlink.MAV_LANDED_STATE_TAKEOFF
        return mavlink.MAV_LANDED_STATE_IN_AIR

    def _stopping_point(self) -> Vec3:
        return multicopter.stopping_point(self.state, self.limits)

    # ----- commands
    def set_mode(self, number: int) -> bool:
        """Copter::set_mode: True if the vehicle is (now) in that mode."""
        try:
            mode = Mode(number)
        except ValueError:
            self.text(mavlink.MAV_SEVERITY_WARNING, "Flight mode change failed")
            return False
        if mode == self.mode:
            return True  # ArduPilot does not re-init the current mode
        if mode not in FLOWN_MODES:
            # AUTO with an empty mission, CIRCLE, ... fail their init() like this.
            self.text(mavlink.MAV_SEVERITY_WARNING, f"Flight mode change failed: {mode.name}")
            return False
        self.mode = mode
        self.state = replace(self.state, xy=None)  # each mode's init restarts the controller
        self.speed = {}
        self.fixed_yaw = None
        self.guided = None
        stop = self._stopping_point()
        if self.takeoff_z is not None and mode not in TAKEOFF_MODES:
            self.takeoff_z = None
        if mode in HOLD_MODES:
            self.hold_pos = stop if self.takeoff_z is None else self.state.pos
        elif mode == Mode.GUIDED:
            # ModeGuided::init: hold at the stopping point until a target arrives.
            self.guided = GuidedTarget("pos", pos=stop, updated_s=self.t)
        elif mode == Mode.LAND:
            self.hold_pos = stop
        elif mode == Mode.RTL:
            self.rtl_phase = "climb"
            rtl_alt = max(self.params["RTL_ALT"] / 100.0, self.alt_above_home())
            self.rtl_z = self.home_ned[2] - rtl_alt
            self.hold_pos = stop
        return True

    def arm(self, force: bool) -> bool:
        if self.armed:
            return True
        if not force and self.mode not in ARMABLE_MODES:
            self.text(mavlink.MAV_SEVERITY_CRITICAL, "Arm: Mode not armable")
            return False
        if not force and not self.position_ok:
            self.text(mavlink.MAV_SEVERITY_CRITICAL, "Arm: Need Position Estimate")
            return False
        self.armed = True
        self.landed_since = self.t
        self.text(mavlink.MAV_SEVERITY_INFO, "Arming motors")
        return True

    def disarm(self, force: bool, reason: str = "") -> bool:
        if not self.armed:
            return True
        self.spool_until = None
        if not force and not self.land_complete:
            # AP_Arming_Copter::disarm refuses a GCS disarm while flying unless forced.
            return False
        self.armed = False
        self.takeoff_z = None
        self.text(mavlink.MAV_SEVERITY_INFO, f"Disarming motors{reason}")
        return True

    def takeoff(self, alt_rel_m: float) -> bool:
        """Mode::do_user_takeoff: armed, landed, a takeoff-capable mode, going up."""
        if not self.armed or not self.land_complete or self.mode not in TAKEOFF_MODES:
            return False
        if not math.isfinite(alt_rel_m) or alt_rel_m <= self.alt_above_home():
            return False
        self.takeoff_z = self.home_ned[2] - alt_rel_m
        self.hold_pos = (self.state.pos[0], self.state.pos[1], self.takeoff_z)
        if self.mode == Mode.GUIDED:
            self.guided = GuidedTarget("pos", pos=self.hold_pos, updated_s=self.t)
        if self.spool_until is None:  # a repeat during the spool-up is accepted, changes nothing
            self.spool_until = self.t + TAKEOFF_SPOOL_S
        return True

    def guided_hold(self) -> None:
        """ModeGuided::init(true): a rejected target makes the vehicle stop and hold."""
        self.guided = GuidedTarget("pos", pos=self._stopping_point(), updated_s=self.t)
        self.takeoff_z = None

    def set_guided(self, target: GuidedTarget) -> None:
        if self.guided is None or self.guided.kind != target.kind:
            self.state = replace(self.state, xy=None)  # a new sub-mode restarts the controller
        self.guided = replace(target, updated_s=self.t)
        self.takeoff_z = None

    def set_home(self, lla: Optional[tuple[float, float, float]]) -> None:
        """MAV_CMD_DO_SET_HOME: a location, or None for the current position."""
        self.home = lla if lla is not None else self.geodetic_from_ned(self.state.pos)
        self.home_ned = self.ned_from_geodetic(*self.home)

    # ----- simulation
    def tick(self, dt: float) -> None:
        self.t += dt
        if not self.armed and not self.position_ok and self.t >= self._prearm_said + 30.0:
            self._prearm_said = self.t  # ArduPilot reports failing pre-arm checks every 30 s
            self.text(mavlink.MAV_SEVERITY_CRITICAL, "PreArm: Need Position Estimate")
        current_a = 0.3
        if not self.armed:
            if self.state.pos[2] < -0.01 or any(self.state.vel):
                self.state = multicopter.fall(self.state, dt, self._ground_z())
            if self.state.pos[2] >= self._ground_z() - 0.01 and not self.land_complete:
                self.land_complete = True
                self.landed_since = self.t
        elif self.spool_until is not None:  # take-off accepted: motors spooling, still landed
            current_a = 5.0
            if self.t >= self.spool_until:
                self.spool_until = None
                self.land_complete = False
        elif self.land_complete and self.takeoff_z is None:
            current_a = 2.0  # spinning at idle on the ground
            delay = self.params["DISARM_DELAY"]
            if delay > 0 and self.t - self.landed_since >= delay:
                self.disarm(True, reason=" (auto disarm)")
        else:
            current_a = 15.0
            sp = self._setpoint(dt)
            self.state = multicopter.on_ground(
                multicopter.step(self.state, sp, dt, self.limits, self.rng), self._ground_z()
            )
            self._update_takeoff_and_landing(sp)
        self.battery_used_mah += current_a * dt / 3.6

    def _ground_z(self) -> float:
        return 0.0  # flat ground at the altitude of the origin (home at boot)

    def _setpoint(self, dt: float) -> Setpoint:
        speeds = dict(
            speed_xy=self.speed.get("xy"), speed_up=self.speed.get("up"),
            speed_down=self.speed.get("down"),
        )
        if self.mode == Mode.GUIDED and self.guided is not None and self.takeoff_z is None:
            return self._guided_setpoint(dt, speeds)
        if self.mode == Mode.LAND:
            return Setpoint(pos=(self.hold_pos[0], self.hold_pos[1], self._ground_z() + 1.0),
                            speed_down=self._descent_speed(), speed_xy=speeds["speed_xy"])
        if self.mode == Mode.RTL:
            return self._rtl_setpoint()
        # Hold modes, and any takeoff in progress.
        pos = self.hold_pos
        if self.takeoff_z is not None:
            pos = (self.hold_pos[0], self.hold_pos[1], self.takeoff_z)
        return Setpoint(pos=pos, yaw=self.fixed_yaw, speed_up=self._takeoff_speed(), **{
            k: v for k, v in speeds.items() if k != "speed_up"})

    def _takeoff_speed(self) -> Optional[float]:
        if self.takeoff_z is None or self.mode == Mode.GUIDED:
            return self.speed.get("up")  # GUIDED takes off with wp_nav: WPNAV_SPEED_UP
        # _TakeOff::start: min(WPNAV_SPEED_UP, max(2/3 PILOT_SPEED_UP, PILOT_SPEED_UP - 50))
        pilot = self.params["PILOT_SPEED_UP"]
        return min(self.limits.speed_up, max(pilot * 2 / 3, pilot - 50) / 100.0)

    def _descent_speed(self) -> float:
        high = self.params["LAND_SPEED_HIGH"] / 100.0 or self.limits.speed_down
        if self.alt_above_home() > self.params["LAND_ALT_LOW"] / 100.0:
            return high
        return max(self.params["LAND_SPEED"], 30.0) / 100.0

    def _guided_setpoint(self, dt: float, speeds: dict) -> Setpoint:
        g = self.guided
        assert g is not None
        timed_out = self.t - g.updated_s > self.params["GUID_TIMEOUT"]
        yaw = g.yaw if g.yaw is not None else self.fixed_yaw
        yaw_rate = g.yaw_rate
        if g.kind == "pos":
            if yaw is None and yaw_rate is None:
                dn, de = g.pos[0] - self.state.pos[0], g.pos[1] - self.state.pos[1]
                if math.hypot(dn, de) > 2.0:  # WP_YAW_BEHAVIOR: face the destination
                    yaw = math.atan2(de, dn)
            return Setpoint(pos=g.pos, yaw=yaw, yaw_rate=yaw_rate, **speeds)
        if g.kind == "posvel":
            vel = (0.0, 0.0, 0.0) if timed_out else g.vel
            acc = None if timed_out else g.acc
            # The firmware moves the target on between messages (input_pos_vel_accel_xy).
            pos, moved = multicopter.advance_input(g.pos, vel, acc, dt)
            self.guided = replace(g, pos=pos, vel=g.vel if timed_out else moved)
            return Setpoint(pos=g.pos, vel=vel, acc=acc, yaw=yaw, yaw_rate=yaw_rate, **speeds)
        if g.kind == "vel":
            vel = (0.0, 0.0, 0.0) if timed_out else g.vel
            acc = None if timed_out else g.acc
            if yaw is None and yaw_rate is None and math.hypot(vel[0], vel[1]) > 1.0:
                yaw = math.atan2(vel[1], vel[0])
            return Setpoint(vel=vel, acc=acc, yaw=yaw, yaw_rate=yaw_rate, **speeds)
        acc = (0.0, 0.0, 0.0) if timed_out else g.acc
        return Setpoint(acc=acc, yaw=yaw, yaw_rate=yaw_rate, **speeds)

    def _rtl_setpoint(self) -> Setpoint:
        home = self.home_ned
        s = self.state
        if self.rtl_phase == "climb":
            if s.pos[2] - self.rtl_z < 0.5:
                self.rtl_phase = "return"
            return Setpoint(pos=(self.hold_pos[0], self.hold_pos[1], self.rtl_z))
        if self.rtl_phase == "return":
            target = (home[0], home[1], self.rtl_z)
            if math.dist(s.pos, target) < 1.0 and math.hypot(s.vel[0], s.vel[1]) < 0.5:
                self.rtl_phase = "loiter"
                self.rtl_loiter_start = self.t
            speed = self.params["RTL_SPEED"] / 100.0 or None
            return Setpoint(pos=target, speed_xy=speed,
                            yaw=math.atan2(home[1] - s.pos[1], home[0] - s.pos[0])
                            if math.hypot(home[0] - s.pos[0], home[1] - s.pos[1]) > 2 else None)
        if self.rtl_phase == "loiter":
            if self.t - self.rtl_loiter_start >= self.params["RTL_LOIT_TIME"] / 1000.0:
                self.rtl_phase = "land"
            return Setpoint(pos=(home[0], home[1], self.rtl_z))
        return Setpoint(pos=(home[0], home[1], self._ground_z() + 1.0),
                        speed_down=self._descent_speed())

    def _update_takeoff_and_landing(self, sp: Setpoint) -> None:
        s = self.state
        if self.takeoff_z is not None and abs(s.pos[2] - self.takeoff_z) < 0.2:
            self.takeoff_z = None  # takeoff complete: keep holding there
            self.text(mavlink.MAV_SEVERITY_INFO, "Takeoff complete")
        if self.takeoff_z is not None:
            return
        on_ground = s.pos[2] >= self._ground_z() - 0.01
        wants_down = (
            (sp.pos is not None and sp.pos[2] >= self._ground_z() - 0.1)
            or (sp.pos is None and sp.vel is not None and sp.vel[2] >= 0.0)
            or (sp.pos is None and sp.vel is None)
        )
        if on_ground and wants_down and not self.land_complete:
            self.land_complete = True
            self.landed_since = self.t
            self.state = replace(s, vel=(0.0, 0.0, 0.0), acc=(0.0, 0.0, 0.0))
            self.text(mavlink.MAV_SEVERITY_INFO, "Landed")
            if self.mode in (Mode.LAND, Mode.RTL):
                self.disarm(True)
