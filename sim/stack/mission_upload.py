"""A waypoint mission uploaded to an autopilot the way a ground station does it (MAVLink's
mission protocol: MISSION_COUNT, the autopilot asks each item by MISSION_REQUEST_INT, answers
MISSION_ACK), on a connection of its own: for flights an autopilot flies by itself in AUTO
while the app advises (tests/firmware/test_ardupilot_advisory.py, examples/advise_mission.py)."""
from __future__ import annotations

import time

from onboard.app.mavlink2 import mavutil
from onboard.app.mavlink_connection import mavlink

UPLOAD_SYSID = 253  # neither the operator's GCS (255), the feed (245) nor the observer (250)


def upload(url: str, waypoints: list[tuple[float, float, float]], timeout_s: float = 20.0,
           target: tuple[int, int] = (1, 1)) -> str:
    """Upload ``waypoints`` (latitude, longitude in degrees, altitude above home in m) as
    NAV_WAYPOINT items after the home item ArduPilot keeps at 0; the MISSION_ACK's result name
    (``MAV_MISSION_ACCEPTED`` on success). Raises TimeoutError when the autopilot stops asking."""
    conn = mavutil.mavlink_connection(url, source_system=UPLOAD_SYSID, source_component=190,
                                      dialect="ardupilotmega")
    try:
        if conn.wait_heartbeat(timeout=timeout_s) is None:
            raise TimeoutError(f"mission upload: no heartbeat on {url} in {timeout_s:g} s")
        items = [waypoints[0][:2] + (0.0,)] + list(waypoints)  # 0: home (the autopilot's own)
        ts, tc = target
        conn.mav.mission_count_send(ts, tc, len(items), mavlink.MAV_MISSION_TYPE_MISSION)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            m = conn.recv_match(type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], blocking=True,
                                timeout=0.5)
            if m is None or m.get_srcSystem() != ts:
                continue
            if m.get_type() == "MISSION_ACK":
                return mavlink.enums["MAV_MISSION_RESULT"][m.type].name
            lat, lon, alt = items[m.seq]
            conn.mav.mission_item_int_send(ts, tc, m.seq, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                                           mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0,
                                           round(lat * 1e7), round(lon * 1e7), alt, mavlink.MAV_MISSION_TYPE_MISSION)
        raise TimeoutError(f"mission upload: no MISSION_ACK in {timeout_s:g} s")
    finally:
        conn.close()
