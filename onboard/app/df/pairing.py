"""A tick's per-channel scans as the core's ``Scan``s: each paired with where the vehicle was
when it was measured.

A DF datagram is measured at its scan time ``t``. A scan from another input may carry its own
measurement time (``t_measured``: a KrakenSDR frame is ticked in the slot of the nearest whole
second, onboard/app/kraken/source.py, but was taken from where the vehicle was at the frame's time)
and its own clutter rate (``clutter_rate``). Channels measured at the same time share one
``Scan``; a channel without a scan, or measured at another time, has an empty set in it (the
likelihood of an empty set is constant: uninformative)."""
from __future__ import annotations

from typing import Callable

import numpy as np

from onboard.core.monitor import Scan


def scans_for_tick(scans: dict, t: float, n_channels: int,
                   position_at: Callable[[float], np.ndarray | None]) -> tuple[list[Scan], int]:
    """The core scans of one tick's ``scans`` (channel -> datagram) at scan time ``t``, and the
    number of channels dropped because the vehicle's position at their time is unknown."""
    groups: dict[float, list[int]] = {}
    for ch, d in scans.items():
        tm = getattr(d, "t_measured", None)
        groups.setdefault(t if tm is None else tm, []).append(ch)
    out, unpaired = [], 0
    empty = np.empty(0)
    for tm in sorted(groups):
        chans = groups[tm]
        pos = position_at(tm)
        if pos is None:
            unpaired += len(chans)
            continue
        bearings = tuple(scans[ch].bearings if ch in chans else empty for ch in range(n_channels))
        rates = tuple(getattr(scans[ch], "clutter_rate", None) if ch in chans else None
                      for ch in range(n_channels))
        out.append(Scan(pos, bearings, None if all(r is None for r in rates) else rates))
    return out, unpaired
