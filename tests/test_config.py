import copy

import pytest
import yaml

from onboard.config import ConfigError, load_scenario, parse_scenario


@pytest.fixture
def raw():
    with open("config/paper.yaml", encoding="utf-8") as f:
        return yaml.safe_load(f)


def test_paper_scenario_is_the_papers_setup(paper):
    assert [t.position_m[:2] for t in paper.targets] == [(281, 925), (238, 706), (901, 925), (885, 676)]
    assert paper.dynamics.process_noise_diag == (30, 30, 1e-10, 3, 3, 1e-10)
    assert paper.guidance.horizon == 50 and paper.uav.n_heading == 15 and paper.uav.n_radial == 4
    assert paper.sensor.sigma_rad == pytest.approx(0.017453292519943295)
    assert paper.uav.start_m == (150, 200, 40)


def test_builtin_and_file_agree(paper):
    assert load_scenario("config/paper.yaml") == paper


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["obstacles"][2].update(size_m=[240, 0, 50]), "obstacles[2].size_m[1]: must be > 0"),
    (lambda d: d["sensor"].update(p_detect=1.5), "sensor.p_detect: must be in [0, 1]"),
    (lambda d: d["guidance"].update(horizon="fifty"), "guidance.horizon: must be an integer"),
    (lambda d: d["uav"].update(start_m=[150, 2000, 40]), "uav.start_m: (150.0, 2000.0, 40.0) is outside"),
    (lambda d: d["goals"][0].update(center_m=[580, 330, 0]), "goals[0].center_m: inside obstacle 'O3'"),
    (lambda d: d["targets"][1].update(goal="H"), "targets[1].goal: no goal named 'H'"),
    (lambda d: d["tracking"].update(particle=3), "tracking: unknown key 'particle'"),
    (lambda d: d.pop("dynamics"), "dynamics: missing"),
    (lambda d: d["dynamics"].update(process_noise_diag=[1, 2, 3]), "dynamics.process_noise_diag: must have 6"),
    (lambda d: d["sensor"].update(sigma_deg=float("nan")), "sensor.sigma_deg: must be finite"),
    (lambda d: d["planning"]["lookahead"].update(ranges_m=[30, -5]), "planning.lookahead.ranges_m[1]: must be > 0"),
    (lambda d: d["planning"]["lookahead"].update(objective="trace"), "planning.lookahead: unknown key 'objective'"),
    (lambda d: d["tracking"].update(free_steering=False), "tracking: unknown key 'free_steering'"),
    (lambda d: d["planning"]["lookahead"].update(radius=3), "planning.lookahead: unknown key 'radius'"),
    (lambda d: d["tracking"].update(plan_steered_share=1.5), "tracking.plan_steered_share: must be in [0, 1]"),
    (lambda d: d["tracking"].update(plan_steering="yes please"), "tracking.plan_steering"),
    (lambda d: d["tracking"].update(plan_references=3), "tracking.plan_references: must be even"),
    (lambda d: d["tracking"].update(plan_max_qp_solves=0), "tracking.plan_max_qp_solves"),
    (lambda d: d["tracking"].update(plan_sides="maybe"), "tracking.plan_sides"),
    (lambda d: d["tracking"].update(plan_sides=True), "tracking.plan_sides: needs tracking.plan_steering"),
    (lambda d: d["tracking"].update(plan_side_temperature=0), "tracking.plan_side_temperature"),
])
def test_invalid_field_is_named(raw, edit, message):
    data = copy.deepcopy(raw)
    edit(data)
    with pytest.raises(ConfigError) as err:
        parse_scenario(data)
    assert message in str(err.value)


def test_bad_files(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML at line"):
        load_scenario(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        load_scenario(tmp_path / "missing.yaml")
    obj = tmp_path / "obj.yaml"
    obj.write_text("!!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(ConfigError):  # safe loader: nothing is executed
        load_scenario(obj)


def test_lookahead_settings_reach_the_planner(raw):
    """planning.lookahead in a scenario sets the planner's knobs; left out, the planner's defaults."""
    from onboard.core.monitor import MonitorSetup
    from onboard.core.planning import LOOKAHEAD_DEFAULT
    data = copy.deepcopy(raw)
    del data["planning"]["lookahead"]
    assert MonitorSetup.from_scenario(parse_scenario(data)).lookahead == LOOKAHEAD_DEFAULT
    data["planning"]["lookahead"] = {"loiter_radius_m": 15.0, "ranges_m": [50, 100]}
    got = MonitorSetup.from_scenario(parse_scenario(data)).lookahead
    assert got.loiter_radius_m == 15.0 and got.ranges_m == (50.0, 100.0)
    assert got.n_headings == LOOKAHEAD_DEFAULT.n_headings


def test_overrides_set_dotted_keys_and_name_missing_parents():
    sc = load_scenario("paper", {"tracking.control_mix": 0.0, "planning.lookahead.loiter_radius_m": 20.0})
    assert sc.tracking.control_mix == 0.0 and sc.planning.lookahead.loiter_radius_m == 20.0
    with pytest.raises(ConfigError, match=r"trackin: missing \(setting trackin.control_mix\)"):
        load_scenario("paper", {"trackin.control_mix": 0.0})
    with pytest.raises(ConfigError, match="tracking.control_mix: must be in"):
        load_scenario("paper", {"tracking.control_mix": 2.0})


def test_bench_set_items_become_overrides():
    """The benches' --set KEY=VALUE: VALUE read as YAML; an item without '=' is named."""
    from onboard.config import parse_overrides
    ov = parse_overrides(["tracking.plan_steering=true", "tracking.plan_trust_sigma=1.5",
                          "planning.lookahead.ranges_m=[30, 80]"])
    assert ov == {"tracking.plan_steering": True, "tracking.plan_trust_sigma": 1.5,
                  "planning.lookahead.ranges_m": [30, 80]}
    sc = load_scenario("paper", ov)
    assert sc.tracking.plan_steering and sc.tracking.plan_trust_sigma == 1.5
    with pytest.raises(ConfigError, match="'tracking.plan_steering': expected KEY=VALUE"):
        parse_overrides(["tracking.plan_steering"])


def test_with_overrides_puts_a_policy_under_the_users_own_settings():
    """A method's policy (onboard.policy) re-reads the scenario with its settings; the run's own
    overrides (pmon eval --set) win over the policy's; the result is validated like a load."""
    from dataclasses import replace

    from onboard.config import with_overrides
    user = load_scenario("paper", {"tracking.control_mix": 0.05})
    sc = with_overrides(user, {"tracking.control_mix": 0.2, "planning.planner": "lookahead"})
    assert sc.tracking.control_mix == 0.05 and sc.planning.planner == "lookahead"
    assert user.planning.planner == "greedy"  # the scenario it came from is untouched
    assert with_overrides(sc, {"planning.motion": "vehicle"}).planning.planner == "lookahead"
    with pytest.raises(ConfigError, match="planning.lookahead_steps: must be <= guidance.horizon"):
        with_overrides(user, {"planning.planner": "lookahead", "planning.lookahead_steps": 60})
    # a change made with dataclasses.replace is not in the file: refused rather than lost
    edited = replace(user, guidance=replace(user.guidance, horizon=20))
    with pytest.raises(ConfigError, match="changed after loading"):
        with_overrides(edited, {"planning.planner": "lookahead"})
