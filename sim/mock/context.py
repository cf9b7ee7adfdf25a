"""What the mock autopilot's parts share, and the contract each part keeps (MAVProxy's module
contract, as the app's: onboard/app/part.py, onboard/app/context.py and onboard/app/gcs/dispatch.py).

The mock (sim/mock/autopilot.py) builds one ``MockContext`` and hands it to each part instead of
letting the parts share its attributes. A part answers the message types of its ``handlers()``
(the mock's router dispatches each message handled locally by ``msg.get_type()``) and does its
share of each loop iteration in ``periodic(now)``. Every handler and ``periodic`` runs on the
mock's thread under its lock."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Mapping

if TYPE_CHECKING:
    from onboard.app.mavlink2 import mavlink
    from sim.mock.copter import Copter
    from sim.mock.copter_params import Params
    from sim.mock.links import _Link

Handler = Callable[["_Link", object], None]  # (the link it came on, the message)


@dataclass(frozen=True, eq=False)
class MockContext:
    sysid: int
    compid: int
    copter: Copter  # the vehicle: modes, boot, the flight model, its clock (``copter.t``, s)
    params: Params
    enc: mavlink.MAVLink  # the message constructor (links do the packing and sequence numbers)
    links: list[_Link]  # the open links; the mock's loop adds and removes them
    counters: dict[str, int]  # the mock's event counters (MockAutopilot.counters())
    crash: Callable[[str], None]  # a defect the firmware dies of: the mock falls silent

    def count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    def broadcast(self, msg) -> None:
        for link in self.links:
            link.send(msg)


class Part:
    """One part of the mock: the messages it answers and its share of each loop iteration."""

    def __init__(self, ctx: MockContext):
        self.ctx = ctx

    def handlers(self) -> Mapping[str, Handler]:
        """Message type -> handler, for the messages this part answers."""
        return {}

    def periodic(self, now: float) -> None:
        """Each loop iteration, ``now`` the autopilot's time since boot (s)."""
