"""The mock autopilot's outgoing messages: its streams (rates per link), and every message it
builds from the copter's state, as ArduCopter fills them, and the requests that set them
(REQUEST_DATA_STREAM, TIMESYNC, AUTOPILOT_VERSION); each iteration, the EKF origin once it is
set, the copter's STATUSTEXTs and the streams due. A part of ``MockAutopilot``
(sim/mock/context.py)."""
from __future__ import annotations

import math
from typing import Callable, Mapping, Optional


from onboard.app.mavlink2 import mavlink
from sim.mock import multicopter

from sim.mock.context import Handler, MockContext, Part
from sim.mock.copter import FIRMWARE, FW_VERSION, Mode
from sim.mock.links import _Link


# --------------------------------------------------------------------------- telemetry

# type_mask bits (POSITION_TARGET_TYPEMASK_*): of the targets reported and of those set
# (sim/mock/commands.py)
_POS_IGNORE = 0b111
_VEL_IGNORE = 0b111 << 3
_ACC_IGNORE = 0b111 << 6
_FORCE_SET = 1 << 9
_YAW_IGNORE = 1 << 10
_YAW_RATE_IGNORE = 1 << 11

# Sent on every link whatever its SRn_ rates (ArduPilot's GCS_MAVLINK heartbeat): interval, sim s
ALWAYS_INTERVALS_S: Mapping[str, float] = {"HEARTBEAT": 1.0}

# REQUEST_DATA_STREAM / SRn_ groups (ArduCopter's STREAM_* lists, restricted to what we send;
# measured on 4.4 SITL: EXTENDED_SYS_STATE is in none, it comes only when asked for).
DATA_STREAMS: Mapping[int, tuple[str, ...]] = {
    mavlink.MAV_DATA_STREAM_EXTENDED_STATUS: ("SYS_STATUS", "GPS_RAW_INT", "POSITION_TARGET_GLOBAL_INT"),
    mavlink.MAV_DATA_STREAM_POSITION: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),
    mavlink.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    mavlink.MAV_DATA_STREAM_EXTRA2: ("VFR_HUD",),
    mavlink.MAV_DATA_STREAM_EXTRA3: ("SYSTEM_TIME", "BATTERY_STATUS", "EKF_STATUS_REPORT"),
}
SR_GROUPS = {"EXT_STAT": mavlink.MAV_DATA_STREAM_EXTENDED_STATUS, "POSITION": mavlink.MAV_DATA_STREAM_POSITION,
             "EXTRA1": mavlink.MAV_DATA_STREAM_EXTRA1, "EXTRA2": mavlink.MAV_DATA_STREAM_EXTRA2,
             "EXTRA3": mavlink.MAV_DATA_STREAM_EXTRA3}

SENSORS = (
    mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG | mavlink.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mavlink.MAV_SYS_STATUS_SENSOR_GPS | mavlink.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mavlink.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | mavlink.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS | mavlink.MAV_SYS_STATUS_SENSOR_RC_RECEIVER
    | mavlink.MAV_SYS_STATUS_AHRS | mavlink.MAV_SYS_STATUS_SENSOR_BATTERY
    | mavlink.MAV_SYS_STATUS_LOGGING | mavlink.MAV_SYS_STATUS_PREARM_CHECK
)

CAPABILITIES = (
    mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
    | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | mavlink.MAV_PROTOCOL_CAPABILITY_FLIGHT_TERMINATION
    | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
    | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
)  # no FTP: clients then fetch parameters with PARAM_REQUEST_LIST



class Telemetry(Part):
    """``builders``: every message the mock can send as a stream or on request, by name;
    ``unix_time0``: UNIX time (s) at boot, for SYSTEM_TIME (set by the mock when it starts)."""

    def __init__(self, ctx: MockContext, unix_time0: Optional[float] = None):
        super().__init__(ctx)
        self.unix_time0 = unix_time0
        self.origin_sent = False
        self.builders: dict[str, Callable[[_Link], Optional[object]]] = {
            "HEARTBEAT": self._heartbeat,
            "SYS_STATUS": self._sys_status,
            "GPS_RAW_INT": self._gps_raw_int,
            "EXTENDED_SYS_STATE": self._extended_sys_state,
            "GLOBAL_POSITION_INT": self._global_position_int,
            "LOCAL_POSITION_NED": self._local_position_ned,
            "ATTITUDE": self._attitude,
            "VFR_HUD": self._vfr_hud,
            "SYSTEM_TIME": self._system_time,
            "BATTERY_STATUS": self._battery_status,
            "EKF_STATUS_REPORT": self._ekf_status_report,
            "HOME_POSITION": self.home_position,
            "GPS_GLOBAL_ORIGIN": self.gps_global_origin,
            "AUTOPILOT_VERSION": self.autopilot_version,
            "POSITION_TARGET_LOCAL_NED": self._position_target_local_ned,
            "POSITION_TARGET_GLOBAL_INT": self._position_target_global_int,
        }

    def handlers(self) -> Mapping[str, Handler]:
        return {"TIMESYNC": self._on_timesync,
                "AUTOPILOT_VERSION_REQUEST": self._on_autopilot_version_request,
                "REQUEST_DATA_STREAM": self._on_request_data_stream}

    def periodic(self, now: float) -> None:
        ctx = self.ctx
        if not self.origin_sent and ctx.copter.origin_set:
            self.origin_sent = True  # ArduPilot tells every link when its EKF origin is set
            ctx.copter.text(mavlink.MAV_SEVERITY_INFO, "EKF3 IMU0 origin set")
            for lk in ctx.links:
                lk.send(self.gps_global_origin(lk))
                lk.send(self.home_position(lk))
        for severity, text in ctx.copter.events:
            ctx.broadcast(ctx.enc.statustext_encode(severity, text.encode()[:50]))
        ctx.copter.events.clear()
        self._send_streams(now)

    def default_intervals(self, port: int) -> dict[str, float]:
        """Stream intervals (sim s) of a new link on endpoint ``port``: a HEARTBEAT a second,
        and the groups its SRn_ parameters turn on (ArduPilot's stream rates per serial port)."""
        out = dict(ALWAYS_INTERVALS_S)
        params = self.ctx.params
        for group, stream in SR_GROUPS.items():
            name = f"SR{port}_{group}"
            hz = params[name] if name in params else 0.0
            for msg in DATA_STREAMS[stream]:
                if hz > 0:
                    out[msg] = 1.0 / hz
        return out

    def set_interval(self, link: _Link, name: str, interval_s: float) -> None:
        link.intervals[name] = interval_s
        link.next_due[name] = self.ctx.copter.t  # start the new rate now

    def _send_streams(self, now: float) -> None:
        for link in self.ctx.links:
            for name, interval in link.intervals.items():
                if interval <= 0.0:
                    continue
                due = link.next_due.get(name, 0.0)
                if now + 1e-9 < due:
                    continue
                due += interval
                link.next_due[name] = due if due > now else now + interval
                builder = self.builders.get(name)
                msg = builder(link) if builder is not None else None
                if msg is not None:
                    link.send(msg)
                    self.ctx.count("tx")

    def _time_ms(self) -> int:
        return int(self.ctx.copter.t * 1000) & 0xFFFFFFFF

    def _base_mode(self) -> int:
        c = self.ctx.copter
        base = (mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
                | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED)
        if c.mode not in (Mode.STABILIZE, Mode.ALT_HOLD):
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED  # position control active
        if c.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        return base

    def _heartbeat(self, link: _Link):
        c = self.ctx.copter
        status = mavlink.MAV_STATE_STANDBY if c.land_complete else mavlink.MAV_STATE_ACTIVE
        return self.ctx.enc.heartbeat_encode(
            mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, self._base_mode(),
            int(c.mode), status)

    def _battery(self) -> tuple[int, int, int]:
        """(voltage mV, current cA, remaining %) of a 3S pack."""
        cap = max(self.ctx.params["BATT_CAPACITY"], 1.0)
        remaining = max(0.0, 1.0 - self.ctx.copter.battery_used_mah / cap)
        volts = 10.5 + 2.1 * remaining
        current = 15.0 if self.ctx.copter.armed and not self.ctx.copter.land_complete else 0.3
        return int(volts * 1000), int(current * 100), int(round(remaining * 100))

    def _sys_status(self, link: _Link):
        mv, ca, pct = self._battery()
        # GEOFENCE is reported healthy while not breached even with no fence (as ArduPilot);
        # the pre-arm bit only once arming would pass
        health = SENSORS | mavlink.MAV_SYS_STATUS_GEOFENCE
        if not self.ctx.copter.prearm_bit:
            health &= ~mavlink.MAV_SYS_STATUS_PREARM_CHECK
        return self.ctx.enc.sys_status_encode(SENSORS, SENSORS, health, 150, mv, ca, pct,
                                             0, 0, 0, 0, 0, 0)

    def _battery_status(self, link: _Link):
        mv, ca, pct = self._battery()
        voltages = [mv] + [65535] * 9
        return self.ctx.enc.battery_status_encode(
            0, mavlink.MAV_BATTERY_FUNCTION_ALL, mavlink.MAV_BATTERY_TYPE_LIPO, 32767, voltages,
            ca, int(self.ctx.copter.battery_used_mah), -1, pct)

    def _geo(self) -> tuple[float, float, float]:
        return self.ctx.copter.geodetic_from_ned(self.ctx.copter.state.pos)

    def _gps_raw_int(self, link: _Link):
        lat, lon, alt = self._geo()
        v = self.ctx.copter.state.vel
        gs = math.hypot(v[0], v[1])
        cog = int(math.degrees(math.atan2(v[1], v[0])) % 360 * 100) if gs > 0.2 else 65535
        fix = mavlink.GPS_FIX_TYPE_3D_FIX if self.ctx.copter.gps_ok else mavlink.GPS_FIX_TYPE_NO_GPS
        if not self.ctx.copter.gps_ok:
            lat = lon = 0.0
        return self.ctx.enc.gps_raw_int_encode(
            int(self.ctx.copter.t * 1e6), fix, int(lat * 1e7), int(lon * 1e7),
            int(alt * 1000), 121, 200, int(gs * 100), cog, 10, int(alt * 1000), 300, 500, 40, 0)

    def _extended_sys_state(self, link: _Link):
        return self.ctx.enc.extended_sys_state_encode(
            mavlink.MAV_VTOL_STATE_UNDEFINED, self.ctx.copter.landed_state())

    def _global_position_int(self, link: _Link):
        lat, lon, alt = self._geo() if self.ctx.copter.gps_ok else (0.0, 0.0, self._geo()[2])
        s = self.ctx.copter.state
        hdg = int(math.degrees(s.yaw) % 360 * 100) % 36000
        return self.ctx.enc.global_position_int_encode(
            self._time_ms(), int(lat * 1e7), int(lon * 1e7), int(alt * 1000),
            int(self.ctx.copter.alt_above_home() * 1000), int(s.vel[0] * 100), int(s.vel[1] * 100),
            int(s.vel[2] * 100), hdg)

    def _local_position_ned(self, link: _Link):
        if not self.ctx.copter.position_ok:
            return None  # no position estimate relative to an origin yet
        s = self.ctx.copter.state
        return self.ctx.enc.local_position_ned_encode(self._time_ms(), *s.pos, *s.vel)

    def _attitude(self, link: _Link):
        roll, pitch, yaw = multicopter.attitude(self.ctx.copter.state)
        return self.ctx.enc.attitude_encode(self._time_ms(), roll, pitch, yaw, 0.0, 0.0, 0.0)

    def _vfr_hud(self, link: _Link):
        s = self.ctx.copter.state
        gs = math.hypot(s.vel[0], s.vel[1])
        throttle = 0 if not self.ctx.copter.armed else (15 if self.ctx.copter.land_complete else 50)
        return self.ctx.enc.vfr_hud_encode(gs, gs, int(math.degrees(s.yaw) % 360), throttle,
                                          self._geo()[2], -s.vel[2])

    def _system_time(self, link: _Link):
        unix_us = int(((self.unix_time0 or 0.0) + self.ctx.copter.t) * 1e6)
        return self.ctx.enc.system_time_encode(unix_us, self._time_ms())

    def _ekf_status_report(self, link: _Link):
        flags = mavlink.EKF_ATTITUDE | mavlink.EKF_VELOCITY_VERT | mavlink.EKF_POS_VERT_ABS
        if self.ctx.copter.position_ok:
            flags |= (mavlink.EKF_VELOCITY_HORIZ | mavlink.EKF_POS_HORIZ_REL | mavlink.EKF_POS_HORIZ_ABS
                      | mavlink.EKF_PRED_POS_HORIZ_REL | mavlink.EKF_PRED_POS_HORIZ_ABS)
        return self.ctx.enc.ekf_status_report_encode(flags, 0.02, 0.02, 0.02, 0.01, 0.0)

    def home_position(self, link: _Link):
        if not self.ctx.copter.origin_set:
            return None  # no home yet: a request is accepted and answered by nothing
        lat, lon, alt = self.ctx.copter.home
        x, y, z = self.ctx.copter.home_ned
        return self.ctx.enc.home_position_encode(
            int(lat * 1e7), int(lon * 1e7), int(alt * 1000), x, y, z, [1.0, 0.0, 0.0, 0.0],
            0.0, 0.0, 0.0, int(self.ctx.copter.t * 1e6))

    def gps_global_origin(self, link: _Link):
        if not self.ctx.copter.origin_set:
            return None
        lat, lon, alt = self.ctx.copter.origin
        return self.ctx.enc.gps_global_origin_encode(
            int(lat * 1e7), int(lon * 1e7), int(alt * 1000), int(self.ctx.copter.t * 1e6))

    def autopilot_version(self, link: _Link):
        return self.ctx.enc.autopilot_version_encode(
            CAPABILITIES, FW_VERSION, 0, 0, 0, [0x70, 0x6d, 0x6f, 0x6e, 0, 0, 0, 0],
            [0] * 8, [0] * 8, 0, 0, 0)

    def _position_target_local_ned(self, link: _Link):
        g = self.ctx.copter.guided
        if self.ctx.copter.mode != Mode.GUIDED or g is None or g.pos is None:
            return None
        mask = _VEL_IGNORE | _ACC_IGNORE | _YAW_IGNORE | _YAW_RATE_IGNORE
        return self.ctx.enc.position_target_local_ned_encode(
            self._time_ms(), mavlink.MAV_FRAME_LOCAL_NED, mask, *g.pos, 0, 0, 0, 0, 0, 0, 0, 0)

    def _position_target_global_int(self, link: _Link):
        g = self.ctx.copter.guided
        if self.ctx.copter.mode != Mode.GUIDED or g is None or g.pos is None:
            return None
        lat, lon, alt = self.ctx.copter.geodetic_from_ned(g.pos)
        mask = _VEL_IGNORE | _ACC_IGNORE | _YAW_IGNORE | _YAW_RATE_IGNORE
        return self.ctx.enc.position_target_global_int_encode(
            self._time_ms(), mavlink.MAV_FRAME_GLOBAL, mask, int(lat * 1e7), int(lon * 1e7), alt,
            0, 0, 0, 0, 0, 0, 0, 0)

    def banner(self, link: _Link) -> None:
        for text in (FIRMWARE, "Frame: QUAD/X"):
            link.send(self.ctx.enc.statustext_encode(mavlink.MAV_SEVERITY_INFO, text.encode()))

    # ----- requests
    def _on_timesync(self, link: _Link, msg) -> None:
        if msg.tc1 == 0:  # a request: answer with our clock (ns since boot)
            link.send(self.ctx.enc.timesync_encode(
                int(self.ctx.copter.t * 1e9), msg.ts1, msg.get_srcSystem(), msg.get_srcComponent()))

    def _on_autopilot_version_request(self, link: _Link, msg) -> None:
        link.send(self.autopilot_version(link))

    def _on_request_data_stream(self, link: _Link, msg) -> None:
        hz = msg.req_message_rate if msg.start_stop else 0
        ids = list(DATA_STREAMS) if msg.req_stream_id == mavlink.MAV_DATA_STREAM_ALL else [
            msg.req_stream_id]
        for sid in ids:
            for name in DATA_STREAMS.get(sid, ()):
                self.set_interval(link, name, 1.0 / hz if hz > 0 else 0.0)
