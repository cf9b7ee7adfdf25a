"""``pmon demo``: the whole system on loopback, as separate processes, paper scenario, accelerated.

    mock autopilot  (python -m sim.mock.autopilot, 2 TCP ports picked by the OS, home = the UAV's start)
    onboard app     (pmon run --auto-launch: GUIDED, arm, take off, monitor)
    DF feed         (pmon feed live --start altitude: truth world and DF scans from the moment the
                     UAV is armed at the mission altitude h, truth JSONL; with --df kraken a
                     simulated KrakenSDR serving its output, which the app reads: docs/KRAKENSDR.md)

stood up by sim/stack/rig.py. Separate processes because that is how it flies (the app knows the
autopilot only through MAVLink, the feed only through its own MAVLink link and UDP) and because
two busy Python loops (core tick and truth step) then run on two cores instead of sharing one GIL.

The scored mission is the paper's (and ``pmon eval``'s): the UAV at s_0 at altitude h at t = 0,
the targets at their mu_0, 100 scans. The take-off and climb come before it (the feed starts its
world at h; the app, which starts monitoring only with DF data, monitors from the first scan on):
with the world started at the arming, the first 17 scans were taken during the launch, with no
plan, and the mission scored was not the one the scale beside it was measured on
(bench/demo_world.py: that cost 2.2 m of the five seeds' mean RMSE, docs/SITL.md).

The demo waits for the feed's last scan, stops everything (also on Ctrl-C or an error), then
scores the run log against the truth: a per-target error table and a PNG of the flight. A launch
the app aborts (a link loss, a disarm) or gives up ends the demo at once, exit 1, with the app's
reason: the app flies again only when an operator says so.
"""
from __future__ import annotations

import argparse
import json
import math
import re
import signal
import time
from pathlib import Path

import numpy as np


# autopilot s until the demo's mock can arm: it boots as ArduCopter does (no fix, no origin,
# arming refused until then) but in 5 s rather than ArduCopter SITL's ~43 s
DEMO_READY_S = 5.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    from onboard.argcheck import OUT_DIR, PORT, SEED, number
    p.add_argument("--out", default="pmon-demo", type=OUT_DIR, help="output directory (default ./pmon-demo/)")
    p.add_argument("--speedup", default="auto",
                   help="autopilot seconds per wall second, or 'auto': from a measured core tick")
    p.add_argument("--duration", type=number(5, 100_000), default=None,
                   help="seconds of mission (DF scans), 5 s or more; default: the scenario's (100 s)")
    p.add_argument("--scenario", default="paper")
    p.add_argument("--seed", type=SEED, default=1)
    from onboard.policy import DEFAULT, POLICIES
    p.add_argument("--policy", choices=tuple(POLICIES), default=DEFAULT,
                   help="the app's flight policy (pmon run --policy; default flight)")
    p.add_argument("--gcs", metavar="PORT", type=PORT,
                   help="also stream the autopilot to udp 127.0.0.1:PORT (e.g. MAVProxy --master udpin:...)")
    from sim.truth.kinds import TRUTH_KINDS
    p.add_argument("--truth", choices=TRUTH_KINDS, default="nominal",
                   help="how the true targets move (default nominal: as the scenario says; stationary: the "
                        "transmitter hunt; docs/RESULTS.md)")
    p.add_argument("--df", choices=("datagram", "kraken"), default="datagram",
                   help="the DF: datagram (default: the feed's datagrams) or kraken (a simulated KrakenSDR's "
                        "output over HTTP, which the app reads: docs/KRAKENSDR.md)")
    p.add_argument("--autopilot", choices=("mock", "ardupilot", "px4"), default="mock",
                   help="mock (default: sim/mock/autopilot.py, booting in 5 s), ardupilot: ArduPilot's own "
                   "ArduCopter SITL ($PMON_ARDUPILOT_SITL or ../shared/ardupilot/arducopter; ~43 s of "
                   "simulated boot before it can arm), or px4: PX4's own SITL, SIH quad ($PMON_PX4_SITL or "
                   "../shared/px4; armable ~5 s after boot, its take-off ~25 s)")




def measure_tick_s(sc, n: int = 10, warmup: int = 2, clock=time.thread_time, seed: int = 0) -> float:
    """Median CPU time of a core tick on this machine, on the bearings a flight of ``sc`` sees at
    its start: the scenario's targets stepped by the truth simulator (sim/truth), scanned by its DF
    model from the UAV, which moves to each tick's planned next position (the evaluation's closed
    loop, sim/evaluation/trials.py). Those first ticks are the mission's dearest (the demo's
    ticks fall to about half their cost by mid-mission): the ones a speed-up must leave room for.
    Random bearings, measured before, agree with no motion mode and re-seed every target each
    tick, a cost that moved with what the draws triggered. ``clock`` (``time.thread_time``: the
    tick runs on this thread) so the choice follows the machine more than what else runs at start
    (with one BLAS thread: ``measure_tick_apart``). The first ``warmup`` ticks are excluded: their
    guidance still searches every target's faces from scratch."""
    from onboard.core.guidance.predictor import GuidanceWorkspace
    from onboard.core.monitor import MonitorSetup, Scan, UavState, initial_state, tick
    from sim.truth.sensors import DirectionFinder, df_scan
    from sim.truth.world import simulate_truth

    setup = MonitorSetup.from_scenario(sc)
    truth_rng, sensor_rng, filter_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(3))
    truth = simulate_truth(sc, warmup + n, truth_rng)
    df = DirectionFinder.from_config(sc.sensor)
    state, ws = initial_state(setup, filter_rng), GuidanceWorkspace()
    uav, vel = np.array([*sc.uav.start_m[:2], sc.uav.altitude_m]), np.zeros(2)
    times = []
    for k in range(warmup + n):
        scans = [Scan(uav.copy(), df_scan(truth[k], uav, df, sensor_rng))]
        t0 = clock()
        state, res = tick(setup, state, scans, filter_rng, plan_from=UavState(uav, vel), workspace=ws)
        times.append(clock() - t0)
        p = res.planning
        if p is not None and p.index is not None:  # fly to the plan's next point, at its velocity there
            uav = np.asarray(p.position, float).copy()
            vel = np.zeros(2) if p.velocities is None else np.asarray(p.velocities[p.index], float)[:2].copy()
    return float(np.median(times[warmup:]))


BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def measure_tick_apart(scenario: str, policy: str, timeout_s: float = 120.0) -> float:
    """``measure_tick_s`` of ``scenario`` under ``policy``, in a child process with one BLAS thread.
    With a BLAS thread per core a busy process beside it made the same tick's CPU time scatter
    1.1-2.3x (the main thread spins waiting for a BLAS thread the busy process holds off its core);
    with one it stayed as idle (docs/DEPLOY.md, "The demo under load"). Idle, both took the same."""
    import os
    import subprocess
    import sys

    code = ("import sys; from onboard.config import load_scenario; from onboard.policy import with_policy; "
            "from sim.stack.demo import measure_tick_s; "
            "print(repr(measure_tick_s(with_policy(load_scenario(sys.argv[1]), sys.argv[2]))))")
    p = subprocess.run([sys.executable, "-c", code, scenario, policy], capture_output=True, text=True,
                       timeout=timeout_s, env={**os.environ, **dict.fromkeys(BLAS_THREADS, "1")})
    if p.returncode != 0:
        raise RuntimeError(f"measuring the core tick failed: {p.stderr.strip()[-500:]}")
    return float(p.stdout.split()[-1])


def choose_speedup(tick_s: float) -> float:
    """A tick must end before the next scan is due (1 autopilot s: 1 / speedup wall s), else
    that scan is skipped. ``tick_s`` (``measure_tick_s``: the mission's first, dearest ticks, CPU
    time) times the speedup stays at most 0.2 autopilot s, leaving 5x for the worst ticks (the
    first, the guidance's search from scratch, 5-9x the measure), for the feed and the mock
    sharing the cores and for a loaded machine: on an idle 2-core Xeon VM 59 ms gave 3x, 45 s
    walls with 0 of 100 scans skipped, and the same beside two busy processes, 47-48 s walls
    (docs/DEPLOY.md, "The demo under load"). Between 1x and 8x, in steps of 0.5."""
    return float(min(8.0, max(1.0, math.floor(0.2 / max(tick_s, 1e-3) * 2) / 2)))


def _speedup(args, console) -> tuple[float, float | None] | None:
    """The autopilot's speedup, measured ('auto') or given, and the tick measured (s; None when
    given); None (said why) when out of range."""
    if args.speedup == "auto":
        tick_s = measure_tick_apart(args.scenario, args.policy)  # the tick the app will run
        speedup = choose_speedup(tick_s)
        console.print(f"core tick measured {tick_s * 1e3:.0f} ms of CPU -> speedup {speedup:g}x")
        return speedup, tick_s
    try:
        speedup = float(args.speedup)
    except ValueError:
        speedup = float("nan")
    if not 0.1 <= speedup <= 50:
        console.print(f"pmon demo: --speedup must be 'auto' or a number in [0.1, 50], got {args.speedup!r}")
        return None
    return speedup, None


def _refusal(args, duration: int, sc) -> str | None:
    """Why the demo cannot run as asked, said before any process starts; None if it can."""
    if duration < 5:
        return "--duration must be >= 5 s"
    if args.df == "kraken" and not sc.kraken.vfos:
        return (f"--df kraken: scenario {sc.name!r} has no kraken.vfos (which VFO frequency is which target? "
                "docs/KRAKENSDR.md)")
    if args.autopilot != "mock":
        from sim.firmware.ardupilot import skip_reason as ardupilot_problem
        from sim.firmware.px4 import skip_reason as px4_problem
        if (why := (ardupilot_problem if args.autopilot == "ardupilot" else px4_problem)()):
            return f"--autopilot {args.autopilot}: {why}"
        if args.gcs:
            return (f"--gcs streams from the mock; with {args.autopilot} connect to its ground-station port "
                    "(the URL printed at start)")
    return None


def run(args) -> int:
    from rich.console import Console

    from onboard.config import load_scenario
    from sim.stack.rig import APP_PORT, FEED_PORT, GCS_PORT, Rig, RigConfig

    console = Console()
    wall0 = time.monotonic()
    # Ctrl-C stops every process even when started from a shell that ignores SIGINT (a
    # background job without job control inherits SIG_IGN, and Python then never raises
    # KeyboardInterrupt); the children get the default disposition back at exec
    signal.signal(signal.SIGINT, signal.default_int_handler)
    sc = load_scenario(args.scenario)
    duration = int(round(args.duration if args.duration is not None else sc.mission.duration_s))
    if (why := _refusal(args, duration, sc)):
        from onboard.argcheck import fail
        return fail("pmon demo", why)  # one line on stderr (the console wraps at its width)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    if (chosen := _speedup(args, console)) is None:
        return 2
    speedup, tick_s = chosen
    mock = args.autopilot == "mock"
    # the demo's vehicle; the mock boots in DEMO_READY_S, ArduPilot's SITL as it does; PX4 with
    # the offboard-loss action docs/SITL.md recommends
    extra = {}
    if args.autopilot == "px4":
        from sim.firmware.px4 import RECOMMENDED_PARAMS as PX4_PARAMS
        extra["params"] = dict(PX4_PARAMS)
    rig = Rig(RigConfig(scenario=args.scenario, policy=args.policy, seed=args.seed, feed_seed=args.seed,
                        autopilot=args.autopilot, speedup=speedup, ready_s=DEMO_READY_S if mock else None,
                        ports=2 if mock else 3, gcs_udp_out=args.gcs, auto_launch=True,
                        feed_duration_s=duration, feed_start="altitude", df=args.df, truth_kind=args.truth,
                        **extra).records_in(out))
    try:
        with rig:
            if not mock:
                firmware = {"ardupilot": "ArduCopter SITL -I", "px4": "PX4 SITL (SIH) -i"}[args.autopilot]
                console.print(f"{firmware} {rig.ap.instance}; a ground station: {rig.url(GCS_PORT)} "
                              f"(e.g. pmon gcs --connect {rig.url(GCS_PORT)} view)")
            console.print(f"{args.autopilot} autopilot {rig.url(APP_PORT)} (app) {rig.url(FEED_PORT)} "
                          f"(feed), DF {f'udp:{rig.df_port}' if rig.kraken_url is None else rig.kraken_url}, "
                          f"speedup {speedup:g}x, policy {args.policy}; logs in {out}/")
            _fly(rig, duration, console)
    except KeyboardInterrupt:
        console.print("interrupted: stopping every process")
        return 130
    except RuntimeError as exc:
        console.print(f"pmon demo: {exc}")
        return 1
    report = score(out / "run.jsonl", out / "truth.jsonl", sc)
    _print_report(console, report, sc, args.policy)
    png = plot(out / "run.jsonl", out / "truth.jsonl", sc, out / "flight.png")
    measured_ms = None if tick_s is None else round(tick_s * 1e3, 1)
    (out / "report.json").write_text(json.dumps({**report, "speedup": speedup, "tick_measured_ms": measured_ms,
                                                 "wall_s": round(time.monotonic() - wall0, 1)}, indent=1))
    console.print(f"flight plot: {png} (map tools: {png.with_suffix('.geojson')})   run log: {out / 'run.jsonl'}   "
                  f"tlog: {out / 'app.tlog'}")
    console.print(f"wall time {time.monotonic() - wall0:.1f} s")
    return 0


def _fly(rig, duration: int, console) -> None:
    """A progress bar until the feed's last scan, then the app's tick of it (and no longer: then
    it would coast on no data). RuntimeError when a program ends early or the feed fails."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    truth_path, run_path = Path(rig.cfg.truth_path), Path(rig.cfg.runlog_path)
    app_log = _Tail(Path(rig.app.log.name))
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed:.0f}/{task.total:.0f} s"),
                  TextColumn("{task.fields[info]}"), TimeElapsedColumn(), console=console) as prog:
        task = prog.add_task("mission", total=duration, info="taking off")
        while rig.feed.p.poll() is None:
            time.sleep(0.25)
            if (why := rig.problem()):
                raise RuntimeError(why.replace(" exited", " exited early"))
            if (stopped := launch_stopped(app_log.read())):
                # the app flies again only when an operator says so (onboard/app/autopilot/launch.py): the
                # feed, waiting for the arming that starts its world, would wait for ever
                raise RuntimeError(f"the app's launch stopped ({stopped}); it flies again only when told "
                                   f"(pmon gcs launch); see {rig.app.log.name}")
            n = max(_count_lines(truth_path) - 1, 0)
            last = _last_json(run_path)
            info = ""
            if last:
                state = {0: "idle", 1: "monitoring", 2: "paused", 3: "pilot", 4: "fault"}.get(last["state"], "?")
                info = f"{state}  t={last['t']:.0f}s  tick {last['tick_ms']:.0f} ms"
            prog.update(task, completed=n, info=info)
        prog.update(task, completed=duration)
    if rig.feed.p.returncode != 0:
        raise RuntimeError(f"feed failed (code {rig.feed.p.returncode}); see {rig.feed.log.name}")
    last = _last_json(truth_path)
    deadline = time.monotonic() + 5.0
    while last and time.monotonic() < deadline and ((_last_json(run_path) or {}).get("t", -1) < last["t"]):
        time.sleep(0.05)


_LAUNCH_STOPPED = re.compile(r"PMON: (.*launch (?:aborted|failed).*)")


def launch_stopped(text: str) -> str | None:
    """The app's line saying its launch sequence ended without a flight (aborted: a link loss, a
    disarm, the vehicle taken out of the launch's modes; failed: no climb), in ``text`` (log lines)."""
    m = _LAUNCH_STOPPED.search(text)
    return m.group(1).strip() if m else None


class _Tail:
    """The lines a growing log gained since the last read (whole lines only)."""

    def __init__(self, path: Path):
        self.path, self.at = Path(path), 0

    def read(self) -> str:
        try:
            with self.path.open("rb") as f:
                f.seek(self.at)
                chunk = f.read()
        except OSError:
            return ""
        end = chunk.rfind(b"\n") + 1
        self.at += end
        return chunk[:end].decode("utf-8", "replace")


def _count_lines(path: Path) -> int:
    try:
        with open(path, "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


def _last_json(path: Path):
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - 20000))
            lines = f.read().splitlines()
        for line in reversed(lines):
            try:
                return json.loads(line)
            except ValueError:
                continue
    except OSError:
        return None
    return None


def load_run(run_path: Path, truth_path: Path):
    ticks = [json.loads(l) for l in open(run_path) if l.strip()]
    truth = [json.loads(l) for l in open(truth_path) if l.strip()]
    truth = [r for r in truth if "header" not in r]
    return ticks, truth


WINDOW_S = 10.0  # pmon eval scores a mission from 10 s after its first scan (sim/evaluation/trials.py)
# What one demo mission's figure is worth: pmon eval paper's 100 missions of the same scenario,
# the per-mission RMSE from 10 s on over all targets (r_n), median and 10th-90th percentile, from
# the files named (docs/RESULTS.md; tests/sim/test_demo.py holds these figures to the files)
SCALE = {
    "flight": ("the flight default at ArduCopter's stock limits (flight@stock)",
               "docs/results_flight_default/intent/nominal/per_trial.csv", "flight@stock", 22.0, 17.4, 38.7),
    "paper": ("the paper's rule with 20 m jumps, which no copter flies (greedy_l1)",
              "docs/results_flight_default/per_trial.csv", "greedy_l1", 23.1, 19.0, 36.7),
    "hover": ("a UAV hovering at its start (hover)", "docs/results_flight_default/per_trial.csv", "hover",
              24.2, 19.7, 39.1),
    "fixed3": ("three fixed DFs (fixed3)", "docs/results_flight_default/per_trial.csv", "fixed3", 8.0, 7.4, 8.4),
}


def score(run_path: Path, truth_path: Path, sc) -> dict:
    """Position errors of the app's estimates against the truth at the same scan times, and how
    the ticks went (their states, their wall times)."""
    ticks, truth = load_run(run_path, truth_path)
    by_t = {round(r["t"], 3): r for r in truth}
    errs, times = [], []
    for tk in ticks:
        tr = by_t.get(round(tk["t"], 3))
        if tr is None:
            continue
        est = np.array(tk["means"])[:, :2]
        true = np.array(tr["targets"])[:, :2]
        errs.append(np.linalg.norm(est - true, axis=1))
        times.append(tk["t"])
    errs = np.array(errs)
    sent = [tk for tk in ticks if tk.get("sent") and tk.get("latency_ms") is not None]
    lat = [tk["latency_ms"] for tk in sent]
    n = len(errs)
    half = errs[n // 2:] if n else errs
    t0 = truth[0]["t"] if truth else None
    window = errs[np.asarray(times) - t0 >= WINDOW_S] if n else errs
    first_monitoring = next((i for i, tk in enumerate(ticks) if tk["state"] == 1), len(ticks))
    launch = ticks[:first_monitoring]

    def median(xs):
        return float(np.median(xs)) if len(xs) else None
    return {
        "targets": [t.name for t in sc.targets],
        "scored_ticks": n,
        "scans": len(truth),
        "first_scan_t": t0,
        "final_m": errs[-1].round(2).tolist() if n else [],
        "rmse_m": np.sqrt((errs ** 2).mean(axis=0)).round(2).tolist() if n else [],
        "rmse_second_half_m": np.sqrt((half ** 2).mean(axis=0)).round(2).tolist() if n else [],
        "rmse_window_m": np.sqrt((window ** 2).mean(axis=0)).round(2).tolist() if len(window) else [],
        "mission_rmse_m": round(float(np.sqrt((window ** 2).mean())), 2) if len(window) else None,
        "ticks": len(ticks),
        "monitoring_ticks": sum(1 for tk in ticks if tk["state"] == 1),
        "launch_ticks": len(launch),
        "setpoints_from_ticks": sum(1 for tk in ticks if tk.get("sent")),
        "latency_ms_median": median(lat),
        "tick_ms_median": median([tk["tick_ms"] for tk in ticks]),
        "tick_ms_median_sent": median([tk["tick_ms"] for tk in sent]),
        "send_ms_median": median([tk["latency_ms"] - tk["tick_ms"] for tk in sent]),
        "tick_ms_median_launch": median([tk["tick_ms"] for tk in launch]),
        "skipped": sum(tk.get("skipped_before", 0) for tk in ticks),
    }


def _print_report(console, rep: dict, sc, policy: str) -> None:
    from rich.markup import escape
    from rich.table import Table

    table = Table(title=f"estimate error at the {rep['scored_ticks']} scans")
    for col in ("target", "final [m]", "RMSE [m]", f"RMSE from {WINDOW_S:g} s [m]"):
        table.add_column(escape(col), justify="right")  # else rich reads "[m]" as markup and drops it
    for j, name in enumerate(rep["targets"]):
        if rep["final_m"]:
            window = f"{rep['rmse_window_m'][j]:.1f}" if rep["rmse_window_m"] else "-"
            table.add_row(name, f"{rep['final_m'][j]:.1f}", f"{rep['rmse_m'][j]:.1f}", window)
    console.print(table)
    for line in _report_lines(rep, sc, policy):
        console.print(escape(line))


def _report_lines(rep: dict, sc, policy: str) -> list[str]:
    """What the figures mean: the mission's clock and ticks, their times, and the scale."""
    other = rep["ticks"] - rep["monitoring_ticks"] - rep["launch_ticks"]
    lines = [f"{rep['scans']} scans, the first at autopilot t = {rep['first_scan_t'] or float('nan'):.0f} s (its "
             f"clock counts from boot); {rep['scored_ticks']} scored (a tick's estimates against the truth), "
             f"{rep['skipped']} skipped at an overrun; {rep['ticks']} ticks: {rep['monitoring_ticks']} monitoring "
             f"({rep['setpoints_from_ticks']} setpoints), {rep['launch_ticks']} before, in the launch (tracking only)"
             + (f", {other} in other states" if other else "")]
    if rep["latency_ms_median"] is not None:
        launch = (f"; launch ticks {rep['tick_ms_median_launch']:.0f} ms"
                  if rep["tick_ms_median_launch"] is not None else "")
        lines.append(f"monitoring tick, wall-time median: core {rep['tick_ms_median_sent']:.0f} ms, scan to setpoint "
                     f"{rep['latency_ms_median']:.0f} ms (the tick + {rep['send_ms_median']:.1f} ms to send){launch}")
    if sc.name == "paper" and rep["mission_rmse_m"] is not None:
        rows = [SCALE.get(policy, SCALE["flight"]), SCALE["hover"], SCALE["fixed3"]]
        lines.append(f"scale (RMSE from {WINDOW_S:g} s, all targets: pmon eval's per-mission figure): this mission "
                     f"{rep['mission_rmse_m']:.1f} m; pmon eval paper, 100 missions, median (10-90 %): "
                     + ", ".join(f"{what} {med:.1f} m ({lo:.1f}-{hi:.1f})" for what, _, _, med, lo, hi in rows)
                     + " (docs/RESULTS.md)")
    return lines


def plot(run_path: Path, truth_path: Path, sc, png: Path) -> Path:
    """flight.png, and flight.geojson beside it (groundstation/plot.py, groundstation/export.py)."""
    from groundstation.export import write
    from groundstation.plot import draw, load

    flight = load(run_path, truth_path)
    write(flight, sc, png.with_suffix(""), formats=("geojson",))
    return draw(flight, png, scenario=sc, dpi=120,
                title="pmon demo: UAV path, true (solid) and estimated (dashed) tracks, 1-sigma ellipses every 10 ticks")
