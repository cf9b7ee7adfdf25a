"""The app's parameters on the MAVLink parameter protocol (component 191): list, read by name
or index, set. A set is answered with the value the app now holds (unchanged if refused, with a
STATUSTEXT saying why); the values and their checks are onboard/app/params.py's. io thread,
under the app lock."""
from __future__ import annotations

from typing import Callable

from onboard.app.context import AppContext
from onboard.app.mavlink_connection import mavlink, param_name
from onboard.app.part import Handler, Part


class ParamServer(Part):
    """``on_change(name)``: called after an accepted set; ``ctx``: the app's link, parameters
    and voice."""

    def __init__(self, ctx: AppContext, on_change: Callable[[str], None]):
        self.link = ctx.link
        self.params = ctx.params
        self.say = ctx.say
        self.on_change = on_change

    def handlers(self) -> dict[str, Handler]:
        return {"PARAM_REQUEST_LIST": self.on_request_list, "PARAM_REQUEST_READ": self.on_request_read,
                "PARAM_SET": self.on_set}

    def send_value(self, name: str, index: int | None = None) -> None:
        p = self.params
        self.link.send(self.link.mav.param_value_encode(
            name.encode(), p[name], mavlink.MAV_PARAM_TYPE_REAL32, len(p), p.index(name) if index is None else index))

    def on_request_list(self, msg) -> None:
        for i, name in enumerate(self.params.names()):
            self.send_value(name, i)

    def on_request_read(self, msg) -> None:
        if msg.param_index >= 0:
            if msg.param_index < len(self.params):
                self.send_value(self.params.names()[msg.param_index], msg.param_index)
            else:
                self.say(f"no parameter index {msg.param_index}", mavlink.MAV_SEVERITY_WARNING)
            return
        name = param_name(msg.param_id)
        if name in self.params:
            self.send_value(name)
        else:
            self.say(f"unknown parameter {name[:16]}", mavlink.MAV_SEVERITY_WARNING)

    def on_set(self, msg) -> None:
        name = param_name(msg.param_id)
        if name not in self.params:
            self.say(f"unknown parameter {name[:16]}", mavlink.MAV_SEVERITY_WARNING)
            return  # nothing to answer with: no such value exists
        refused = self.params.set(name, float(msg.param_value))
        if refused:
            self.say(refused, mavlink.MAV_SEVERITY_WARNING)
        self.send_value(name)
        if not refused:
            self.on_change(name)
