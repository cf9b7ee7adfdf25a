"""A lawnmower flown by a real firmware's SITL, for ``pmon locate``'s firmware-log tests and bench:
the flight a pilot (or a ground station's survey) would fly, its log the firmware's own.

* ArduCopter (sim/firmware/ardupilot.py): GUIDED, arm, take off, then each corner of the lawnmower as a
  SET_POSITION_TARGET_GLOBAL_INT (position only: the copter flies to it and brakes), LAND; the
  firmware writes its DataFlash log (``logs/*.BIN`` in its working directory, LOG_BACKEND_TYPE 1,
  logging while armed: LOG_DISARMED 0) with POS, ATT and GPS (its week and ms: UTC).
* PX4 (sim/firmware/px4.py, SIH): arm in Hold, take off, each corner as MAV_CMD_DO_REPOSITION, land; it
  logs a ULog from boot to the first disarm (SDLOG_MODE 1) under ``log/`` in its working directory.

The corners are sim/stack/locate_recording.py's (``RecordingConfig.box_m``, ``spacing_m``) in the
mission frame at its ``ORIGIN``, the SITL's home.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from onboard.app.mavlink2 import mavlink, mavutil
from onboard.app.autopilot.pose import Frame
from sim.stack import locate_recording as rec

ALT_M = 40.0
REACH_M = 4.0  # within this of a corner (horizontal) counts as there


def corners(cfg: rec.RecordingConfig = rec.RecordingConfig()) -> list[tuple[float, float]]:
    x0, y0, x1, y1 = cfg.box_m
    out = []
    for k, y in enumerate(np.arange(y0, y1 + 1e-9, cfg.spacing_m)):
        out += [(x0, float(y)), (x1, float(y))] if k % 2 == 0 else [(x1, float(y)), (x0, float(y))]
    return out


class Link:
    """A pymavlink connection to one autopilot with the last position it reported."""

    def __init__(self, url: str, wall_timeout_s: float):
        self.conn = mavutil.mavlink_connection(url, source_system=245, source_component=190)
        self.deadline = time.monotonic() + wall_timeout_s
        self.frame = Frame(*rec.ORIGIN)
        self.enu = None
        self.armed = False
        self.mode = None  # HEARTBEAT.custom_mode
        self.target = (1, 1)

    def pump(self, seconds: float = 0.2):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if time.monotonic() > self.deadline:
                raise TimeoutError("the firmware's flight took longer than its wall-time budget")
            m = self.conn.recv_match(blocking=True, timeout=0.05)
            if m is None:
                continue
            kind = m.get_type()
            if kind == "HEARTBEAT" and m.get_srcComponent() == 1:
                self.target = (m.get_srcSystem(), 1)
                self.armed = bool(m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                self.mode = m.custom_mode
            elif kind == "GLOBAL_POSITION_INT" and (m.lat or m.lon):
                self.enu = self.frame.enu_from_geodetic(m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3)

    def command(self, cmd: int, *params: float) -> None:
        p = list(params) + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(*self.target, cmd, 0, *p)

    def until(self, cond, what: str, resend=None, every_s: float = 1.0) -> None:
        while not cond():
            if resend is not None:
                resend()
            try:
                self.pump(every_s)
            except TimeoutError:
                raise TimeoutError(f"waiting for {what}") from None

    def interval(self, msg_id: int, hz: float) -> None:
        self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)

    def near(self, e: float, n: float) -> bool:
        return self.enu is not None and math.hypot(self.enu[0] - e, self.enu[1] - n) < REACH_M

    def geodetic(self, e: float, n: float) -> tuple[int, int, float]:
        lat, lon, alt = self.frame.geodetic_from_enu([e, n, ALT_M])
        return int(round(lat * 1e7)), int(round(lon * 1e7)), alt


def _ardupilot_goto(link: Link, e: float, n: float) -> None:
    lat, lon, alt = link.geodetic(e, n)
    link.conn.mav.set_position_target_global_int_send(0, *link.target, mavlink.MAV_FRAME_GLOBAL_INT, 0b110111111000,
                                                      lat, lon, alt, 0, 0, 0, 0, 0, 0, 0, 0)


def _px4_goto(link: Link, e: float, n: float) -> None:
    lat, lon, alt = link.geodetic(e, n)
    link.conn.mav.command_int_send(*link.target, mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_CMD_DO_REPOSITION, 0, 0,
                                   -1, mavlink.MAV_DO_REPOSITION_FLAGS_CHANGE_MODE, 0, math.nan, lat, lon, alt)


def _survey(link: Link, goto, cfg: rec.RecordingConfig) -> None:
    for e, n in corners(cfg):
        link.until(lambda: link.near(e, n), f"the corner ({e:.0f}, {n:.0f})", lambda: goto(link, e, n), 2.0)


def fly_ardupilot(workdir: Path, speedup: float = 5.0, wall_timeout_s: float = 400.0,
                  cfg: rec.RecordingConfig = rec.RecordingConfig()) -> Path:
    """The lawnmower of ``cfg`` on ArduCopter's SITL; the DataFlash log it wrote."""
    from sim.firmware.ardupilot import ArduPilotSitl, find_binary

    params = {"LOG_BACKEND_TYPE": 1, "LOG_DISARMED": 0, "WPNAV_SPEED": 600}
    with ArduPilotSitl(find_binary(), home=(*rec.ORIGIN, 0.0), speedup=speedup, params=params,
                       workdir=Path(workdir)) as sitl:
        link = Link(sitl.url(0), wall_timeout_s)
        link.until(lambda: link.target is not None and link.conn.target_system, "a heartbeat")
        for msg in (mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, mavlink.MAVLINK_MSG_ID_HEARTBEAT):
            link.interval(msg, 4.0)
        link.until(lambda: link.enu is not None, "a position", lambda: link.interval(
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 4.0))
        guided = lambda: link.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 4)  # noqa: E731
        link.until(lambda: link.mode == 4, "GUIDED", guided, 1.0)

        def arm_and_take_off():  # refused until the EKF and GPS are ready; auto-disarmed if not off soon
            if not link.armed:
                link.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
                link.pump(0.5)
            link.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, ALT_M)
        link.until(lambda: link.enu[2] > ALT_M - 2.0, "the take-off", arm_and_take_off, 2.0)
        _survey(link, _ardupilot_goto, cfg)
        link.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 9)  # LAND
        link.until(lambda: not link.armed, "landing and disarming")
        link.conn.close()
    logs = sorted((Path(workdir) / "logs").glob("*.BIN"))
    if not logs:
        raise RuntimeError(f"{workdir}/logs: no DataFlash log written")
    return max(logs, key=lambda p: p.stat().st_size)


def fly_px4(workdir: Path, speed: float = 4.0, wall_timeout_s: float = 400.0,
            cfg: rec.RecordingConfig = rec.RecordingConfig()) -> Path:
    """The lawnmower of ``cfg`` on PX4's SIH SITL; the ULog it wrote."""
    from sim.firmware.px4 import Px4Sitl, find_sitl

    with Px4Sitl(find_sitl(), home=rec.ORIGIN, speed=speed, workdir=Path(workdir)) as sitl:
        link = Link(sitl.url("api"), wall_timeout_s)
        link.until(lambda: link.enu is not None, "a position", lambda: link.conn.mav.heartbeat_send(
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
        link.until(lambda: link.armed, "arming", lambda: link.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1), 1.0)
        link.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, rec.ORIGIN[2] + ALT_M)
        link.until(lambda: link.enu[2] > ALT_M - 3.0, "the take-off")
        _survey(link, _px4_goto, cfg)
        link.command(mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        link.until(lambda: not link.armed, "landing and disarming")
        link.conn.close()
        logs = sitl.ulogs()
    if not logs:
        raise RuntimeError(f"{workdir}: no ULog written")
    return max(logs, key=lambda p: p.stat().st_size)


SHORT = rec.RecordingConfig(box_m=(220.0, 100.0, 640.0, 200.0))  # the three northern legs, 300-525 m away


def main(argv=None) -> int:
    """``python -m sim.stack.lawnmower ardupilot|px4 DIR [--short] [--speed X]``: fly it (the
    whole lawnmower, or ``SHORT``: its three northern legs, 300-525 m from the emitters; ``--speed``:
    ArduPilot's speedup, default 5, or PX4's speed factor, default 4), print the log's path."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m sim.stack.lawnmower",
                                 description="Fly the lawnmower on a firmware's SITL; print its log's path.")
    ap.add_argument("firmware", choices=("ardupilot", "px4"))
    ap.add_argument("dir", type=Path)
    ap.add_argument("--short", action="store_true", help="only the three northern legs")
    ap.add_argument("--speed", type=float, help="simulated s per wall s")
    args = ap.parse_args(argv)
    cfg = SHORT if args.short else rec.RecordingConfig()
    if args.firmware == "ardupilot":
        print(fly_ardupilot(args.dir, args.speed or 5.0, cfg=cfg))
    else:
        print(fly_px4(args.dir, args.speed or 4.0, cfg=cfg))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
