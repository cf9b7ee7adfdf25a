"""Helpers the onboard app's tests share (test modules do not import each other): waits on
conditions, a scripted direction finder on the mock autopilot's clock, and a core tick a test
can put faults into (``OnboardApp(..., tick=FaultyTick())``)."""
from __future__ import annotations

import math
import socket
import threading
import time

import numpy as np

from sim.mock.autopilot import MockAutopilot

from onboard.app.df import datagram as dg
from onboard.core import monitor


def wait_for(pred, timeout: float = 30.0, poll_s: float = 0.02) -> bool:
    """Until ``pred()`` holds (True) or ``timeout`` wall seconds pass (its last value)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(poll_s)
    return pred()


def wait_autopilot_s(ap: MockAutopilot, dt: float, timeout: float = 30.0) -> float:
    """Let ``dt`` autopilot seconds pass; returns the autopilot time at the end."""
    t_end = ap.sim_time + dt
    assert ap.wait_until(lambda s: s.time_boot_ms / 1000 >= t_end, timeout)
    return t_end


class FaultyTick:
    """The core tick, with a fault a test switches on and off: ``fault`` is None (the real
    tick) or a function called as the tick is, given the real tick as ``real=``."""

    def __init__(self, real=monitor.tick):
        self.real = real
        self.fault = None

    def __call__(self, *args, **kwargs):
        fault = self.fault
        if fault is None:
            return self.real(*args, **kwargs)
        return fault(*args, real=self.real, **kwargs)


class ScriptedDf:
    """A direction finder on the autopilot's clock: every whole second T, one datagram per
    channel with the bearing from the UAV to each (static) target. ``silent`` sends nothing;
    ``empty_ch0`` sends ch 0 with no bearing (with p_D = 1 and no clutter: impossible)."""

    def __init__(self, ap: MockAutopilot, port: int, targets: np.ndarray):
        self.ap, self.dest, self.targets = ap, ("127.0.0.1", port), targets
        self.silent = False
        self.empty_ch0 = 0  # number of scans to send ch 0 empty
        self.sent: list[float] = []
        self._stop = threading.Event()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._t = threading.Thread(target=self._run, daemon=True)

    def start(self):
        self._t.start()
        return self

    def _run(self):
        T = math.floor(self.ap.sim_time) + 1.0
        while not self._stop.is_set():
            if self.ap.sim_time < T:
                time.sleep(0.003)
                continue
            s = self.ap.state()
            if s.armed and not self.silent:
                uav = np.array(s.pos_enu)
                for ch, tgt in enumerate(self.targets):
                    d = tgt[:2] - uav[:2]
                    b = [math.atan2(d[0], d[1])]
                    if ch == 0 and self.empty_ch0 > 0:
                        b = []
                    self._sock.sendto(dg.encode(T, ch, b), self.dest)
                if self.empty_ch0 > 0:
                    self.empty_ch0 -= 1
                self.sent.append(T)
            T += 1.0

    def stop(self):
        self._stop.set()
        self._t.join(timeout=2)
        self._sock.close()
