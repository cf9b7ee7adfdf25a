import subprocess
import sys
from pathlib import Path

import pytest


def run(*args):
    return subprocess.run([sys.executable, "-m", "onboard.cli", *args], capture_output=True, text=True, timeout=120)


def main_rc(capsys, *args) -> tuple[int, str, str]:
    """``pmon ARGS`` through its entry point in this process (no Python start-up per case; the
    real program runs in the other tests here): (exit code, stdout, stderr)."""
    from onboard.cli import main
    try:
        rc = main(list(args))
    except SystemExit as exc:  # argparse
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def test_check_config_ok_and_bad(tmp_path, capsys):
    ok = run("check-config")
    assert ok.returncode == 0 and "4 targets, 4 obstacles" in ok.stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\n")
    rc, _, err = main_rc(capsys, "check-config", str(bad))
    assert rc == 2 and "origin: missing" in err and "Traceback" not in err


def test_simulate_runs_a_short_mission():
    res = run("simulate", "--ticks", "3")
    assert res.returncode == 0, res.stderr
    assert "position error after 3 ticks" in res.stdout
    assert "error per target [m]" in res.stdout and "final [m]" in res.stdout  # units, not eaten as markup


def test_bad_arguments_exit_nonzero(capsys):
    assert main_rc(capsys, "simulate", "--ticks", "0")[0] == 2
    assert main_rc(capsys, "fly")[0] == 2


def test_advise_with_auto_launch_is_refused_in_one_line(capsys):
    rc, _, err = main_rc(capsys, "run", "--advise", "--auto-launch", "--mavlink", "udpin:127.0.0.1:0")
    assert rc == 2 and err.strip() == ("pmon run: --advise and --auto-launch exclude each other "
                                       "(advisory commands nothing)"), err


def test_the_flight_program_loads_no_simulator_ground_station_or_lab_packages():
    """``pmon run`` (the companion computer's program) imports onboard/ and its runtime
    dependencies only: a flight install has none of these."""
    res = subprocess.run([sys.executable, "-X", "importtime", "-m", "onboard.cli", "run", "--help"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "--mavlink" in res.stdout
    modules = {line.split("|")[-1].strip() for line in res.stderr.splitlines() if line.startswith("import time:")}
    assert "onboard.app.run" in modules
    lab = sorted(m for m in modules if m.split(".")[0] in ("sim", "groundstation", "matplotlib", "dask", "rich",
                                                           "mavsdk", "distributed"))
    assert lab == []


def test_version_and_every_verb_listed():
    from importlib.metadata import version
    res = run("--version")
    assert res.returncode == 0 and res.stdout.strip() == f"pmon {version('passive-monitor')}"
    res = run("--help")
    assert res.returncode == 0
    for verb in ("run", "check-config", "replay", "demo", "simulate", "eval", "feed", "gcs"):
        assert f"\n    {verb}" in res.stdout, res.stdout
    assert run("demo", "--help").stdout.startswith("usage: pmon demo ")


def test_a_verb_whose_extra_is_not_installed_is_refused_in_one_line(monkeypatch, capsys):
    from importlib import metadata

    from onboard import cli

    real = metadata.distribution
    hidden = {"dask", "rich"}

    def distribution(name):
        if name.lower() in hidden:
            raise metadata.PackageNotFoundError(name)
        return real(name)
    monkeypatch.setattr(metadata, "distribution", distribution)
    assert cli.main(["eval", "--help"]) == 2  # refused before it parses anything
    err = capsys.readouterr().err
    assert err == "pmon eval: needs the 'sim' extra (rich, dask not installed): pip install 'passive-monitor[sim]'\n"
    assert cli.main(["gcs", "status"]) == 2
    assert capsys.readouterr().err == ("pmon gcs: needs the 'gcs' extra (rich not installed): "
                                       "pip install 'passive-monitor[gcs]'\n")
    from groundstation.cli import script  # the pmon-gcs program
    monkeypatch.setattr(sys, "argv", ["pmon-gcs", "status"])
    assert script() == 2 and capsys.readouterr().err.startswith("pmon-gcs: needs the 'gcs' extra (rich not")
    hidden.update({"matplotlib", "distributed"})  # the flight install: feed needs no extra
    with pytest.raises(SystemExit) as exc:
        cli.main(["feed", "--help"])
    assert exc.value.code == 0 and "usage: pmon feed" in capsys.readouterr().out


def test_the_ground_station_help_says_what_applies(capsys):
    rc, params, _ = main_rc(capsys, "gcs", "params", "--help")
    assert rc == 0
    for sub in ("list", "get", "set"):
        assert f"\n    {sub} " in params, params
    for offline in ("plot", "export"):
        rc, out, _ = main_rc(capsys, "gcs", offline, "--help")
        assert rc == 0 and "--json" in out and "--connect" not in out and "--timeout" not in out and "--sysid" not in out, out


def test_a_programs_help_says_what_it_is_in_whole_sentences():
    """argparse's description was the docstring's first line: cut mid-sentence where it wraps."""
    for argv in (["-m", "sim.stack.sitl_stack"], ["-m", "sim.mock.autopilot"], ["-m", "bench.latency"]):
        out = subprocess.run([sys.executable, *argv, "--help"], capture_output=True, text=True, timeout=60,
                             cwd=Path(__file__).resolve().parents[2]).stdout
        description = out.split("\n\n")[1]
        assert description.rstrip().endswith("."), (argv, description)


def test_check_config_names_each_experimental_setting_the_file_or_set_changes(tmp_path, capsys):
    """A research knob changed is named, one line each, after the rest; not an error. The paper's
    file states some at their defaults (the paper's values): nothing named."""
    rc, out, err = main_rc(capsys, "check-config")
    assert rc == 0 and "experimental" not in out, out
    f = tmp_path / "knob.yaml"
    f.write_text((Path(__file__).parents[2] / "config" / "paper.yaml").read_text()
                 + "tracking:\n  regularise_bandwidth: 0.3\n")
    rc, out, err = main_rc(capsys, "check-config", str(f), "--set", "planning.lookahead.n_headings=8",
                           "--set", "sensor.p_detect=0.9")
    assert rc == 0, err
    assert out.splitlines()[-2:] == [
        "tracking.regularise_bandwidth: experimental, 0.3 here (default 0.2): a research knob, unsupported in flight",
        "planning.lookahead.n_headings: experimental, 8 here (default 16): a research knob, unsupported in flight"]
    rc, _, err = main_rc(capsys, "check-config", "--set", "tracking.regularise_bandwidth=2")
    assert rc == 2 and "tracking.regularise_bandwidth: must be in [0, 1], got 2" in err


def test_check_config_says_what_the_filter_assumes_of_each_target(tmp_path, capsys):
    """A goal, candidates, a standing emitter and a target nobody knows: each line says the prior the
    flight policy's filter starts from, and what the paper's one-goal filter does instead."""
    import yaml

    data = yaml.safe_load((Path(__file__).parents[2] / "config" / "paper.yaml").read_text())
    data["targets"][1].update(goal=None, goals=["G", "W", "E"])
    data["targets"][2].update(goal=None, stationary=True)
    data["targets"][3].pop("goal")
    f = tmp_path / "intent.yaml"
    f.write_text(yaml.safe_dump(data))
    rc, out, err = main_rc(capsys, "check-config", str(f))
    assert rc == 0, err
    lines = out.splitlines()[1:]
    assert "T1 (its goal G): prior G 0.60; stationary 0.30" in lines[0] and "paper's filter: heads for G" in lines[0]
    assert "T2 (no goal, candidates G, W, E): prior G 0.20, W 0.20, E 0.20; stationary 0.30" in lines[1]
    assert "T3 (no goal, stationary): prior stationary 0.80, free 0.10, elsewhere 0.10" in lines[2]
    assert "T4 (no goal): prior stationary 0.50, free 0.25, elsewhere 0.25" in lines[3]
    assert "stays at its start (its goal unknown)" in lines[3]
