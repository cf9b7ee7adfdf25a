"""Hostile `pmon gcs hub` options (issue 45, items 6 and 7) with a vehicle on loopback that
would let the hub start: each is refused with one line, exit 2, before the link is opened or
a thread started, and no name is looked up for a malformed endpoint."""
from __future__ import annotations

import os
import socket
import threading
import time

import pytest

from sim.stack.gcs_fake_vehicle import FakeVehicle, free_udp_port
from groundstation.cli import main

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def vehicle():
    """A vehicle heartbeating at 10 Hz to a free loopback port (the hub's --connect)."""
    port = free_udp_port()
    veh = FakeVehicle(port)
    stop = threading.Event()

    def beat():
        while not stop.wait(0.1):
            veh.heartbeat()
    th = threading.Thread(target=beat, daemon=True)
    th.start()
    yield port, veh
    stop.set()
    th.join(timeout=2)
    veh.close()


@pytest.fixture
def lookups(monkeypatch):
    """Every name getaddrinfo is asked for that is not an address literal or localhost."""
    asked: list = []
    real = socket.getaddrinfo

    def spy(host, *args, **kwargs):
        name = host.decode() if isinstance(host, bytes) else host
        try:
            socket.inet_pton(socket.AF_INET6 if ":" in (name or "") else socket.AF_INET, name or "")
        except (OSError, TypeError):
            if name not in (None, "localhost"):
                asked.append(name)
                raise socket.gaierror(socket.EAI_NONAME, f"test: no lookup of {name!r}")
        return real(host, *args, **kwargs)
    monkeypatch.setattr(socket, "getaddrinfo", spy)
    return asked


def hub(capsys, vport: int, *argv, out: list | None = None) -> tuple[int, str, float]:
    capsys.readouterr()
    threads = threading.active_count()
    t0 = time.monotonic()
    rc = main(["--connect", f"udpin:127.0.0.1:{vport}", "--timeout", "3", "hub", "--duration", "1", *argv])
    dt = time.monotonic() - t0
    assert threading.active_count() <= threads, "a thread was left running"
    cap = capsys.readouterr()
    if out is not None:
        out.append(cap.out)
    return rc, cap.err.strip(), dt


def test_hostile_hub_options_are_one_line_exit_2_before_anything_starts(vehicle, lookups, capsys, tmp_path):
    vport, veh = vehicle
    (tmp_path / "dir.pem").mkdir()
    os.mkfifo(tmp_path / "fifo.pem")
    (tmp_path / "junk.pem").write_text("not a certificate\n")
    tls = ["--tak", "tls://127.0.0.1:8089"]
    cases = [
        (tls, "tls:// needs a client certificate"),
        (tls + ["--tak-cert", str(tmp_path / "missing.pem")], "missing.pem: cannot read: No such file"),
        (tls + ["--tak-cert", str(tmp_path / "dir.pem")], "dir.pem: a directory, not a regular file"),
        (tls + ["--tak-cert", str(tmp_path / "fifo.pem")], "fifo.pem: a FIFO, not a regular file"),
        (tls + ["--tak-cert", str(tmp_path / "junk.pem")], "junk.pem: not a PEM certificate"),
        (tls + ["--tak-ca", str(tmp_path / "fifo.pem")], "fifo.pem: a FIFO, not a regular file"),
        (["--serve", "udp:127.0.0.1:\u0661\u0664\u0665\u0666\u0660"], "port must be 0..65535"),  # Arabic-Indic 14560
        (["--out", "udp:127.0.0.1:0"], "port must be 1..65535, got '0'"),
        (["--view", "abc"], "argument --view: port must be 0..65535, got 'abc'"),
        (["--view", "70000"], "argument --view: port must be 0..65535"),
        # item 7: malformed endpoints, never resolved
        (["--serve", f"tcp:127.0.0.1:{free_udp_port()}"], "'tcp:127.0.0.1' is not an IP address or a host name"),
        (["--out", "udp:999.1.1.1:14550"], "'999.1.1.1' is not an IP address or a host name"),
        (["--tak", "udp+log://stderr:1"], "is not udp://HOST:PORT, tcp://HOST:PORT or tls://HOST:PORT"),
        (["--tak", "udp://tcp:127.0.0.1:1"], "is not udp://HOST:PORT"),
        (["--tak", "tcp://127.0.0.1:\u0661"], "port must be 1..65535"),
    ]
    failures = []
    for argv, want in cases:
        rc, err, dt = hub(capsys, vport, *argv)
        if rc != 2 or len(err.splitlines()) != 1 or want not in err or dt > 2.0:
            failures.append((argv, rc, err, round(dt, 2)))
    assert failures == [] and lookups == []
    time.sleep(0.3)
    assert veh.received == [], "the hub opened the link"


def test_wellformed_options_still_start_the_hub(vehicle, lookups, capsys):
    """The checks refuse only what is malformed: a served port 0 (any free one) and a TAK URL
    with pytak's write-only modifier start, and the loopback names are not looked up. Unsigned,
    the hub says in one line that its clients command the vehicle (issue 45, item 8)."""
    vport, _ = vehicle
    tak = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tak.bind(("127.0.0.1", 0))
    out: list = []
    try:
        rc, err, _ = hub(capsys, vport, "--serve", "udp:127.0.0.1:0", "--out", "udp:localhost:9",
                         "--tak", f"udp+wo://127.0.0.1:{tak.getsockname()[1]}", out=out)
    finally:
        tak.close()
    assert rc == 0, err
    assert lookups == []
    warn = [line for line in out[0].splitlines() if "UNSIGNED" in line]
    assert len(warn) == 1 and "every client of the hub commands the vehicle" in warn[0], out[0]
