"""The contract every part of the app keeps (MAVProxy's module contract; the mock autopilot's is
sim/mock/context.py): the MAVLink message types it handles and its periodic jobs. The app
(onboard/app/app.py) holds its parts in one list, in the order their jobs run.

- ``handlers()``: message type -> handler. The router (onboard/app/gcs/dispatch.py) dispatches
  each message by ``msg.get_type()`` to every part that registered its type, in the parts'
  order, once the message passed who-may-be-obeyed.
- ``jobs()``: the part's periodic jobs, each called as ``run(local_s, now_s)`` every io
  iteration (local s; the autopilot's s, None before its first clock sample) and each contained
  on its own under its ``where`` (onboard/app/contain.py): one that raises costs itself, not the
  jobs after it. A ``clocked`` job waits for the autopilot's clock: it is skipped while
  ``now_s`` is None.

Handlers and jobs run on the io thread, under the app lock.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Mapping

Handler = Callable[[object], None]  # (the message)


@dataclass(frozen=True)
class Job:
    where: str  # its name in the error counts and what is said ("periodic link: KeyError")
    run: Callable[[float, "float | None"], None]  # (local s, autopilot s or None)
    clocked: bool = False  # only once the autopilot's clock has a sample


class Part:
    """A part of the app: the messages it handles and its periodic jobs (none by default)."""

    def handlers(self) -> Mapping[str, Handler]:
        return {}

    def jobs(self) -> tuple[Job, ...]:
        return ()
