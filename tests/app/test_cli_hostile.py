"""Hostile command lines and scenario files (issue 23, part 5): each is refused with exit 2 and
one line on stderr, no traceback, no hang. Every case runs through its program's entry point
(``main(argv)`` of onboard.cli, sim.stack.sitl_stack, sim.mock.autopilot: what ``pmon``, ``python -m sim.stack.sitl_stack``
and ``python -m sim.mock.autopilot`` call), in this process with its file descriptors captured: a
Python start-up per case (numpy, scipy: ~1.5 s each) made this file 79 s of the suite. A few
cases, one of each program and kind, also run as the real program in a subprocess, bounded by
60 s. A hang fails either test (pytest-timeout, or the subprocess's bound). The first cases are
issue 23's list; the others found alongside them.
"""
from __future__ import annotations

import importlib
import os
import subprocess
import sys
import time
import traceback
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAPER = (ROOT / "config" / "paper.yaml").read_text()
HANG_S = 60.0


def files(tmp: Path) -> dict[str, str]:
    """Scenario and recording files a hostile user could name."""
    out = {}

    def write(name: str, text: str) -> None:
        (tmp / name).write_text(text)
        out[name] = str(tmp / name)
    write("bigint.yaml", PAPER.replace("dt_s: 1.0", "dt_s: 1" + "0" * 400))
    write("bigint_particles.yaml", PAPER + "tracking:\n  particles: 1" + "0" * 400 + "\n")
    write("bigint_5000.yaml", PAPER.replace("n_radial: 4", "n_radial: 1" + "0" * 4999))
    write("radians.yaml", PAPER.replace("sigma_deg: 1.0", "sigma_deg: 0.01745"))
    write("twice.yaml", PAPER.replace("  p_detect: 0.95", "  p_detect: 0.95\n  p_detect: 0.5"))
    write("deep.yaml", "name: " + "[" * 3000 + "]" * 3000 + "\n")
    write("tag.yaml", "name: !!python/object/apply:os.system [\"echo owned\"]\n")
    targets = "".join(f"  - {{name: X{i}, position_m: [10.0, 10.0, 0.0], goal: G}}\n" for i in range(100))
    write("many_targets.yaml", PAPER.replace("targets:", "targets:\n" + targets + "#", 1))
    write("huge.yaml", "# " + "x" * 2_000_000 + "\n")
    write("rec_bigint.jsonl", '{"t": 1' + "0" * 400 + ', "ch": 0, "bearings_rad": [0.1]}\n')
    write("rec_deep.jsonl", "[" * 100000 + "]" * 100000 + "\n")
    write("rec_types.jsonl", '{"t": 1.0, "ch": "0", "bearings_rad": 7}\n')
    write("nokraken.yaml", PAPER[:PAPER.index("\nkraken:")] + "\n")
    os.mkfifo(tmp / "fifo")
    out["fifo"] = str(tmp / "fifo")
    return out


def cases(f: dict[str, str]) -> list[tuple[list[str], str]]:
    """(argv as ``python -m MODULE ARGS...`` minus the interpreter, a part of the one line
    expected on stderr)."""
    pmon = ["-m", "onboard.cli"]
    run = pmon + ["run", "--mavlink", "udpin:127.0.0.1:0", "--df", "127.0.0.1:0"]
    stack = ["-m", "sim.stack.sitl_stack"]
    mock = ["-m", "sim.mock.autopilot", "--tcp", "127.0.0.1:0"]
    return [
        # issue 23's list
        (pmon + ["check-config", f["bigint.yaml"]], "dynamics.dt_s: must be in [0.1, 10] s, got 1000000... (401 digits)"),
        (pmon + ["check-config", f["deep.yaml"]], "nested too deeply"),
        (pmon + ["check-config", "/dev/zero"], "/dev/zero: a device, not a regular file"),
        (pmon + ["check-config", f["fifo"]], "a FIFO, not a regular file"),
        (run + ["--seed", "-1"], "argument --seed: must be >= 0"),
        (pmon + ["run", "--mavlink", "udpin:127.0.0.1:70000"], "argument --mavlink: port must be 0..65535"),
        (pmon + ["run", "--mavlink", "nonsense://x"], "argument --mavlink: want udpin|"),
        (pmon + ["run", "--df", "127.0.0.1:\u00b2"], "argument --df: port must be 0..65535"),
        (stack + ["--speedup", "-1"], "argument --speedup: must be in (0, 1000]"),
        (stack + ["--speedup", "0"], "argument --speedup: must be in (0, 1000]"),
        (stack + ["--speedup", "nan"], "argument --speedup: must be in (0, 1000]"),
        (stack + ["--gcs-udp", "70000"], "argument --gcs-udp: port must be 1..65535"),
        (pmon + ["eval", "--set", "tracking.control_mix=!!python/object/apply:os.system ['echo owned']"],
         "VALUE is not plain YAML"),
        # found alongside
        (pmon + ["check-config", f["bigint_particles.yaml"]], "tracking.particles: must be in [100, 20000], got 1000000..."),
        (pmon + ["check-config", f["bigint_5000.yaml"]], "uav.n_radial: must be in [0, 20], got 1000000... (5000 digits)"),
        (pmon + ["check-config", f["radians.yaml"]], "sensor.sigma_deg: must be in [0.05, 30] deg, got 0.01745"),
        (pmon + ["check-config", f["twice.yaml"]], "sensor.p_detect: key given twice (lines"),
        (pmon + ["check-config", f["tag.yaml"]], "not valid YAML"),
        (pmon + ["check-config", f["many_targets.yaml"]], "targets: must have at most 64 items"),
        (pmon + ["check-config", f["huge.yaml"]], "more than 1000000"),
        (pmon + ["check-config", "/tmp"], "a directory, not a regular file"),
        (pmon + ["replay", "/dev/zero"], "/dev/zero: a device, not a regular file"),
        (pmon + ["replay", f["fifo"]], "a FIFO, not a regular file"),
        (pmon + ["replay", "/tmp"], "/tmp: a directory, not a regular file"),
        (pmon + ["replay", f["rec_deep.jsonl"]], "rec_deep.jsonl:1: not a JSON record"),
        (pmon + ["replay", f["rec_bigint.jsonl"]], "rec_bigint.jsonl:1: no 'replay' field"),
        (run + ["--scenario", f["fifo"]], "a FIFO, not a regular file"),
        (pmon + ["run", "--mavlink", "/usr/bin/true"], "/usr/bin/true: not a serial device"),
        (pmon + ["run", "--mavlink", "udpin:127.0.0.1:-1"], "argument --mavlink: want udpin|"),
        (pmon + ["run", "--mavlink", "tcp:127.0.0.1:0"], "argument --mavlink: port must be 1..65535"),
        (run + ["--df-from", "10.0.0.x"], "argument --df-from: '10.0.0.x': want an IPv4 address"),
        (run + ["--df-rate", "nan"], "argument --df-rate: must be in [1, 1e+06]"),
        (run + ["--baud", "-5"], "argument --baud: must be in 50..20000000"),
        (run + ["--sysid", "1e3"], "argument --sysid: want an integer"),
        (run + ["--runlog", "/nonexistent/run.jsonl"], "no directory /nonexistent"),
        (pmon + ["eval", "--set", "name=" + "[" * 3000], "--set"),
        (pmon + ["eval", "--trials", "0"], "argument --trials: must be in 1..1000000"),
        (pmon + ["eval", "--truth", "teleport"], "argument --truth: invalid choice: 'teleport'"),
        (pmon + ["eval", "--truth", "wander", "--told"], "--told applies to --truth candidate_goal or stationary"),
        (pmon + ["eval", "--truth", "candidate_goal", "--set", "goals=[{name: G, center_m: [550, 150, 0], "
                 "size_m: [100, 100, 0]}]"], "--truth candidate_goal needs a scenario with at least 3 goal regions"),
        (pmon + ["eval", "--out", "/dev/null"], "argument --out: /dev/null: exists and is not a directory"),
        (pmon + ["eval", "--out", "/proc/pmon-out"], "argument --out: /proc/pmon-out: cannot make a directory in /proc"),
        (pmon + ["demo", "--out", "/dev/null"], "argument --out: /dev/null: exists and is not a directory"),
        (pmon + ["demo", "--seed", "-1"], "argument --seed: must be >= 0"),
        (pmon + ["demo", "--duration", "nan"], "argument --duration: must be in [5, 100000]"),
        (pmon + ["demo", "--df", "kraken", "--gcs", "70000"], "argument --gcs: port must be 1..65535"),
        (pmon + ["demo", "--df", "kraken", "--scenario", f["nokraken.yaml"]], "has no kraken.vfos"),
        (pmon + ["simulate", "--seed", "-1"], "argument --seed: must be >= 0"),
        (pmon + ["simulate", "--ticks", "0"], "argument --ticks: must be in 1..100000"),
        (pmon + ["feed", "live", "--mavlink", "nonsense://x"], "argument --mavlink: want udpin|"),
        (pmon + ["feed", "replay", "/dev/zero"], "/dev/zero: a device, not a regular file"),
        (pmon + ["feed", "replay", f["fifo"]], "a FIFO, not a regular file"),
        (pmon + ["feed", "replay", f["rec_bigint.jsonl"]], "rec_bigint.jsonl:1: 1000000"),
        (pmon + ["feed", "replay", f["rec_deep.jsonl"]], "rec_deep.jsonl:1: not JSON"),
        (pmon + ["feed", "replay", f["rec_types.jsonl"]], "rec_types.jsonl:1: ch must be an integer"),
        (pmon + ["feed", "replay", f["rec_types.jsonl"], "--to", "127.0.0.1:\u00b2"], "argument --to: port must be"),
        (pmon + ["feed", "live", "--mavlink", "tcp:127.0.0.1:5760", "--seed", "-3"], "argument --seed: must be >= 0"),
        (stack + ["--speedup", "inf"], "argument --speedup: must be in (0, 1000]"),
        (stack + ["--seed", "-1"], "argument --seed: must be >= 0"),
        (stack + ["--truth", "/nonexistent/truth.jsonl"], "no directory /nonexistent"),
        (mock + ["--speedup", "0"], "argument --speedup: must be in (0, 1000]"),
        (mock + ["--udp", "127.0.0.1:70000"], "argument --udp: port must be 1..65535"),
        (mock + ["--param", "NOPE=1"], "unknown parameter 'NOPE'"),
        (mock + ["--param", "WPNAV_SPEED=nan"], "argument --param: want NAME=VALUE with a finite number"),
        (mock + ["--max-lag", "nan"], "argument --max-lag: must be in (0, 3600]"),
    ]


# the first case expecting each of these also runs as the real program: each program once, a YAML
# tag, a FIFO (an open would block), a recording, the evaluation's --set
AS_PROGRAMS = ("dynamics.dt_s: must be in", "a FIFO, not a regular file", "argument --speedup: must be in (0, 1000]",
               "unknown parameter 'NOPE'", "VALUE is not plain YAML", "not valid YAML",
               "rec_types.jsonl:1: ch must be an integer")


def _in_process(argv: list[str], capfd) -> tuple[int, str, str]:
    """``python -m MODULE ARGS`` as its entry point in this process: (exit code, stdout, stderr),
    an exception escaping main() as the interpreter would print it (exit 1)."""
    main = importlib.import_module(argv[1]).main
    err_tail = ""
    try:
        rc = main(argv[2:])
    except SystemExit as exc:  # argparse
        rc = exc.code
    except Exception:  # a crash (not pytest-timeout's Failed, a BaseException: a hang fails the test)
        rc, err_tail = 1, traceback.format_exc()
    out, err = capfd.readouterr()
    return rc, out, err + err_tail


def _judge(argv, want, rc, out, err, failures) -> None:
    lines = [x for x in err.splitlines() if x.strip()]
    if rc != 2 or len(lines) != 1 or "Traceback" in err or want not in err:
        failures.append((argv[1:], rc, err[-600:]))
    assert "owned" not in out + err, "a YAML tag was executed"


@pytest.mark.timeout(120)  # a hang fails it
def test_every_hostile_case_exits_2_with_one_line_and_no_traceback(tmp_path, capfd, monkeypatch):
    todo = cases(files(tmp_path))
    monkeypatch.chdir(tmp_path)
    capfd.readouterr()
    failures: list = []
    for argv, want in todo:
        _judge(argv, want, *_in_process(argv, capfd), failures)
    assert failures == [], failures


@pytest.mark.timeout(300)
def test_as_real_programs_a_few_cases_exit_2_with_one_line_and_no_traceback(tmp_path):
    every = cases(files(tmp_path))
    todo = [next(c for c in every if w in c[1]) for w in AS_PROGRAMS]
    assert {argv[1] for argv, _ in todo} == {"onboard.cli", "sim.stack.sitl_stack", "sim.mock.autopilot"}
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    failures: list = []
    batch = [(subprocess.Popen([sys.executable, *argv], cwd=tmp_path, env=env, stdin=subprocess.DEVNULL,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True), time.monotonic())
             for argv, _ in todo]
    for (argv, want), (p, t0) in zip(todo, batch):
        try:
            out, err = p.communicate(timeout=max(HANG_S - (time.monotonic() - t0), 1.0))
        except subprocess.TimeoutExpired:
            p.kill()
            p.communicate()
            failures.append((argv[1:], "hung"))
            continue
        _judge(argv, want, p.returncode, out, err, failures)
    assert failures == [], failures
