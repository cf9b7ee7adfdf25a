"""Real MAVLink clients against the mock autopilot: MAVProxy and MAVSDK (native, asyncio).

MAVProxy runs as a separate process, connected to the mock started as a process with
`python -m sim.mock.autopilot`; a pymavlink client on the mock's UDP port flies the vehicle
while MAVProxy reports mode, arming and position on its stdout. MAVSDK connects the way
a ground station would (udpin) and flies arm -> takeoff -> goto_location itself.
"""

from __future__ import annotations

import asyncio
import math
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from onboard.app.mavlink2 import mavlink, mavutil
from sim.mock.autopilot import BootTimeline, MockAutopilot, Mode

from tests.support.processes import LineReader, stop_process

pytestmark = pytest.mark.sitl

REPO = Path(__file__).resolve().parents[2]
HOME = (-35.363261, 149.165230, 584.0)
M_PER_DEG_LAT = 111_132.0  # close enough at -35 deg for a 20 m test offset


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.timeout(60)
def test_mavproxy_reports_mode_arming_and_position(tmp_path):
    pytest.importorskip("MAVProxy", reason="MAVProxy is a test-only dependency")
    tcp_port = free_port(socket.SOCK_STREAM)
    cmd_port = free_port(socket.SOCK_DGRAM)
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    mock = subprocess.Popen(
        [sys.executable, "-m", "sim.mock.autopilot", "--tcp", f"127.0.0.1:{tcp_port}",
         "--udp", f"127.0.0.1:{cmd_port}", "--speedup", "5", "--ready-after", "8",
         "--home=" + ",".join(str(v) for v in HOME)],  # '=': the value starts with '-'
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env, cwd=tmp_path)
    mavproxy = None
    commander = None
    try:
        mock_out = LineReader(mock)
        mock_out.wait_for(r"mock autopilot up: .*tcpin:127\.0\.0\.1:%d" % tcp_port, 10)

        mavproxy = subprocess.Popen(
            [sys.executable, "-m", "MAVProxy.mavproxy", f"--master=tcp:127.0.0.1:{tcp_port}",
             "--non-interactive", "--no-state",
             "--cmd=repeat add 1 status GLOBAL_POSITION_INT"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            text=True, env=env, cwd=tmp_path)
        out = LineReader(mavproxy)
        out.wait_for(r"Detected vehicle 1:1", 20)
        out.wait_for(r"Mode STABILIZE", 10)
        out.wait_for(r"Received \d+ parameters", 20)  # MAVProxy fetched the whole list
        out.wait_for(r"GLOBAL_POSITION_INT .*relative_alt : 0\b", 10)

        # A second client (like a GCS on udp 14550) flies; MAVProxy only watches.
        commander = mavutil.mavlink_connection(f"udpin:127.0.0.1:{cmd_port}",
                                               source_system=254, dialect="ardupilotmega")
        commander.wait_heartbeat(timeout=10)

        def command(cmd, *params):
            # the commander does not read while the test watches MAVProxy: its socket buffer
            # fills with telemetry and the kernel would drop the ACK, so drain it first and,
            # as a GCS does, resend (confirmation 1, 2) when no ACK comes
            p = list(params) + [0.0] * (7 - len(params))
            ack = None
            for confirmation in range(3):
                while commander.recv_msg() is not None:
                    pass
                commander.mav.command_long_send(1, 1, cmd, confirmation, *p)
                ack = commander.recv_match(type="COMMAND_ACK", blocking=True, timeout=5,
                                           condition=f"COMMAND_ACK.command=={cmd}")
                if ack is not None:
                    break
            assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED, ack

        mark = len(out.lines)
        command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                Mode.GUIDED)
        command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 10)
        out.wait_for(r"Mode GUIDED", 10, since=mark)
        out.wait_for(r"\bARMED\b", 10, since=mark)
        m = out.wait_for(r"GLOBAL_POSITION_INT .*relative_alt : (9\d{3}|10\d{3})\b", 15,
                         since=mark)
        assert m is not None

        north = 20.0
        lat = int((HOME[0] + north / M_PER_DEG_LAT) * 1e7)
        commander.mav.set_position_target_global_int_send(
            0, 1, 1, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, 0b110111111000, lat,
            int(HOME[1] * 1e7), 10.0, 0, 0, 0, 0, 0, 0, 0, 0)
        out.wait_for(r"GLOBAL_POSITION_INT .*lat : (-?\d+),", 20, since=mark,
                     check=lambda m: abs(int(m.group(1)) - lat) < 100)  # within ~1 m

        command(mavlink.MAV_CMD_NAV_LAND)
        out.wait_for(r"Mode LAND", 10, since=mark)
    finally:
        if commander is not None:
            commander.close()
        if mavproxy is not None:
            stop_process(mavproxy)
        stop_process(mock)
    assert mock.returncode == 0
    mock_out.wait_for(r"mock autopilot stopped: .*'rx'", 5)


async def _mavsdk_flight(port: int, ap: MockAutopilot) -> dict:
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.telemetry import FlightMode, LandedState, TelemetryAsync

    async def first(gen, pred, timeout):
        async def scan():
            async for value in gen:
                if pred(value):
                    return value
        return await asyncio.wait_for(scan(), timeout)

    seen = {}
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(config) as sdk:
        await sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        drone = await sdk.first_autopilot(timeout_s=10.0)
        assert drone is not None, "MAVSDK found no autopilot"
        tel = TelemetryAsync(drone)
        action = ActionAsync(drone)
        # ArduCopter streams nothing it is not asked for (SRn_ rates 0, as its SITL): a MAVSDK
        # application asks for what it reads, as it must against a real ArduPilot
        await tel.set_rate_position(5.0)
        await tel.set_rate_landed_state(2.0)
        await tel.set_rate_health(2.0)

        # a fix: before it ArduCopter reports lat = lon = 0, which MAVSDK passes on as a position
        pos = await first(tel.subscribe_position(),
                          lambda p: not math.isnan(p.latitude_deg) and abs(p.latitude_deg) > 1e-3, 10)
        seen["start"] = pos
        seen["armed0"] = await first(tel.subscribe_armed(), lambda a: True, 5)
        seen["mode0"] = await first(tel.subscribe_flight_mode(), lambda m: True, 5)
        seen["health"] = await first(tel.subscribe_health(), lambda h: h.is_armable, 10)

        await action.set_takeoff_altitude(10.0)
        # ArduCopter's pre-arm bit (MAVSDK's is_armable) can read healthy a moment before arming
        # passes (its SITL at ~24 s; the mock's BootTimeline.blip_s): a client tries again
        for attempt in range(10):
            try:
                await action.arm()
                break
            except Exception as exc:  # mavsdk's ActionError: "Command denied"
                seen.setdefault("arm_refused", []).append(str(exc))
                await asyncio.sleep(1.0)
        seen["armed"] = await first(tel.subscribe_armed(), lambda a: a, 5)
        await action.takeoff()  # MAVSDK switches ArduPilot to GUIDED itself
        seen["mode"] = await first(tel.subscribe_flight_mode(),
                                   lambda m: m == FlightMode.OFFBOARD, 5)
        seen["in_air"] = await first(tel.subscribe_landed_state(),
                                     lambda s: s == LandedState.IN_AIR, 15)
        seen["climbed"] = await first(tel.subscribe_position(),
                                      lambda p: p.relative_altitude_m > 9.5, 15)

        target_lat = pos.latitude_deg + 20.0 / M_PER_DEG_LAT
        await action.goto_location(target_lat, pos.longitude_deg, pos.absolute_altitude_m + 12.0,
                                   0.0)
        seen["arrived"] = await first(
            tel.subscribe_position(),
            lambda p: abs(p.latitude_deg - target_lat) * M_PER_DEG_LAT < 1.0
            and abs(p.relative_altitude_m - 12.0) < 0.5, 20)
        seen["state"] = ap.state()
    return seen


@pytest.mark.timeout(60)
def test_mavsdk_connects_arms_takes_off_and_goes_to_a_location():
    from mavsdk.asyncio.plugins.telemetry import FlightMode

    port = free_port(socket.SOCK_DGRAM)
    with MockAutopilot(home=HOME, endpoints=[f"udpout:127.0.0.1:{port}"], speedup=5.0, boot=BootTimeline.scaled(8.0),
                       seed=5) as ap:
        seen = asyncio.run(_mavsdk_flight(port, ap))
        counters = ap.counters()

    start = seen["start"]
    assert start.latitude_deg == pytest.approx(HOME[0], abs=1e-6)
    assert start.absolute_altitude_m == pytest.approx(HOME[2], abs=0.2)
    assert seen["armed0"] is False
    assert seen["mode0"] == FlightMode.STABILIZED  # ArduCopter STABILIZE
    assert seen["armed"] is True and seen["mode"] == FlightMode.OFFBOARD  # GUIDED
    final = seen["state"]
    assert final.mode == Mode.GUIDED and final.armed
    assert final.pos_ned[0] == pytest.approx(20.0, abs=1.0)
    assert final.alt_rel == pytest.approx(12.0, abs=0.5)
    assert counters.get("ack_accepted", 0) >= 4  # set mode, arm, takeoff, reposition
    assert counters.get("handler_errors", 0) == 0 and counters.get("loop_errors", 0) == 0
