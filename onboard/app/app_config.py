"""The app's run options (``pmon run``'s command line, onboard/app/run.py; a rig's in process):
what the app is built from beside the scenario. The app (onboard/app/app.py) takes one and hands
it to its parts in the shared context (onboard/app/context.py)."""
from __future__ import annotations

from dataclasses import dataclass

from onboard.app.df.udp_input import DEFAULT_RATE_HZ, Source


@dataclass(frozen=True)
class AppConfig:
    mavlink_url: str
    sensor_host: str = "127.0.0.1"
    sensor_port: int = 14600  # 0: pick a free port (see OnboardApp.sensor_port)
    baud: int = 57600
    target_system: int | None = None  # None: the first autopilot heard
    auto_launch: bool = False  # the demo's "by itself": GUIDED, arm, take off, start
    seed: int = 0
    runlog_path: str | None = None
    tlog_path: str | None = None
    link_timeout_s: float = 3.0  # local seconds without autopilot heartbeats -> link lost
    # system ids whose commands and parameter writes are obeyed (reads are answered to anyone)
    gcs_sysids: tuple[int, ...] = (255,)
    signing_key_path: str | None = None  # MAVLink 2 signing key file (onboard/app/signing.py)
    # with a key: the autopilot's own packets taken unsigned (one that cannot sign: PX4 v1.16);
    # everyone else's must still be signed (docs/SAFETY.md)
    autopilot_unsigned: bool = False
    history: int = 600  # tick records kept in memory (app.ticks, ~3 kB each); the run log keeps all
    watchdog_s: float = 3.0  # autopilot s a tick may run (or the io loop stall) before a report
    # autopilot s between returns of freed heap memory to the OS (glibc malloc_trim, by the idle
    # worker); 0: never. A tick's planning allocates tens of MB for a moment; without this the
    # allocator keeps the largest such peak resident for good (see docs/SAFETY.md, long flights)
    trim_memory_s: float = 60.0
    # DF senders accepted (onboard/app/df/udp_input.py); empty: the first peer whose datagram is valid
    df_sources: tuple[Source, ...] = ()
    df_rate_hz: float = DEFAULT_RATE_HZ  # datagrams/s per accepted DF sender; the excess is dropped
    # PX4's event metadata (its build's etc/extras/all_events.json.xz): its EVENTs said in words
    px4_events_path: str | None = None
    kraken: bool = False  # also read a KrakenSDR's DoA output at the scenario's kraken.url (kraken.py)
    # SCHED_FIFO priority of the io thread, the worker one below (onboard/app/realtime.py); 0: normal
    rt_priority: int = 0
    advise: bool = False  # start in advisory (pmon run --advise): plan and publish, command nothing
