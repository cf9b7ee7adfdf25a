"""What the app's parts share, built once by the app (onboard/app/app.py) and handed to each part
instead of wiring them one by one: the app's config, the autopilot link, the autopilot clock and
the local one, the parameters, the event counters, the app's voice and the app lock."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from onboard.app.counters import Counters

if TYPE_CHECKING:
    from onboard.app.app_config import AppConfig
    from onboard.app.mavlink_connection import Link
    from onboard.app.params import ParamTable


@dataclass(frozen=True)
class AppContext:
    cfg: AppConfig
    link: Link
    clock: object  # the autopilot's clock (onboard/app/autopilot/clock.py): ``now()``, autopilot s or None
    mono: Callable[[], float]  # local s
    params: ParamTable
    counters: Counters
    say: Callable[..., None]  # Publisher.say: STATUSTEXT and the event list
    lock: object  # the app lock (a threading.RLock): the io thread's parts run under it
