"""The mock autopilot's stores as ArduCopter answers for them: its parameters (read, list, set;
an SRn_ rate set applies at once), an empty mission, fence and rally, and MAVLink FTP on a
vehicle without files. A part of ``MockAutopilot`` (sim/mock/context.py)."""
from __future__ import annotations

from typing import Mapping

from onboard.app.mavlink2 import mavlink
from sim.mock.context import Handler, MockContext, Part
from sim.mock.links import _Link
from sim.mock.messages import Telemetry

# MAVLink FTP opcodes and error codes used by the FTP refusal
_FTP_TERMINATE_SESSION, _FTP_RESET_SESSIONS = 1, 2
_FTP_OPEN_OPS = {3, 4, 6, 11, 13}  # list dir, open RO, create, open WO, calc CRC
_FTP_ACK, _FTP_NAK = 128, 129
_FTP_ERR_INVALID_SESSION, _FTP_ERR_FILE_NOT_FOUND = 4, 10


class Stores(Part):
    """``telemetry``: the banner a parameter list starts with and the stream rates an SRn_
    parameter sets."""

    def __init__(self, ctx: MockContext, telemetry: Telemetry):
        super().__init__(ctx)
        self.telemetry = telemetry

    def handlers(self) -> Mapping[str, Handler]:
        return {"PARAM_REQUEST_LIST": self._on_param_request_list,
                "PARAM_REQUEST_READ": self._on_param_request_read,
                "PARAM_SET": self._on_param_set,
                "MISSION_REQUEST_LIST": self._on_mission_request_list,
                "MISSION_REQUEST_INT": self._on_mission_request_int,
                "MISSION_REQUEST": self._on_mission_request_int,
                "MISSION_CLEAR_ALL": self._on_mission_clear_all,
                "MISSION_COUNT": self._on_mission_count,
                "MISSION_SET_CURRENT": self._on_mission_set_current,
                "FILE_TRANSFER_PROTOCOL": self._on_file_transfer_protocol}

    # ----- parameters
    def _param_value(self, name: str):
        return self.ctx.enc.param_value_encode(
            name.encode(), self.ctx.params[name], self.ctx.params.ptype(name), len(self.ctx.params),
            self.ctx.params.index(name))

    def _on_param_request_list(self, link: _Link, msg) -> None:
        self.telemetry.banner(link)
        for name in self.ctx.params.names():
            link.send(self._param_value(name))

    def _on_param_request_read(self, link: _Link, msg) -> None:
        names = self.ctx.params.names()
        if msg.param_index >= 0:
            name = names[msg.param_index] if msg.param_index < len(names) else None
        else:
            name = _param_name(msg.param_id)
        if name is None or name not in self.ctx.params:
            self.ctx.count("param_unknown")
            link.send(self.ctx.enc.statustext_encode(
                mavlink.MAV_SEVERITY_WARNING,
                f"Unknown parameter {_param_name(msg.param_id) or msg.param_index}".encode()[:50]))
            return
        link.send(self._param_value(name))

    def _on_param_set(self, link: _Link, msg) -> None:
        name = _param_name(msg.param_id)
        if name not in self.ctx.params:
            self.ctx.count("param_unknown")
            link.send(self.ctx.enc.statustext_encode(
                mavlink.MAV_SEVERITY_WARNING, f"Unknown parameter {name}".encode()[:50]))
            return
        if self.ctx.params.set(name, float(msg.param_value)):
            self.ctx.count("param_set")
            self.ctx.copter.params_changed()
            if name.startswith("SR") and "_" in name:  # a port's stream rates: at once
                tm = self.telemetry
                for lk in self.ctx.links:
                    if name.startswith(f"SR{lk.port_index}_"):
                        for msg_name, iv in tm.default_intervals(lk.port_index).items():
                            tm.set_interval(lk, msg_name, iv)
        self.ctx.broadcast(self._param_value(name))  # ArduPilot tells every link

    # ----- missions: an empty mission, fence and rally
    def _on_mission_request_list(self, link: _Link, msg) -> None:
        link.send(self.ctx.enc.mission_count_encode(
            msg.get_srcSystem(), msg.get_srcComponent(), 0, getattr(msg, "mission_type", 0)))

    def _mission_nack(self, link: _Link, msg, result: int) -> None:
        link.send(self.ctx.enc.mission_ack_encode(
            msg.get_srcSystem(), msg.get_srcComponent(), result,
            getattr(msg, "mission_type", 0)))

    def _on_mission_request_int(self, link: _Link, msg) -> None:
        self._mission_nack(link, msg, mavlink.MAV_MISSION_INVALID_SEQUENCE)

    def _on_mission_clear_all(self, link: _Link, msg) -> None:
        self._mission_nack(link, msg, mavlink.MAV_MISSION_ACCEPTED)

    def _on_mission_count(self, link: _Link, msg) -> None:
        # Uploading an empty list is fine; storing missions is not modelled.
        result = mavlink.MAV_MISSION_ACCEPTED if msg.count == 0 else mavlink.MAV_MISSION_UNSUPPORTED
        self._mission_nack(link, msg, result)

    def _on_mission_set_current(self, link: _Link, msg) -> None:
        self._mission_nack(link, msg, mavlink.MAV_MISSION_INVALID_SEQUENCE)

    # ----- MAVLink FTP: a vehicle without files
    def _on_file_transfer_protocol(self, link: _Link, msg) -> None:
        """Answer every FTP request at once so clients (MAVProxy fetches parameters over FTP
        first) fall back to PARAM_REQUEST_LIST instead of waiting for a timeout."""
        payload = bytes(msg.payload)
        if len(payload) < 12:
            return
        seq = int.from_bytes(payload[0:2], "little")
        session, opcode = payload[2], payload[3]
        if opcode in (_FTP_TERMINATE_SESSION, _FTP_RESET_SESSIONS):
            reply_op, size, data = _FTP_ACK, 0, b""
        else:
            code = _FTP_ERR_FILE_NOT_FOUND if opcode in _FTP_OPEN_OPS else _FTP_ERR_INVALID_SESSION
            reply_op, size, data = _FTP_NAK, 1, bytes([code])
        header = (((seq + 1) & 0xFFFF).to_bytes(2, "little")
                  + bytes([session, reply_op, size, opcode, 0, 0]) + payload[8:12])
        body = (header + data).ljust(251, b"\x00")
        link.send(self.ctx.enc.file_transfer_protocol_encode(
            0, msg.get_srcSystem(), msg.get_srcComponent(), list(body)))


def _param_name(raw) -> str:
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0].strip()
