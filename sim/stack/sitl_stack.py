"""A SITL stack on loopback for ground-station work: the mock ArduCopter and the onboard app as
threads of one process, the live DF feed as a process, nothing launched by itself (an operator,
or a test, arms, takes off and starts monitoring). The rig of sim/stack/rig.py, set up so.

    with SitlStack(speedup=4) as st:       # ports picked by the OS
        st.gcs_url                          # tcp:127.0.0.1:PORT, a ground station's link
        st.start_feed()                     # DF scans start (when the vehicle is armed)

Or as a process, for a terminal session (docs/OPERATING.md):

    python -m sim.stack.sitl_stack --gcs-udp 14550     # then: pmon gcs status

Used by tests/gcs/test_gcs*.py and bench/gcs_latency.py. ``pmon demo`` is the self-flying version
(separate processes, --auto-launch).
"""
from __future__ import annotations

import signal
import sys
import threading
from dataclasses import replace

from sim.mock.autopilot import BootTimeline

from onboard.policy import DEFAULT as DEFAULT_POLICY
from onboard.policy import POLICIES
from sim.stack.rig import Rig, RigConfig


# the stack for ground-station work: mock and app in this process (a test looks inside them), no
# launch, the feed when asked (Rig.start_feed), ArduCopter's boot, 4x, the demo's vehicle
STACK = RigConfig(speedup=4.0, in_process=True, feed="later", feed_duration_s=600.0)


class SitlStack(Rig):
    """Mock autopilot (TCP ports: app, feed, GCS), onboard app, DF feed (``start_feed``): the
    rig of ``STACK`` with ``overrides`` (RigConfig's fields)."""

    def __init__(self, cfg: RigConfig = STACK, **overrides):
        super().__init__(replace(cfg, **overrides))


def main(argv=None) -> int:
    from onboard.argcheck import OUT_FILE, PORT, SEED, SPEEDUP, OneLineParser, fail, number

    p = OneLineParser(prog="python -m sim.stack.sitl_stack", description="A SITL stack on loopback for ground-station "
                      "work: the mock ArduCopter, the onboard app and the live DF feed, nothing launched by "
                      "itself (arm, take off and start from a ground station: docs/OPERATING.md).")
    p.add_argument("--speedup", type=SPEEDUP, default=1.0, help="autopilot s per wall s, (0, 1000] (default 1)")
    p.add_argument("--gcs-udp", type=PORT, default=14550, metavar="PORT",
                   help="stream to a ground station listening on udp 127.0.0.1:PORT (default 14550)")
    p.add_argument("--seed", type=SEED, default=1)
    p.add_argument("--ready-after", type=number(0.0, 600.0), default=BootTimeline.ready_s, metavar="S",
                   help="autopilot s after boot until the mock can arm (default "
                   f"{BootTimeline.ready_s:g}, as ArduCopter 4.4 SITL)")
    p.add_argument("--policy", choices=tuple(POLICIES), default=DEFAULT_POLICY,
                   help="the app's flight policy (pmon run --policy; default flight)")
    p.add_argument("--runlog", type=OUT_FILE, help="the app's JSONL run log")
    p.add_argument("--truth", type=OUT_FILE, help="the feed's truth JSONL")
    p.add_argument("--signing-key", metavar="FILE",
                   help="MAVLink 2 signing key file (mode 0600): mock, app and feed sign, and drop "
                   "unsigned packets; give the GCS the same file (pmon gcs --signing-key FILE)")
    args = p.parse_args(argv)
    import logging
    logging.basicConfig(level=logging.WARNING)
    from onboard.app.signing import KeyFileError
    try:
        st = SitlStack(speedup=args.speedup, seed=args.seed, gcs_udp_out=args.gcs_udp, runlog_path=args.runlog,
                       truth_path=args.truth, signing_key_path=args.signing_key, ready_s=args.ready_after,
                       policy=args.policy).start()
    except KeyFileError as exc:
        return fail(p.prog, str(exc))
    except OSError as exc:  # a log file's directory missing, a port in use ...
        return fail(p.prog, f"cannot open {exc.filename or 'a socket'}: {exc.strerror or exc}")
    st.start_feed()
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    print(f"sitl stack up: GCS on udpin:127.0.0.1:{args.gcs_udp} or {st.gcs_url}; speedup "
          f"{args.speedup:g}{'; signed' if st.key else ''}; Ctrl-C stops", flush=True)
    try:
        while not stop.wait(0.2):
            pass
    finally:
        st.stop()
        print("sitl stack stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
