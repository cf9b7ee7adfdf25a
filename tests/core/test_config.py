import copy
import dataclasses
import math
import os
from pathlib import Path

import pytest
import yaml

from onboard.config import ConfigError, load_scenario, override, parse_overrides, parse_scenario, scenario_tree
from onboard.settings import declare, docs, sections

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def raw():
    with open(ROOT / "config" / "paper.yaml", encoding="utf-8") as f:
        return yaml.safe_load(f)


def test_paper_scenario_is_the_papers_setup(paper):
    assert [t.position_m[:2] for t in paper.targets] == [(281, 925), (238, 706), (901, 925), (885, 676)]
    assert paper.dynamics.process_noise_diag == (30, 30, 1e-10, 3, 3, 1e-10)
    assert paper.guidance.horizon == 50 and paper.uav.n_heading == 15 and paper.uav.n_radial == 4
    assert paper.sensor.sigma_rad == pytest.approx(0.017453292519943295)
    assert paper.uav.start_m == (150, 200, 40)


def test_the_builtin_scenario_is_the_example_file_not_a_copy():
    """`pmon ... paper` reads onboard/data/paper.yaml, packaged with the code: it is a link to
    config/paper.yaml, so the two cannot drift apart."""
    assert os.path.samefile(ROOT / "onboard" / "data" / "paper.yaml", ROOT / "config" / "paper.yaml")


@pytest.mark.parametrize("edit, message", [
    (lambda d: d["obstacles"][2].update(size_m=[240, 0, 50]), "obstacles[2].size_m[1]: must be > 0"),
    (lambda d: d["sensor"].update(p_detect=1.5), "sensor.p_detect: must be in [0.01, 1], got 1.5"),
    (lambda d: d["sensor"].update(sigma_deg=0.01745), "sensor.sigma_deg: must be in [0.05, 30] deg, got 0.01745"),
    (lambda d: d["sensor"].update(sigma_deg=float("nan")), "sensor.sigma_deg: must be finite"),
    (lambda d: d["sensor"].update(clutter_rate=float("inf")), "sensor.clutter_rate: must be finite"),
    (lambda d: d["sensor"].update(clutter_rate=True), "sensor.clutter_rate: must be a number, got bool"),
    (lambda d: d["sensor"].update(p_detect=10 ** 400), "sensor.p_detect: must be in [0.01, 1], got an integer"),
    (lambda d: d["guidance"].update(horizon="fifty"), "guidance.horizon: must be an integer"),
    (lambda d: d["guidance"].update(horizon=50.0), "guidance.horizon: must be an integer, got float"),
    (lambda d: d["guidance"].update(horizon=201), "guidance.horizon: must be in [2, 200] steps, got 201"),
    (lambda d: d["guidance"].update(max_solve_time_s=0), "guidance.max_solve_time_s: must be in (0, 10] s"),
    (lambda d: d["uav"].update(start_m=[150, 2000, 40]), "uav.start_m: (150.0, 2000.0, 40.0) is outside"),
    (lambda d: d["uav"].update(start_m=[150, 2e6, 40]), "uav.start_m[1]: must be in [-100000, 100000] m, got 2000000.0"),
    (lambda d: d["goals"][0].update(center_m=[580, 330, 0]), "goals[0].center_m: inside obstacle 'O3'"),
    (lambda d: d["targets"][1].update(goal="H"), "targets[1].goal: no goal named 'H'"),
    (lambda d: d["targets"][1].update(goals=["G", "H"]), "targets[1].goals[1]: no goal named 'H'"),
    (lambda d: d["targets"][1].update(goals="G"), "targets[1].goals: must be a list"),
    (lambda d: d["targets"][1].update(goals=["G", 3]), "targets[1].goals[1]: must be a non-empty string"),
    (lambda d: d["targets"][1].update(stationary="yes"), "targets[1].stationary: must be true or false"),
    (lambda d: d["targets"][1].update(name="T" * 65), "targets[1].name: must be at most 64 characters"),
    (lambda d: d["goals"].append(dict(d["goals"][0])), "goals[3].name: duplicate name 'G'"),
    (lambda d: d.setdefault("tracking", {}).update(particle=3),
     "tracking.particle: unknown key (expected one of: particles, "),
    (lambda d: d.setdefault("tracking", {}).update(particles=50), "tracking.particles: must be in [100, 20000]"),
    (lambda d: d.pop("origin"), "origin: missing"),
    (lambda d: d["uav"].pop("start_m"), "uav.start_m: missing"),
    (lambda d: d["dynamics"].update(process_noise_diag=[1, 2, 3]), "dynamics.process_noise_diag: must have 6 numbers, got 3"),
    (lambda d: d["planning"].update(lookahead={"ranges_m": [30, -5]}),
     "planning.lookahead.ranges_m[1]: must be in (0, 5000] m, got -5.0"),
    (lambda d: d["planning"].update(lookahead={"ranges_m": list(range(1, 18))}),
     "planning.lookahead.ranges_m: must have at most 16 items, got 17"),
    (lambda d: d["planning"].update(lookahead={"objective": "trace"}), "planning.lookahead.objective: unknown key"),
    (lambda d: d.setdefault("tracking", {}).update(free_steering=False), "tracking.free_steering: unknown key"),
    (lambda d: d.setdefault("tracking", {}).update(plan_steered_share=1.5),
     "tracking.plan_steered_share: must be in [0, 1]"),
    (lambda d: d.setdefault("tracking", {}).update(plan_steering="yes please"),
     "tracking.plan_steering: must be true or false, got str"),
    (lambda d: d.setdefault("tracking", {}).update(plan_references=3), "tracking.plan_references: must be even"),
    (lambda d: d.setdefault("tracking", {}).update(plan_max_qp_solves=0), "tracking.plan_max_qp_solves"),
    (lambda d: d.setdefault("tracking", {}).update(plan_side_temperature=0), "tracking.plan_side_temperature"),
    (lambda d: d["planning"].update(planner="lookahead", lookahead_steps=60),
     "planning.lookahead_steps: must be <= guidance.horizon (50)"),
    (lambda d: d["planning"].update(planner="spiral"), "planning.planner: must be one of greedy, lookahead"),
    (lambda d: d.update(app={"fence_max_m": 30}), "uav.altitude_m: must be within the geofence band"),
])
def test_invalid_field_is_named(raw, edit, message):
    data = copy.deepcopy(raw)
    edit(data)
    with pytest.raises(ConfigError) as err:
        parse_scenario(data)
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_bad_files(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: not valid YAML at line"):
        load_scenario(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        load_scenario(tmp_path / "missing.yaml")
    obj = tmp_path / "obj.yaml"
    obj.write_text("!!python/object/apply:os.system ['echo pwned']\n")
    with pytest.raises(ConfigError):  # safe loader: nothing is executed
        load_scenario(obj)


def test_a_key_given_twice_is_refused_with_its_path_and_lines(tmp_path):
    """YAML readers keep the last of two equal keys; a scenario file names both lines."""
    paper = (ROOT / "config" / "paper.yaml").read_text()
    twice = tmp_path / "twice.yaml"
    twice.write_text(paper.replace("  horizon: 50 ", "  horizon: 50\n  horizon: 20 "))
    line = paper[:paper.index("  horizon: 50")].count("\n") + 1
    with pytest.raises(ConfigError) as err:
        load_scenario(twice)
    assert str(err.value) == f"{twice}: guidance.horizon: key given twice (lines {line} and {line + 1})"
    flow = tmp_path / "flow.yaml"
    flow.write_text(paper.replace("{name: T2, position_m", "{name: T2, name: T5, position_m"))
    with pytest.raises(ConfigError, match=r"targets\[1\]\.name: key given twice"):
        load_scenario(flow)


def test_a_huge_integer_is_named_not_converted(tmp_path):
    """Python refuses int() of more than 4300 digits (ValueError: a traceback before); the
    integer is never converted and its error names the key, the range and its length."""
    paper = (ROOT / "config" / "paper.yaml").read_text()
    huge = tmp_path / "huge.yaml"
    huge.write_text(paper + "tracking:\n  particles: 1" + "0" * 4999 + "\n")
    with pytest.raises(ConfigError) as err:
        load_scenario(huge)
    assert str(err.value) == f"{huge}: tracking.particles: must be in [100, 20000], got 1000000... (5000 digits)"
    with pytest.raises(ConfigError, match=r"tracking.particles: must be in \[100, 20000\], got -100000\.\.\. \(5001 digits\)"):
        load_scenario("paper", parse_overrides(["tracking.particles=-" + "1" + "0" * 5000]))
    with pytest.raises(ConfigError, match=r"name: must be a non-empty string, got an integer of 5001 digits"):
        load_scenario("paper", parse_overrides(["name=" + "9" * 5001]))


def test_aliases_are_not_walked_exponentially(tmp_path):
    """A billion-laughs file (each level aliases the last twice): refused at once, not expanded."""
    lines = ["a0: &a0 [x]"] + [f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}]" for i in range(1, 40)]
    laughs = tmp_path / "laughs.yaml"
    laughs.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match="a0: unknown key"):
        load_scenario(laughs)


def test_lookahead_settings_reach_the_planner(raw):
    """planning.lookahead in a scenario sets the planner's knobs; left out, the declared defaults."""
    from onboard.core.monitor import MonitorSetup
    from onboard.core.planning.inputs import LookaheadParams
    data = copy.deepcopy(raw)
    data["planning"].pop("lookahead", None)
    defaults = LookaheadParams.from_config(sections.Lookahead())
    assert MonitorSetup.from_scenario(parse_scenario(data)).lookahead == defaults
    data["planning"]["lookahead"] = {"loiter_radius_m": 15.0, "ranges_m": [50, 100]}
    got = MonitorSetup.from_scenario(parse_scenario(data)).lookahead
    assert got.loiter_radius_m == 15.0 and got.ranges_m == (50.0, 100.0)
    assert got.n_headings == defaults.n_headings


def test_overrides_set_dotted_keys_and_name_unknown_ones():
    sc = load_scenario("paper", {"tracking.control_mix": 0.0, "planning.lookahead.loiter_radius_m": 20.0})
    assert sc.tracking.control_mix == 0.0 and sc.planning.lookahead.loiter_radius_m == 20.0
    with pytest.raises(ConfigError, match=r"^<builtin paper>: trackin: unknown key \(expected one of: name, "):
        load_scenario("paper", {"trackin.control_mix": 0.0})
    with pytest.raises(ConfigError, match=r"tracking.control_mx: unknown key"):
        load_scenario("paper", {"tracking.control_mx": 0.0})
    with pytest.raises(ConfigError, match=r"name.x: name is not a mapping"):
        load_scenario("paper", {"name.x": 0.0})
    with pytest.raises(ConfigError, match="tracking.control_mix: must be in"):
        load_scenario("paper", {"tracking.control_mix": 2.0})
    # a file fixed by its overrides loads (they are set before the checks)
    sc = load_scenario("paper", {"guidance.horizon": 20, "planning.planner": "lookahead", "planning.lookahead_steps": 20})
    assert sc.guidance.horizon == sc.planning.lookahead_steps == 20


def test_bench_set_items_become_overrides():
    """--set KEY=VALUE: VALUE read as YAML; an item without '=' is named; so is a key given twice
    inside a VALUE and a tag."""
    ov = parse_overrides(["tracking.plan_steering=true", "tracking.plan_trust_sigma=1.5",
                          "planning.lookahead.ranges_m=[30, 80]"])
    assert ov == {"tracking.plan_steering": True, "tracking.plan_trust_sigma": 1.5,
                  "planning.lookahead.ranges_m": [30, 80]}
    sc = load_scenario("paper", ov)
    assert sc.tracking.plan_steering and sc.tracking.plan_trust_sigma == 1.5
    with pytest.raises(ConfigError, match="'tracking.plan_steering': expected KEY=VALUE"):
        parse_overrides(["tracking.plan_steering"])
    with pytest.raises(ConfigError, match=r"^--set planning.lookahead.n_headings: key given twice"):
        parse_overrides(["planning.lookahead={n_headings: 8, n_headings: 9}"])
    with pytest.raises(ConfigError, match=r"^--set tracking.control_mix: VALUE is not plain YAML"):
        parse_overrides(["tracking.control_mix=!!python/object/apply:os.system ['true']"])


def test_a_number_with_an_exponent_and_no_dot_is_a_number():
    """PyYAML's YAML 1.1 reads 1e-9 as a string (its floats need a dot): `--set
    tracking.control_mix=1e-9` was refused with "must be a number, got str"."""
    assert parse_overrides(["tracking.control_mix=1e-9", "sensor.clutter_rate=2E0", "x=-3e+2", "y=1e"]) == \
        {"tracking.control_mix": 1e-9, "sensor.clutter_rate": 2.0, "x": -300.0, "y": "1e"}
    assert load_scenario("paper", {"tracking.control_mix": 1e-9}).tracking.control_mix == 1e-9


def test_a_policy_goes_beneath_the_users_own_settings():
    """A flight policy (onboard.policy) applies its settings beneath the scenario's own changes
    (pmon eval --set wins over the policy's); the result is checked like a load. The declared
    defaults are what flies: the flight policy changes nothing, the paper's restores its method."""
    from dataclasses import replace

    from onboard.policy import POLICIES, with_policy
    user = load_scenario("paper", {"tracking.control_mix": 0.05})
    sc = override(user, {"tracking.control_mix": 0.2, "planning.planner": "greedy"}, beneath=True)
    assert sc.tracking.control_mix == 0.05 and sc.planning.planner == "greedy"
    assert user.planning.planner == "lookahead"  # the scenario it came from is untouched
    assert override(sc, {"planning.motion": "jump"}).planning.planner == "greedy"
    assert with_policy(user, "paper") == override(user, POLICIES["paper"], beneath=True)
    assert with_policy(user, "flight") == user and with_policy(user, "paper").tracking.control_mix == 0.05
    paper = with_policy(user, "paper")
    assert (paper.planning.planner, paper.planning.motion, paper.tracking.intent) == ("greedy", "jump", False)
    with pytest.raises(ConfigError, match="planning.lookahead_steps: must be <= guidance.horizon"):
        override(paper, {"planning.planner": "lookahead", "planning.lookahead_steps": 60})
    # a scenario built with dataclasses.replace is changed as it is (nothing re-read from its file)
    edited = replace(paper, guidance=replace(paper.guidance, horizon=20))
    with pytest.raises(ConfigError, match=r"must be <= guidance.horizon \(20\)"):
        override(edited, {"planning.planner": "lookahead"})
    assert override(edited, {"sensor.clutter_rate": 2.0}).guidance.horizon == 20


def test_a_scenario_written_back_reads_as_itself():
    """scenario_tree is what override starts from: read back, the same scenario, bit for bit
    (degrees stay degrees: radians(degrees(x)) is not x for 1 value in 20)."""
    from onboard.policy import with_policy
    for policy in ("paper", "flight"):
        sc = load_scenario("paper", {"sensor.sigma_deg": 1.3, "obstacles": [
            {"name": "B", "center_m": [500.0, 500.0, 10.0], "size_m": [10.0, 10.0, 20.0], "yaw_deg": 33.3}]})
        sc = with_policy(sc, policy)
        again = parse_scenario(yaml.safe_load(yaml.safe_dump(scenario_tree(sc))))
        assert again == sc and again.sensor.sigma_rad == sc.sensor.sigma_rad == math.radians(1.3)
        assert again.obstacles[0].yaw_rad == math.radians(33.3)


# --------------------------------------------------------------------------- one declaration


def _leaf_keys(tree, prefix=""):
    """Dotted keys of a file's tree (list items as key[].field)."""
    for k, v in tree.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            yield from _leaf_keys(v, key + ".")
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for item in v:
                yield from _leaf_keys(item, key + "[].")
        else:
            yield key


def test_the_reader_the_parameters_and_the_docs_derive_from_the_one_declaration(paper):
    """The YAML keys the reader writes and accepts, the PMON_* parameters (names, ranges,
    integer-ness) and docs/SETTINGS.md's table are those of onboard/settings/sections.py: a setting added,
    renamed, or re-ranged in one place and not the others fails here."""
    from onboard.app.params import BY_NAME, SPECS
    from onboard.policy import with_policy
    declared = set(sections.SETTINGS)
    assert set(_leaf_keys(scenario_tree(paper))) == declared  # every setting, written back
    # the reader accepts these keys: each number, set to a bound (or, where that breaks a check
    # across settings, between them), is read into the object (on the paper's greedy rule, which
    # bounds no lookahead) ...
    greedy = with_policy(paper, "paper")
    for key, s in sections.SETTINGS.items():
        if "[]" in key or s.kind not in ("number", "integer"):
            continue
        eps = 1 if s.kind == "integer" else 1e-3
        for v in (s.hi - eps * s.hi_open, s.lo + eps * s.lo_open, (s.lo + s.hi) / 2):
            v = int(v) if s.kind == "integer" else v
            try:
                changed = override(greedy, {"planning.lookahead_steps": 1, key: v})
            except ConfigError as exc:
                assert not str(exc).startswith(key), exc  # refused across settings, never in range
                continue
            assert sections.value_of(changed, key) == pytest.approx(v), key
            break
        else:
            raise AssertionError(f"{key}: no value in its range was read")
    # ... and a key next to them is refused
    with pytest.raises(ConfigError, match="sensor.sigma_rad: unknown key"):
        override(paper, {"sensor.sigma_rad": 0.1})
    # the PMON_* parameters: one per declared param=, its range and type the setting's
    assert {s.name: s.key for s in SPECS} == sections.PARAMS
    for s in SPECS:
        d = sections.SETTINGS[s.key]
        assert (s.lo, s.hi, s.integer) == (d.lo, d.hi, d.kind == "integer") and not d.lo_open and not d.hi_open
        assert BY_NAME[s.name] is s and len(s.name) <= 16
    # the docs' table is the declaration's
    doc = (ROOT / "docs" / "SETTINGS.md").read_text(encoding="utf-8")
    assert docs.docs_with_table(doc) == doc, "docs/SETTINGS.md is stale: python -m onboard.settings --write"
    for key in declared:
        assert f"| `{key}` |" in doc


def test_at_most_40_settings_are_not_experimental_and_no_experimental_one_flies_as_a_parameter():
    """What an operator or integrator sets stays short; the research knobs are experimental, apart
    in docs/SETTINGS.md and never a PMON_* parameter. A list of records (targets, goals,
    obstacles, kraken.vfos) is one setting: each item is one thing the mission states."""
    outside = {key.split("[]")[0] for key, s in sections.SETTINGS.items() if not s.experimental}
    assert len(outside) <= 40, sorted(outside)
    assert [key for key, s in sections.SETTINGS.items() if s.experimental and s.param] == []
    assert all(not sections.SETTINGS[key].experimental for key in sections.PARAMS.values())
    doc = (ROOT / "docs" / "SETTINGS.md").read_text(encoding="utf-8")
    apart = doc.partition(docs.EXPERIMENTAL_BEGIN)[2]
    for key, s in sections.SETTINGS.items():
        assert (f"| `{key}` |" in apart) == s.experimental, key


def test_experimental_changes_name_what_differs_from_the_default():
    """The paper's file states experimental settings at their defaults (the paper's values): none
    named; a change is, with its value and default (the paper's policy changes some)."""
    from onboard.policy import with_policy
    file = load_scenario("paper")
    assert sections.experimental_changes(file) == []
    assert ("planning.motion", "jump", "vehicle") in sections.experimental_changes(with_policy(file, "paper"))
    sc = override(file, {"tracking.regularise_bandwidth": 0.3, "sensor.p_detect": 0.9,
                          "planning.lookahead.ranges_m": [30.0, 80.0]})
    assert sections.experimental_changes(sc) == [("tracking.regularise_bandwidth", "0.3", "0.2"),
                                                 ("planning.lookahead.ranges_m", "[30, 80]", "[30, 80, 160, 320]")]


def test_every_default_is_within_its_range():
    """A tree stating only what is required reads as the declared defaults: each passes its own
    check (the reader checks a stated value, not a default)."""
    required = {"name": "x", "origin": {"lat_deg": 0.0, "lon_deg": 0.0, "alt_m": 0.0},
                "area": {"min_m": [0, 0, 0], "max_m": [1000, 1000, 1000]},
                "targets": [{"name": "T", "position_m": [100, 100, 0], "goal": "G"}],
                "goals": [{"name": "G", "center_m": [500, 500, 0], "size_m": [10, 10, 0]}],
                "uav": {"start_m": [10, 10, 40]}}
    sc = parse_scenario(required)
    stated = parse_scenario(scenario_tree(sc))  # every default now stated, so checked
    assert stated == sc
    assert sc.tracking == sections.Tracking() and sc.guidance == sections.Guidance()


def test_the_example_file_states_the_geometry_the_papers_values_and_what_differs(raw):
    """config/paper.yaml: each setting it states is required (the mission's geometry), the
    paper's own value (declared paper=True), or differs from its default; nothing else."""
    fields = {key: f for key, f, _ in declare.walk(sections.Scenario)}
    for key in _leaf_keys(raw):
        s, f = sections.SETTINGS[key], fields[key]
        if f.default is dataclasses.MISSING or s.paper or "[]" in key:
            continue
        sc = load_scenario("paper")
        assert sections.value_of(sc, key) != f.default, f"{key} equals its default and is not the paper's"


def test_the_cores_parameter_classes_have_no_defaults_of_their_own():
    """They take every value from the scenario (from_config / from_scenario): a default in one
    of them could disagree with the declaration (control_mix was 0.1 there, 0.0 here)."""
    from onboard.core.guidance.predictor import GuidanceParams
    from onboard.core.monitor import MonitorSetup, PlanSteering
    from onboard.core.planning.inputs import CandidateGrid, LookaheadParams, UavMotion
    from onboard.core.tracking.filter import SensorModel
    for cls in (GuidanceParams, SensorModel, CandidateGrid, UavMotion, LookaheadParams, PlanSteering, MonitorSetup):
        # a field the constructor does not take (MonitorSetup.parts: the parts built from the
        # settings) is no setting, so it cannot disagree with one
        with_default = [f.name for f in dataclasses.fields(cls) if f.init and
                        (f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING)]
        assert not with_default, (cls.__name__, with_default)


# --------------------------------------------------------------------------- in flight


def test_a_parameter_set_in_flight_is_checked_as_a_file_is():
    """PMON_HORIZON below planning.lookahead_steps is refused with the flight policy's lookahead
    (the cross-field check, which dataclasses.replace skipped) and accepted with the paper's
    greedy rule; a refused set changes nothing; apply is the scenario with the values."""
    from onboard.app.params import ParamTable
    from onboard.policy import POLICIES, with_policy
    flight = load_scenario("paper", POLICIES["flight"])
    table = ParamTable.from_scenario(flight)
    refused = table.set("PMON_HORIZON", 30)
    assert refused == ("PMON_HORIZON=30 refused: planning.lookahead_steps: must be <= guidance.horizon (30) "
                       "with the lookahead planner, got 50: it follows the guidance plans")
    assert table["PMON_HORIZON"] == 50 and table.version == 0
    assert table.set("PMON_HORIZON", 60) is None and table.apply(flight).guidance.horizon == 60
    paper = ParamTable.from_scenario(with_policy(load_scenario("paper"), "paper"))
    assert paper.set("PMON_HORIZON", 30) is None and paper.version == 1
    assert table.set("PMON_PD", 1.5) == "PMON_PD=1.5 out of range [0.01, 1]"
    assert table.set("PMON_SIGMA_DEG", 0.01745) == "PMON_SIGMA_DEG=0.01745 out of range [0.05, 30]"
    assert table.set("PMON_ALT_MAX", 30).startswith("PMON_ALT_MAX=30 refused: uav.altitude_m: must be within")
    assert table.set("PMON_ALT", 150).startswith("PMON_ALT=150 refused: uav.altitude_m: must be within")
    assert table.set("PMON_NR", 3.4) is None and table["PMON_NR"] == 3
    sc = table.apply(flight)
    assert (sc.uav.n_radial, sc.app.reach_m, sc.app.fence_max_m) == (3, 20.0, 120.0)
    assert table.set("PMON_NOPE", 1.0) == "unknown parameter 'PMON_NOPE'"
    assert table.set("PMON_CLUTTER", math.nan) == "PMON_CLUTTER: value is not finite"


def test_unchanged_parameters_leave_the_scenario_as_it_is(paper):
    """The app applies every parameter on each rebuild: at their start values the scenario's
    settings are unchanged, bit for bit (sigma stays degrees, nothing converted back)."""
    from onboard.app.params import ParamTable, defaults_from_scenario
    from onboard.core.monitor import MonitorSetup
    for sc in (paper, load_scenario("paper", {"sensor.sigma_deg": 1.3, "uav.step_m": 2.7})):
        applied = ParamTable.from_scenario(sc).apply(sc)
        assert dataclasses.replace(applied, app=sc.app) == sc
        assert MonitorSetup.from_scenario(applied).sensor == MonitorSetup.from_scenario(sc).sensor
        assert defaults_from_scenario(sc)["PMON_REACH"] == max(sc.uav.n_radial * sc.uav.step_m, 1.0)
    # a file (or --set) gives the app's own settings their start values, as for every parameter
    own = load_scenario("paper", {"app.setpoint_hz": 20, "app.fence_max_m": 90, "uav.n_radial": 2})
    assert {k: v for k, v in defaults_from_scenario(own).items() if k in ("PMON_SP_HZ", "PMON_ALT_MAX", "PMON_NR",
                                                                          "PMON_REACH")} == {
        "PMON_SP_HZ": 20.0, "PMON_ALT_MAX": 90.0, "PMON_NR": 2.0, "PMON_REACH": 10.0}


def test_a_targets_intent_may_be_a_goal_candidates_stationary_or_nothing(raw):
    """docs/SCENARIO.md's four forms read back as written; a target without a goal is not given the
    first goal of the file."""
    data = copy.deepcopy(raw)
    data["targets"][0].pop("goal")
    data["targets"][1].update(goal=None, goals=["G", "W"])
    data["targets"][2].update(stationary=True)
    sc = parse_scenario(data)
    t0, t1, t2 = sc.targets[:3]
    assert (t0.goal, t0.candidates, sc.goal_of(t0)) == (None, (), None)
    assert sc.goal_point(t0) == t0.position_m
    assert t1.candidates == ("G", "W") and t2.stationary and t2.candidates == ("G",)
