"""The fence, checked on the setpoint when planned and on the message as it is sent (issue 23,
part 3): ``fence.outgoing_violation`` reads the SET_POSITION_TARGET_LOCAL_NED's own position
(float32, LOCAL_NED at the fixed origin) back to ENU. Unit tests; the flight with a spoofed
origin is tests/app/test_frame_spoof.py."""
from __future__ import annotations

import math

import numpy as np
import pytest

from onboard.app.mavlink2 import mavlink

from onboard.app.autopilot.fence import Fence, outgoing_violation, violation
from onboard.app.params import ParamTable
from onboard.app.autopilot.pose import Frame
from onboard.core.monitor import MonitorSetup

POSITION_ONLY = 3576
VELOCITY_TOO = 3576 & ~0b111000  # x, y, z and vx, vy, vz used (issue 24's feed-forward)


@pytest.fixture(scope="module")
def world(paper):
    setup = MonitorSetup.from_scenario(paper)
    params = ParamTable.from_scenario(paper)
    o = paper.origin
    frame = Frame(o.lat_deg, o.lon_deg, o.alt_m)
    # the autopilot's EKF origin: its home, 300 m south-west of the mission origin, 10 m lower
    ned_origin = frame.geodetic_from_enu((-300.0, -300.0, -10.0))
    return setup, params, frame, ned_origin


def message(frame, ned_origin, enu, coordinate_frame=mavlink.MAV_FRAME_LOCAL_NED, type_mask=POSITION_ONLY,
            vel=(0.0, 0.0, 0.0)):
    """The message the app builds: ENU -> LOCAL_NED at ``ned_origin``."""
    mav = mavlink.MAVLink(None)
    ned = frame.ned_from_enu(enu, ned_origin)
    return mav.set_position_target_local_ned_encode(0, 1, 1, coordinate_frame, type_mask, *map(float, ned),
                                                    *vel, 0, 0, 0, 0, 0)


def test_plan_time_rules(world):
    setup, params, _, _ = world
    f = Fence.of(setup, params)
    assert violation(f, (150.0, 200.0, 40.0), centre=(140.0, 200.0, 40.0)) is None
    assert violation(f, (-1.0, 200.0, 40.0)) == "outside the area"
    assert violation(f, (150.0, 200.0, 130.0)) == "outside the altitude band"
    assert violation(f, (150.0, 200.0, 41.0)) == "not at altitude h"
    assert violation(f, (400.0, 600.0, 40.0)) == "inside an obstacle"  # O1, 60 m tall
    assert violation(f, (400.0, 680.0, 40.0), centre=(400.0, 520.0, 40.0)) == "path crosses an obstacle"
    assert violation(f, (math.nan, 0.0, 40.0)) == "not a finite position"
    assert violation(Fence.of(setup, params, at_altitude=False), (150.0, 200.0, 41.0)) is None


def test_the_message_as_sent_is_read_back_and_checked(world):
    setup, params, frame, ned_origin = world
    f = Fence.of(setup, params, at_altitude=False)
    inside = np.array([150.0, 200.0, 40.0])
    assert outgoing_violation(message(frame, ned_origin, inside), frame, ned_origin, f) is None
    # on the area's edge: float32 fields move it by < 1 mm, still inside
    for edge in ((0.0, 0.0, 40.0), (1000.0, 1000.0, 40.0)):
        assert outgoing_violation(message(frame, ned_origin, edge), frame, ned_origin, f) is None
    # a velocity feed-forward in the same message changes nothing in the check
    msg = message(frame, ned_origin, inside, type_mask=VELOCITY_TOO, vel=(5.0, -3.0, 0.0))
    assert outgoing_violation(msg, frame, ned_origin, f) is None
    # built with another origin than the fixed one (the old app took GPS_GLOBAL_ORIGIN from the
    # air): the vehicle would fly 2 km off; the same point in ENU, refused as sent
    moved = frame.geodetic_from_enu((1843.0, 1891.0, 0.0))
    assert outgoing_violation(message(frame, moved, inside), frame, ned_origin, f) == "outside the area"
    assert outgoing_violation(message(frame, ned_origin, inside, mavlink.MAV_FRAME_BODY_NED), frame,
                              ned_origin, f) == "frame 8 is not LOCAL_NED"
    assert outgoing_violation(message(frame, ned_origin, inside, type_mask=POSITION_ONLY | 0b111), frame,
                              ned_origin, f) == "position fields ignored by type_mask"
    assert outgoing_violation(message(frame, ned_origin, inside), frame, None, f) == "no fixed NED origin"
    nan = message(frame, ned_origin, inside)
    nan.x = math.nan
    assert outgoing_violation(nan, frame, ned_origin, f) == "not a finite position"
    far = message(frame, ned_origin, inside)
    far.x = 1e39  # past float32: inf on the wire
    assert outgoing_violation(far, frame, ned_origin, f) == "not a finite position"
