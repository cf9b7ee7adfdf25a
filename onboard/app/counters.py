"""The app's event counters (``ticks``, ``io_errors``, ``setpoints_refused``, ...): a dict every
part adds to under the app lock, and rigs and tests read (docs/SAFETY.md names them)."""
from __future__ import annotations


class Counters(dict):
    def add(self, key: str, n: int = 1) -> None:
        self[key] = self.get(key, 0) + n
