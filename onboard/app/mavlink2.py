"""pymavlink speaking MAVLink 2: every module of the project takes ``mavutil`` and the
``mavlink`` dialect from here, never from pymavlink itself.

pymavlink chooses MAVLink 1 or 2 from the ``MAVLINK20`` environment variable when ``mavutil``
loads its dialect (on its import and on each ``mavlink_connection``); set once here, before the
first import of ``mavutil`` in the process, whichever entry point runs.
"""
from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

__all__ = ["mavlink", "mavutil"]
