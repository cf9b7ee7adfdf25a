"""``pmon gcs hub`` on loopback for the hub's tests and benches: a fake vehicle
(sim/stack/gcs_fake_vehicle.py) behind a Hub on a thread, and one client on its serve port."""
from __future__ import annotations

import threading
import time

from sim.stack.gcs_fake_vehicle import Client, FakeVehicle, free_udp_port, target_values
from groundstation.hub import Hub, HubLink
from groundstation.hub_options import HubConfig
from onboard.app.autopilot.pose import Frame
from onboard.config import load_scenario

SC = load_scenario("paper")
FRAME = Frame(SC.origin.lat_deg, SC.origin.lon_deg, SC.origin.alt_m)
TARGETS = [(281.0, 925.0), (238.0, 706.0), (901.0, 925.0), (885.0, 676.0)]


class Rig:
    def __init__(self, signing_key: bytes | None = None, **cfg):
        """``signing_key``: the vehicle signs with it, and the hub's link and the hub use it."""
        self.vport, self.sport = free_udp_port(), free_udp_port()
        self.cfg = HubConfig(serve=(("127.0.0.1", self.sport),), **cfg)
        self.key = signing_key
        self.veh = FakeVehicle(self.vport)
        if signing_key is not None:
            from onboard.app import signing
            signing.apply(self.veh.conn, signing_key, link_id=1)
        self.stop = threading.Event()
        self.hub: Hub | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()
        deadline = time.monotonic() + 10
        while self.hub is None and self.error is None and time.monotonic() < deadline:
            self.veh.heartbeat()
            time.sleep(0.1)
        assert self.hub is not None, f"hub did not start: {self.error!r}"
        self.client = Client(self.sport)
        deadline = time.monotonic() + 5
        while not self.client.got("HEARTBEAT") and time.monotonic() < deadline:  # the hub knows the client
            self.veh.heartbeat()
            time.sleep(0.05)
        assert self.client.got("HEARTBEAT")

    def _run(self):
        try:
            with HubLink(f"udpin:127.0.0.1:{self.vport}", timeout=8, signing_key=self.key) as gl:
                gl.connect()
                hub = Hub(gl, SC, self.cfg, self.key)
                try:
                    self.hub = hub
                    hub.run(stop=self.stop)
                finally:
                    hub.close()
        except BaseException as exc:  # noqa: BLE001 (reported by the test)
            self.error = exc

    def tick(self, t: float, since=0.4, targets=TARGETS):
        for j, (x, y) in enumerate(targets):
            self.veh.target(j, target_values(x + t, y - t, since=since, t=t), t_usec=int(t * 1e6))
        self.veh.stat(t)

    def close(self):
        self.stop.set()
        self.thread.join(timeout=5)
        self.client.close()
        self.veh.close()
