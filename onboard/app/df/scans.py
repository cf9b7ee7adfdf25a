"""DF datagrams into the scan buffer (io thread, under the app lock): the reader thread
(onboard/app/df/udp_input.py) queued them, here each is parsed and stored on the autopilot clock
(onboard/app/df/datagram.py), the first valid sender locks the input, and what was refused is said
once per kind, per foreign sender and per episode of rate limiting."""
from __future__ import annotations

from onboard.app.df import datagram as dg
from onboard.app.counters import Counters
from onboard.app.df.udp_input import DfInput
from onboard.app.mavlink_connection import mavlink
from onboard.app.part import Job, Part


class DfScans(Part):
    def __init__(self, df: DfInput, scans: dg.ScanBuffer, clock, counters: Counters, say):
        self.df = df
        self.scans = scans
        self.clock = clock
        self.counters = counters
        self.say = say
        self._foreign_seen: set = set()  # foreign DF senders reported
        self._limited_seen = 0

    def on_datagram(self, data: bytes, addr: tuple[str, int]) -> None:
        if not self.df.accepts(addr):  # queued before the lock to another sender
            self.counters.add("df_foreign_queued")
            return
        try:
            self.scans.offer(data, self.clock.now())
        except dg.DatagramError as err:
            if self.scans.rejected[err.reason] == 1:  # the first of each kind
                self.say(f"bad DF datagram: {err}"[:44], mavlink.MAV_SEVERITY_WARNING)
            return
        if self.df.lock(addr):
            self.say(f"DF source {addr[0]}:{addr[1]}; others ignored")

    def jobs(self) -> tuple[Job, ...]:
        return (Job("periodic DF input", lambda local, now: self.report()),)

    def report(self) -> None:
        """The periodic job: say once per foreign DF sender, and once per episode of rate
        limiting."""
        for addr in list(self.df.foreign):
            if addr not in self._foreign_seen:
                self._foreign_seen.add(addr)
                self.counters.add("df_foreign_sources")
                self.say(f"DF from {addr[0]}:{addr[1]} ignored", mavlink.MAV_SEVERITY_WARNING)
        limited = self.df.dropped["rate_limited"]
        if limited > self._limited_seen:
            self._limited_seen = limited
            self.say(f"DF sender over {self.df.rate_hz:g}/s: excess dropped", mavlink.MAV_SEVERITY_WARNING,
                     once="df_rate")
