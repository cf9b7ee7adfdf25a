"""Generated worlds (sim/truth/worlds.py) and the evaluation across them (sim/evaluation/across_worlds.py): a world is
the same for the same (family, seed, index) in any process, passes the scenario validator, reads
back from its file as the same scenario, has its family's properties, and ``pmon eval --worlds``
pairs the methods per world as ``pmon eval FILE`` runs that world."""
import csv
import json
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from onboard.config import load_scenario, parse_scenario
from onboard.settings.sections import Box
from onboard.core.obstacles import Obstacles
from sim.evaluation import trials as ev
from sim.evaluation import across_worlds as we
from sim.truth import worlds as W

ROOT = Path(__file__).resolve().parents[2]
N = 8  # worlds per family in the fast checks
H = 40.0  # uav.altitude_m's default, what the generator measures heights against


def worlds(family, n=N, seed=11):
    return [W.draw_world(family, seed, i) for i in range(n)]


def low(sc):
    return [o for o in sc.obstacles if o.size_m[2] < sc.uav.altitude_m]


def tall(sc):
    return [o for o in sc.obstacles if o.size_m[2] > sc.uav.altitude_m]


def test_a_world_is_its_family_seed_and_index_in_any_process():
    code = ("from sim.truth.worlds import world_yaml, FAMILIES; "
            "print('\\n'.join(world_yaml(f, 5, 3) for f in FAMILIES))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         env={"PYTHONHASHSEED": "123", **__import__("os").environ})
    assert out.returncode == 0, out.stderr
    assert out.stdout == "\n".join(W.world_yaml(f, 5, 3) for f in W.FAMILIES) + "\n"
    for f in W.FAMILIES:
        a = W.world_tree(f, 5, 3)
        assert a == W.world_tree(f, 5, 3)
        assert a != W.world_tree(f, 6, 3) and a != W.world_tree(f, 5, 4), f  # another seed, another index


@pytest.mark.parametrize("family", W.FAMILIES)
def test_every_world_passes_the_validator_and_reads_back_from_its_file(family, tmp_path):
    paths = W.write_worlds(family, N, 11, tmp_path)
    for i, path in enumerate(paths):
        sc = W.draw_world(family, 11, i)
        assert parse_scenario(W.world_tree(family, 11, i)) == sc
        assert load_scenario(path) == sc  # the file a user opens is the world
        assert W.unreachable(sc) is None
        assert sc.area.min_m == (0.0, 0.0, 0.0) and sc.area.max_m == (1000.0, 1000.0, 1000.0)
        assert len(sc.goals) >= 3  # --truth candidate_goal runs on every world
        for t in sc.targets:
            assert t.goal is not None
            d = math.dist(t.position_m[:2], sc.goal_named(t.goal).center_m[:2])
            assert d >= W.FROM_GOAL_M, (sc.name, t.name, d)


def test_the_reachability_check_finds_a_walled_in_target():
    sc = W.draw_world("open", 11, 0)
    x, y, _ = sc.targets[0].position_m
    walls = tuple(Box(f"W{i}", (x + dx, y + dy, 20.0), size, 0.0) for i, (dx, dy, size) in enumerate([
        (0, 60, (160.0, 20.0, 40.0)), (0, -60, (160.0, 20.0, 40.0)),
        (60, 0, (20.0, 160.0, 40.0)), (-60, 0, (20.0, 160.0, 40.0))]))
    walled = replace(sc, obstacles=walls)
    assert W.unreachable(walled) == f"target T1 cannot reach goal {sc.targets[0].goal}"
    assert W.unreachable(replace(sc, obstacles=walls[:3])) is None  # one side open


def test_town_has_six_to_eight_buildings_some_overflown_and_some_on_the_targets_ways():
    for sc in worlds("town"):
        assert 6 <= len(sc.obstacles) <= 8 and 3 <= len(sc.targets) <= 5
        assert len(low(sc)) >= 2 and len(tall(sc)) >= 2, sc.name
        assert all(o.size_m[2] <= H - 10.0 for o in low(sc))  # the UAV keeps its 10 m over them
        ground = Obstacles.from_boxes(sc.obstacles).extruded(0.0)
        starts = np.array([t.position_m for t in sc.targets])
        ends = np.array([sc.goal_named(t.goal).center_m for t in sc.targets])
        assert ground.segments_cross(starts, ends).any(), sc.name  # some target must go round


def test_open_has_three_targets_and_at_most_one_obstacle():
    scs = worlds("open", 16)
    assert all(len(sc.targets) == 3 and len(sc.obstacles) <= 1 for sc in scs)
    assert {len(sc.obstacles) for sc in scs} == {0, 1}


def test_crowd_has_six_targets_converging_from_all_sides_past_three_or_four_obstacles():
    for sc in worlds("crowd"):
        assert len(sc.targets) == 6 and 3 <= len(sc.obstacles) <= 4
        assert len(low(sc)) >= 1 and len(tall(sc)) >= 1
        assert len({t.goal for t in sc.targets}) == 1
        centre = np.array(sc.goal_named(sc.targets[0].goal).center_m[:2])
        angles = np.sort([math.atan2(t.position_m[1] - centre[1], t.position_m[0] - centre[0]) for t in sc.targets])
        gaps = np.diff(np.r_[angles, angles[0] + 2 * math.pi])
        assert gaps.max() < math.radians(120), sc.name  # from all sides: no side left out
        assert all(math.dist(t.position_m[:2], centre) > 300 for t in sc.targets)


def test_corridor_targets_are_on_a_road_between_two_rows_of_buildings():
    for sc in worlds("corridor"):
        a, b = (np.array(sc.goal_named(n).center_m[:2]) for n in ("R1", "R2"))
        u = (b - a) / np.linalg.norm(b - a)
        normal = np.array([-u[1], u[0]])

        def across(p):
            return float((np.asarray(p[:2]) - a) @ normal)
        assert all(abs(across(t.position_m)) < 30 and t.goal in ("R1", "R2") for t in sc.targets)
        assert 3 <= len(sc.targets) <= 6
        sides = [across(o.center_m) for o in sc.obstacles]
        assert min(sides) < -40 and max(sides) > 40, sc.name  # a row either side
        across_size = [o.size_m[0] if abs(u[1]) > 0.5 else o.size_m[1] for o in sc.obstacles]
        assert min(abs(s) - w / 2 for s, w in zip(sides, across_size)) >= 30, sc.name  # none on the road
        assert len(low(sc)) >= 1 and len(tall(sc)) >= 1


def test_mixed_spans_one_to_ten_targets_any_heights_and_declares_candidate_goals():
    scs = worlds("mixed", 30)
    n = [len(sc.targets) for sc in scs]
    assert min(n) >= 1 and max(n) <= 10 and min(n) <= 3 and max(n) >= 8
    assert max(len(sc.obstacles) for sc in scs) <= 10
    assert any(low(sc) for sc in scs) and any(tall(sc) for sc in scs)
    assert any(o.yaw_deg != 0 for sc in scs for o in sc.obstacles)
    declared = [t for sc in scs for t in sc.targets if t.goals]
    assert declared and all(len(t.candidates) == len(sc.goals) for sc in scs for t in sc.targets if t.goals)


def test_a_worlds_spec_is_checked():
    assert W.parse_spec("town:3,open:1") == [("town", 3), ("open", 1)]
    for bad in ("town", "town:0", "moon:2", "town:2,town:1", "town:x"):
        with pytest.raises(ValueError, match="--worlds"):
            W.parse_spec(bad)
    with pytest.raises(ValueError, match="unknown world family"):
        W.world_tree("moon", 1, 0)


@pytest.mark.slow
def test_every_familys_targets_reach_their_goals_in_a_mission():
    from sim.truth.world import simulate_truth

    for family in W.FAMILIES:
        for i in range(2):
            sc = W.draw_world(family, 2024, i)
            truth = simulate_truth(sc, int(sc.mission.duration_s) - 1, np.random.default_rng(i))
            for j, t in enumerate(sc.targets):
                d = math.dist(truth[-1, j, :2], sc.goal_named(t.goal).center_m[:2])
                assert d < 100.0, (sc.name, t.name, d)


def test_a_world_is_flown_as_pmon_eval_flies_its_file(tmp_path):
    """World i of ``--worlds`` is trial i of ``pmon eval FILE`` with the same seed."""
    (job,) = [j for j in we.world_jobs("open:2", 7, ["hover", "greedy_l1"], {}, duration_s=6.0, particles=100)
              if j.index == 1]
    mine = we._run_job(job)
    path = W.write_worlds("open", 2, 7, tmp_path)[1]
    cfg = ev.make_config(load_scenario(path), 2, 7, ["hover", "greedy_l1"], duration_s=6.0, particles=100)
    s = ev.summarise(cfg, [ev.run_trial(cfg, 1)])
    for m in ("hover", "greedy_l1"):
        assert mine.rmse_m[m] == pytest.approx(float(s.methods[m].per_trial_rmse[0]), rel=1e-12)


def test_the_ratio_is_of_the_worlds_rms_rmses_and_its_ci_brackets_it():
    a, b = np.array([10.0, 20.0, 30.0, 12.0]), np.array([20.0, 20.0, 40.0, 10.0])
    v, lo, hi = we.rms_ratio(a, b, 1)
    assert v == pytest.approx(math.sqrt(np.mean(a ** 2) / np.mean(b ** 2)))
    assert lo < v < hi
    assert math.isnan(we.rms_ratio(a[:1], b[:1], 1)[1])


def test_the_family_rows_pool_every_world_and_set_the_first_method_against_each_other():
    nan = float("nan")

    def world(fam, i, a, b, pa, pc):
        return we.WorldResult(fam, i, 3, 1, {"a": a, "b": b, "c": nan}, {"a": pa, "b": pa, "c": pc})
    rs = [world("town", 0, 10.0, 20.0, 8.0, 4.0), world("town", 1, 30.0, 20.0, 9.0, 6.0),
          world("open", 0, 5.0, 10.0, 4.0, 4.0)]
    rows = we.family_rows(rs, ["a", "b", "c"], 1)
    assert [r["family"] for r in rows] == ["town", "open", we.POOLED]
    town, _, pooled = rows
    assert town["rmse_m"]["a"] == pytest.approx(math.sqrt((100 + 900) / 2))
    assert town["ratios"]["b"][0] == pytest.approx(math.sqrt(1000 / 800)) and town["ratios"]["b"][3] == 1
    assert "c" not in town["ratios"] and pooled["worlds"] == 3 and pooled["ratios"]["b"][3] == 2
    assert pooled["bound_ratios"]["c"][0] == pytest.approx(math.sqrt((64 + 81 + 16) / (16 + 36 + 16)))
    table = we.table_markdown(rows, ["a", "b", "c"])
    assert table[0].endswith("| a / b (95 % CI; worlds lower) | a PCRB / c PCRB (95 % CI) |")
    assert table[2].startswith("| town | 2 | 3.0 | 22.4 | 20.0 | (PCRB 5.1) | 1.12 (")


def test_pmon_eval_worlds_writes_a_table_per_family_and_pooled(tmp_path, capsys):
    from sim.verbs import evaluate

    out = tmp_path / "ev"
    assert evaluate(["--worlds", "open:2,crowd:1", "--duration", "4", "--particles", "100", "--methods",
                     "hover,greedy_l1", "--workers", "1", "--quiet", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    head = json.loads(lines[-1])
    assert list(head["worlds"]) == ["open", "crowd", "pooled"]
    rows = list(csv.DictReader(open(out / "worlds.csv", encoding="utf-8")))
    assert len(rows) == 3 * 2
    r = {(x["family"], x["index"], x["method"]): float(x["rmse_window_m"]) for x in rows}
    for fam, idx in (("open", ("0", "1")), ("crowd", ("0",))):
        for m in ("hover", "greedy_l1"):
            rms = math.sqrt(np.mean([r[(fam, i, m)] ** 2 for i in idx]))
            assert head["worlds"][fam]["rmse_m"][m] == pytest.approx(rms, abs=1e-4)
    pooled = head["worlds"]["pooled"]["ratios"]["hover / greedy_l1"]
    assert pooled[0] == pytest.approx(head["worlds"]["pooled"]["rmse_m"]["hover"]
                                      / head["worlds"]["pooled"]["rmse_m"]["greedy_l1"], abs=1e-3)
    assert any(x.startswith("| pooled | 3 |") for x in lines)
    for name in ("open-s2024-000", "open-s2024-001", "crowd-s2024-000"):
        assert load_scenario(out / "worlds" / f"{name}.yaml") == W.draw_world(name.split("-")[0], 2024,
                                                                                 int(name[-3:]))
    assert "pmon eval --worlds open:2,crowd:1" in (out / "worlds.md").read_text()


@pytest.mark.parametrize("args, message", [
    (("--worlds", "moon:2"), "--worlds 'moon:2': expected FAMILY:N"),
    (("paper", "--worlds", "open:1"), "--worlds draws its own scenarios"),
    (("--worlds", "open:1", "--set", "uav.altitude_m=5000"), "uav.altitude_m"),
])
def test_pmon_eval_worlds_bad_arguments(args, message, capsys):
    from sim.verbs import evaluate

    try:
        code = evaluate([*args, "--methods", "hover", "--quiet"])
    except SystemExit as exc:  # the parser's error
        code = exc.code
    assert code == 2
    assert message in capsys.readouterr().err


def test_pmon_worlds_writes_files_check_config_accepts(tmp_path, capsys):
    from onboard.cli import main as pmon
    from sim.verbs import worlds as pmon_worlds

    assert pmon_worlds(["crowd", "--n", "2", "--seed", "3", "--out", str(tmp_path)]) == 0
    said = capsys.readouterr().out.splitlines()
    assert len(said) == 2 and "6 targets" in said[0]
    for i in range(2):
        path = tmp_path / f"crowd-s3-{i:03d}.yaml"
        assert pmon(["check-config", str(path)]) == 0
        assert load_scenario(path) == W.draw_world("crowd", 3, i)


def test_the_scaling_scenario_is_the_papers_world_and_more_under_the_worlds_rules():
    """config/scale_8x10.yaml (issue 47's 8 targets x 10 obstacles): the validator takes it, its first
    four targets and obstacles, its goals, area and UAV start are the paper's, and the generated
    worlds' rules hold (gaps, clearances, every target reaching its goal)."""
    sc, paper = load_scenario(ROOT / "config" / "scale_8x10.yaml"), load_scenario("paper")
    assert (len(sc.targets), len(sc.obstacles)) == (8, 10)
    assert sc.targets[:4] == paper.targets and sc.obstacles[:4] == paper.obstacles and sc.goals == paper.goals
    assert sc.area == paper.area and sc.uav.start_m == paper.uav.start_m
    assert sorted(v.target for v in sc.kraken.vfos) == sorted(t.name for t in sc.targets)
    assert W.unreachable(sc) is None
    rects = [W.Rect(o.center_m[0], o.center_m[1], o.size_m[0], o.size_m[1], o.yaw_deg) for o in sc.obstacles]
    goals = [W.Rect(g.center_m[0], g.center_m[1], W.GOAL_M, W.GOAL_M) for g in sc.goals]
    for i, r in enumerate(rects):
        assert r.edge_gap() >= W.EDGE_M and all(r.gap(o) >= W.GAP_M for o in rects[:i] + goals), i
        assert all(r.distance(*t.position_m[:2]) >= W.CLEAR_M for t in sc.targets), i
    for t in sc.targets:
        g = sc.goal_named(t.candidates[0]).center_m
        assert math.hypot(t.position_m[0] - g[0], t.position_m[1] - g[1]) >= W.FROM_GOAL_M, t.name
    assert sum(o.size_m[2] > sc.uav.altitude_m for o in sc.obstacles[4:]) == 3  # as the file says


def test_the_planner_bench_refuses_a_bad_scenario_in_one_line_and_times_several_in_one_run(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: bad\n", encoding="utf-8")
    for item, says in ((str(bad), f"{bad}: origin: missing"), (str(tmp_path / "none.yaml"), "none.yaml: cannot read"),
                       ("paper,config/paper.yaml", "two scenarios named 'paper'")):
        done = subprocess.run([sys.executable, "-m", "bench.planner", "--scenarios", item], cwd=ROOT,
                              capture_output=True, text=True, timeout=60)
        last = done.stderr.strip().splitlines()[-1]
        assert done.returncode == 2 and done.stdout == "" and last.startswith("planner.py: error: --scenarios: "), done
        assert says in last, last
    done = subprocess.run([sys.executable, "-m", "bench.planner", "--scenarios", "paper,config/scale_8x10.yaml",
                           "--cases", "greedy/jump", "--ticks", "3", "--clock", "cpu"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert list(out) == ["paper", "scale_8x10"] and all(list(v) == ["greedy/jump"] for v in out.values()), out
    assert "scale_8x10 (config/scale_8x10.yaml): 8 targets, 10 obstacles" in done.stdout
