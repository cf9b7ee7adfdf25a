import subprocess
import sys


def run(*args):
    return subprocess.run([sys.executable, "-m", "onboard.cli", *args], capture_output=True, text=True, timeout=120)


def test_check_config_ok_and_bad(tmp_path):
    ok = run("check-config")
    assert ok.returncode == 0 and "4 targets, 4 obstacles" in ok.stdout
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\n")
    res = run("check-config", str(bad))
    assert res.returncode == 2 and "origin: missing" in res.stderr and "Traceback" not in res.stderr


def test_simulate_runs_a_short_mission():
    res = run("simulate", "--ticks", "3")
    assert res.returncode == 0, res.stderr
    assert "position error after 3 ticks" in res.stdout
    assert "error per target [m]" in res.stdout and "final [m]" in res.stdout  # units, not eaten as markup


def test_bad_arguments_exit_nonzero():
    assert run("simulate", "--ticks", "0").returncode == 2
    assert run("fly").returncode == 2
