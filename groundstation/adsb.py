"""Target estimates as ADSB_VEHICLE: the one MAVLink message QGroundControl, Mission Planner
and MAVProxy draw as traffic on their maps (docs/OPERATING.md, "Targets on your own ground
station"). Sent by ``pmon gcs hub`` to its ground-station clients only, never to the vehicle:
an autopilot with ADS-B avoidance enabled takes ADSB_VEHICLE as traffic to avoid
(measured on ArduCopter and PX4 SITL, docs/OPERATING.md).

What the tools do with it (their source): QGroundControl (ADSBVehicleManager) keeps one entry
per ICAO address, creates it only with ADSB_FLAGS_VALID_COORDS, ignores a message whose
``tslc`` exceeds 15 s, and removes an entry 120 s after its last update; it hands the message
on only when it comes from the vehicle's system id (Vehicle::_mavlinkMessageReceived).
MAVProxy's adsb module passes on only messages from its target system, keys by ICAO
address, removes an entry 5 s (its ``timeout`` setting) after the last, and draws a message
with ``emitter_type`` 255 as a circle of radius ``squawk`` cm without an icon (ArduPilot's
obstacle database, callsign "OA_DB"); Mission Planner takes ADSB_VEHICLE from any system.

Hence: messages from the vehicle's system id and component MAV_COMP_ID_ADSB (156, an ADS-B
receiver: what the hub is standing in for), an address per target in a block no aircraft is
given (below), callsign ``PMON-T1``..., ``tslc`` the estimate's age, and, optionally, the
1-sigma circle as an OA_DB item of its own address.

Addresses: ICAO Annex 10 Vol. III, Appendix to Chapter 9 allocates the 24-bit aircraft
addresses to States in blocks; the lowest block is 0x004000 (Zimbabwe), so 0x000001-0x003FFF
belongs to no State and no certified transponder sends it. Targets use 0x002000 + 16 sysid +
j (circles 0x003000 + 16 sysid + j), 16 targets per vehicle; ArduPilot's own OA_DB items use
their index (below 0x002000 unless OA_DB_SIZE > 8192), so the two never collide.
"""
from __future__ import annotations

import math

from groundstation.estimates import MAX_TARGETS, OutputEstimate
from onboard.app.mavlink_connection import mavlink

COMPONENT = mavlink.MAV_COMP_ID_ADSB  # 156
MARKER_BASE = 0x002000
CIRCLE_BASE = 0x003000
BLOCK_END = 0x004000  # first allocated address (ICAO Annex 10 Vol. III)
EMITTER = mavlink.ADSB_EMITTER_TYPE_SERVICE_SURFACE  # the surface-vehicle category that is no emergency
OA_DB_EMITTER = 255  # ArduPilot's obstacle database item: a circle of radius squawk cm
MARKER_FLAGS = (mavlink.ADSB_FLAGS_VALID_COORDS | mavlink.ADSB_FLAGS_VALID_ALTITUDE
                | mavlink.ADSB_FLAGS_VALID_HEADING | mavlink.ADSB_FLAGS_VALID_VELOCITY
                | mavlink.ADSB_FLAGS_VALID_CALLSIGN)


def icao(sysid: int, index: int, circle: bool = False) -> int:
    """The target's address: stable per (vehicle, target), in the unallocated block."""
    if not (1 <= sysid <= 255 and 0 <= index < MAX_TARGETS):
        raise ValueError(f"no ADSB address for vehicle {sysid} target {index}")
    return (CIRCLE_BASE if circle else MARKER_BASE) + 16 * sysid + index


def is_ours(address: int) -> bool:
    """An address of the block the hub gives targets (a client echoing them back)."""
    return MARKER_BASE <= address < BLOCK_END


def callsign(est: OutputEstimate) -> bytes:
    return f"PMON-{est.name}".encode()[:8]


def encoder(sysid: int) -> mavlink.MAVLink:
    """A MAVLink 2 encoder speaking as the vehicle's ADS-B receiver component."""
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=COMPONENT)
    return mav


def marker(mav: mavlink.MAVLink, est: OutputEstimate):
    """The target as traffic: position, ground altitude, course and speed, age in ``tslc``."""
    return mav.adsb_vehicle_encode(
        icao(mav.srcSystem, est.index), round(est.lat_deg * 1e7), round(est.lon_deg * 1e7),
        mavlink.ADSB_ALTITUDE_TYPE_GEOMETRIC, round(est.alt_m * 1e3),
        round(est.course_deg * 100) % 36000, min(round(est.speed_mps * 100), 65535), 0,
        callsign(est), EMITTER, min(max(round(est.age_s), 0), 255), MARKER_FLAGS, 0)


def circle(mav: mavlink.MAVLink, est: OutputEstimate):
    """The 1-sigma circle as ArduPilot sends an obstacle-database item (AP_OADatabase::
    send_adsb_vehicle: callsign OA_DB, emitter_type 255, flags 0, radius in ``squawk`` cm,
    at most 655.35 m). Flags 0: QGroundControl, which draws no circle, makes no entry of it."""
    radius_cm = min(math.ceil(est.radius_1sigma_m * 100), 65535)
    return mav.adsb_vehicle_encode(
        icao(mav.srcSystem, est.index, circle=True), round(est.lat_deg * 1e7), round(est.lon_deg * 1e7),
        mavlink.ADSB_ALTITUDE_TYPE_GEOMETRIC, round(est.alt_m * 1e3), 0, 0, 0, b"OA_DB",
        OA_DB_EMITTER, 0, 0, radius_cm)


def messages(mav: mavlink.MAVLink, est: OutputEstimate, circles: bool) -> list:
    return [marker(mav, est)] + ([circle(mav, est)] if circles else [])


def pack(mav: mavlink.MAVLink, msgs: list) -> list[bytes]:
    """The messages as MAVLink 2 frames from ``mav``'s system and component, in sequence."""
    out = []
    for m in msgs:
        out.append(bytes(m.pack(mav)))
        mav.seq = (mav.seq + 1) % 256
    return out
