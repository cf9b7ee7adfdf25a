"""The Monte Carlo harness: the fixed-sensor baseline reaches the triangulation bound, the
harness is deterministic for a seed (whatever the workers or the cluster), a short evaluation
keeps every target with every method, and ``pmon eval`` writes what it promises."""
import json
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import scipy
from scipy import stats

from onboard.config import ConfigError, override
from onboard.settings.sections import Box, Target
from sim.evaluation import trials as ev


@pytest.fixture(scope="module")
def quick(paper):
    """The paper scenario with a shorter guidance horizon (same world, faster ticks); the lookahead
    scores the whole (shorter) plan, as it did before it was held to the horizon."""
    return override(paper, {"guidance.horizon": 20, "planning.lookahead_steps": 20})


def test_fixed_sensors_localise_a_target_to_the_triangulation_bound(paper):
    """One slow target (no control authority, so the truth is the linear model with noise Q)
    seen by the three fixed DFs: the filter's RMSE matches the posterior Cramér-Rao bound computed
    from the sensors' geometry and sigma along the true trajectory."""
    t = Target(name="S", position_m=(450.0, 500.0, 0.0), velocity_mps=(0.0, 0.0, 0.0), goal="H")
    sc = replace(paper, targets=(t,), goals=(Box("H", (450.0, 500.0, 0.0), (10.0, 10.0, 0.0)),), obstacles=(),
                 guidance=replace(paper.guidance, horizon=10, u_max_n=1.0),
                 kraken=replace(paper.kraken, vfos=()))  # paper's VFOs name targets this scenario lacks
    cfg = ev.make_config(sc, 30, 5, ["fixed3"], duration_s=30)
    trials = ev.run_trials(cfg, workers=1, progress=False)
    mse, bound = [], []
    for tr in trials:
        # the evaluation's own bound (sim.evaluation.metrics.pcrb along the truth, closed loop)
        mse.append(tr.traces["fixed3"].error_m[5:, 0] ** 2)
        bound.append(tr.traces["fixed3"].bound_m2[5:, 0])
    ratio = np.sqrt(np.mean(mse) / np.mean(bound))
    # a bound: the error cannot be far below it (that would mean less noise than stated), and
    # an efficient filter is close above it (an inefficient or wrong one is far above)
    assert 0.75 < ratio < 1.4, ratio
    assert 3.0 < np.sqrt(np.mean(bound)) < 15.0  # the geometry gives metres, not centimetres or 100 m


def _same(a: list, b: list) -> bool:
    if len(a) != len(b):
        return False
    for x, y in zip(a, b):
        if x.trial != y.trial or not np.array_equal(x.truth, y.truth) or not np.array_equal(x.start, y.start):
            return False
        for name in x.traces:
            p, q = x.traces[name], y.traces[name]
            if not (np.array_equal(p.error_m, q.error_m) and np.array_equal(p.nees, q.nees)
                    and (p.uav is None or np.array_equal(p.uav, q.uav))):
                return False
    return True


@pytest.fixture(scope="module")
def tiny(quick):
    return ev.make_config(quick, 2, 42, ev.DEFAULT_METHODS, duration_s=5, particles=200)


@pytest.fixture(scope="module")
def tiny_serial(tiny):
    return ev.run_trials(tiny, workers=1, progress=False)


@pytest.mark.slow
def test_harness_is_deterministic_for_a_seed_and_across_workers(tiny, tiny_serial):
    assert _same(tiny_serial, ev.run_trials(tiny, workers=1, progress=False))
    assert _same(tiny_serial, ev.run_trials(tiny, workers=2, progress=False))
    # chosen trials (bench/consistency.py --trial-ids) are those trials of the whole run
    assert _same(tiny_serial[1:], ev.run_trials(tiny, workers=1, progress=False, trials=[1]))
    other = ev.run_trials(replace(tiny, seed=43), workers=1, progress=False)
    assert not np.array_equal(other[0].traces["greedy_l1"].error_m, tiny_serial[0].traces["greedy_l1"].error_m)


def test_plan_steering_trials_are_the_same_whatever_the_workers(paper):
    """The plan-steering filter amplifies last-bit differences (this process's BLAS may sum in
    another order with more threads): every local worker, even a lone one, is a spawned process
    with one BLAS thread, so --workers does not change the numbers."""
    sc = replace(paper, tracking=replace(paper.tracking, plan_steering=True))
    cfg = ev.make_config(sc, 2, 42, ["orbit"], duration_s=3, particles=200)
    assert _same(ev.run_trials(cfg, workers=1, progress=False), ev.run_trials(cfg, workers=2, progress=False))


def test_a_method_does_not_change_another_methods_numbers(tiny, tiny_serial):
    alone = ev.run_trials(replace(tiny, methods=(ev.METHODS["hover"],)), workers=1, progress=False)
    for a, b in zip(alone, tiny_serial):
        assert np.array_equal(a.truth, b.truth)
        assert np.array_equal(a.traces["hover"].error_m, b.traces["hover"].error_m)


def test_all_methods_share_the_truth_and_the_uav_start(tiny_serial, tiny):
    for tr in tiny_serial:
        uav_starts = [t.uav[0] for t in tr.traces.values() if t.uav is not None]
        assert all(np.array_equal(s, tr.start) for s in uav_starts)
        assert tr.start[2] == tiny.scenario.uav.altitude_m
    assert not np.array_equal(tiny_serial[0].start, tiny_serial[1].start)  # a new start per trial


def test_dask_cluster_gives_the_same_trials(tiny, tiny_serial):
    """A worker process started as docs/RESULTS.md says (one BLAS thread, the pinned kernels of
    sim/evaluation/numerics.py in its environment) over TCP on loopback, the comms a remote scheduler uses."""
    distributed = pytest.importorskip("distributed")
    import dask

    from sim.evaluation.numerics import PINNED, can_pin
    env = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", **(PINNED if can_pin() else {})}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": env}), \
            distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, protocol="tcp://",
                                     host="127.0.0.1", scheduler_port=0, dashboard_address=None) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        got = ev.run_trials(tiny, scheduler=cluster.scheduler_address, progress=False)
    assert _same(tiny_serial, got)


@pytest.mark.slow
def test_short_evaluation_every_filter_keeps_every_target_and_fixed_beats_hover(quick):
    cfg = ev.make_config(quick, 4, 7, ev.DEFAULT_METHODS, duration_s=20, particles=1000)
    trials = ev.run_trials(cfg, workers=2, progress=False)
    s = ev.summarise(cfg, trials)
    lo, hi = s.nees_band
    tail = stats.chi2.ppf(0.999, 2)
    for name, m in s.methods.items():
        err = np.stack([t.traces[name].error_m for t in trials])
        nees = np.stack([t.traces[name].nees for t in trials])
        # kept: a lost track runs away at up to 16 m/s, and its filter is confidently wrong. A
        # single DF leaves the range loosely observed, so single errors of 100+ m happen; the
        # filter must know it (NEES), and never lose a target across a quarter of the area
        assert err.max() < 250.0, (name, err.max())
        assert lo <= m.nees_mean <= hi, (name, m.nees_mean, (lo, hi))
        # heavy tails: a consistent Gaussian filter exceeds the 99.9 % point in 0.1 % of cells;
        # a particle filter in clutter somewhat more, a lost track in most cells from then on
        assert np.mean(nees > tail) < 0.02, (name, np.mean(nees > tail))
    assert s.methods["fixed3"].rmse_mean_m < s.methods["hover"].rmse_mean_m
    # the paired statistics exist and are consistent with the per-method figures
    d = s.methods["fixed3"].diff_vs_ref
    assert d[1] <= d[0] <= d[2]
    assert s.ratio == pytest.approx(s.methods["greedy_l1"].rmse_mean_m / s.methods["fixed3"].rmse_mean_m)
    assert s.ratio_ci[0] <= s.ratio <= s.ratio_ci[1]
    assert (s.ratio, *s.ratio_ci) == s.methods["fixed3"].ratio_vs_ref  # one CI for one ratio in results.md
    # the greedy UAV moves (the paper's rule with N_r = 4: up to 20 m), the hover one does not
    assert s.methods["greedy_l1"].motion["mean_step_m"] > 1.0
    assert s.methods["hover"].motion["mean_step_m"] == 0.0
    step = quick.uav.n_radial * quick.uav.step_m
    for tr in trials:
        for name in ("greedy_l1", "orbit", "random"):
            u = tr.traces[name].uav
            assert np.all(np.linalg.norm(np.diff(u[:, :2], axis=0), axis=1) <= step + 1e-6)


def test_new_planners_run_in_the_evaluation_within_their_motion_limits(quick):
    """lookahead, lookahead_vehicle and greedy_vehicle are methods of pmon eval; the vehicle ones
    plan within the scenario's limits (here 8 m/s, 2 m/s^2) and are flown: the vehicle model
    follows each plan's setpoint (ArduCopter's stock 10 m/s, 2.5 m/s^2) and scans where it is a
    tick later, within a metre or two of the planned point, while the paper's jump model is not
    bound by them; every method gets a PCRB, and no estimator beats it by much (a few trials:
    sampling error)."""
    names = ["greedy_l1", "lookahead", "lookahead_vehicle", "greedy_vehicle"]
    # the user's own limits (as --set gives them: over the paper methods' policy, whose 10 m/s it replaces)
    slow = override(quick, {"planning.speed_max_mps": 8.0, "planning.accel_max_mps2": 2.0})
    cfg = ev.make_config(slow, 1, 11, names, duration_s=12, particles=300)
    tr = ev.run_trial(cfg, 0)
    for name in names:
        t = tr.traces[name]
        u = t.uav[:, :2]
        step = np.diff(u, axis=0)
        assert np.linalg.norm(step, axis=1).max() > 1.0, name  # it moves
        if name.endswith("vehicle"):
            assert t.plan_speed_mps.max() <= 8.0 + 1e-6, name
            assert t.plan_miss_m.max() < 3.0 and np.median(t.plan_miss_m) < 1.0, (name, t.plan_miss_m)
            assert np.linalg.norm(step, axis=1).max() <= 8.0 + 1.0, name
            # flown, not teleported to the plan: the scan is where the vehicle is
            assert t.plan_miss_m.min() > 0.0, name
        else:
            assert np.linalg.norm(step, axis=1).max() > 8.0 + 1e-6, name
            assert t.plan_miss_m is None
        b = tr.traces[name].bound_m2
        assert b.shape == tr.traces[name].error_m.shape and np.all(b > 0)
    s = ev.summarise(cfg, [tr])
    for name in names:
        assert 0.5 < s.methods[name].rmse_over_bound < 5.0, (name, s.methods[name].rmse_over_bound)
    # issue 4's vehicle target: each vehicle method against its planner with the jump model, paired
    for name, twin in (("lookahead_vehicle", "lookahead"), ("greedy_vehicle", "greedy_l1")):
        got, (ratio, _, _) = s.methods[name].vs_jump
        assert got == twin
        assert ratio == pytest.approx(s.methods[name].rmse_mean_m / s.methods[twin].rmse_mean_m)
        assert f"{name} / {twin} (the same planner, jump model): RMSE ratio {ratio:.2f}" in ev.results_markdown(s, "x")
    # and how to compare at equal speed: the grid step that makes the jump model as fast as the vehicle
    equal = f"`--set uav.step_m={8.0 * cfg.dt_s / slow.uav.n_radial:g}`"
    assert "the vehicle at most 8 m/s (2 m/s^2)" in ev.results_markdown(s, "x") and equal in ev.results_markdown(s, "x")
    assert s.methods["lookahead"].vs_jump is None
    assert ev.headline(s)["methods"]["greedy_vehicle"]["ratio_vs_jump"][0] == pytest.approx(
        s.methods["greedy_vehicle"].vs_jump[1][0], abs=1e-4)


@pytest.mark.slow
def test_the_flight_default_is_a_method_flown_with_the_autopilots_limits():
    """``flight`` is onboard/policy.py's flight default (with the side-aware filter), planned with the
    autopilot's WPNAV_SPEED / WPNAV_ACCEL capped by what the airframe flies; ``NAME@demo`` flies a
    vehicle method with the demo's parameters. A plan faster than the airframe (20 m/s on the demo's
    WPNAV_SPEED) is not flown: the copter tops out near 10 m/s (its drag at ANGLE_MAX) and falls
    behind its plan."""
    from onboard.config import load_scenario
    from onboard.core.monitor import particle_steering
    from onboard.core.tracking.steering import SideSteering
    from onboard.policy import POLICIES

    user = {"guidance.horizon": 20, "planning.lookahead_steps": 20, "tracking.particles": 300}
    sc = load_scenario("paper", user)
    names = ["flight", "flight@demo", "lookahead_vehicle@demo"]
    fast = load_scenario("paper", {**user, "planning.speed_max_mps": 20.0, "planning.accel_max_mps2": 5.0})
    cfg = ev.make_config(fast, 1, 5, names, duration_s=30)
    flight, demo, fast_plan = cfg.methods
    policy = load_scenario("paper", {**POLICIES["flight"], **user, "planning.speed_max_mps": 20.0,
                                     "planning.accel_max_mps2": 5.0})
    for m, (v, a) in ((flight, (10.0, 2.5)), (demo, (20.0, 5.0)), (fast_plan, (20.0, 5.0))):
        setup, _, limits = ev._setup_for(cfg, m)
        assert (setup.motion.kind, setup.motion.speed_max_mps, setup.motion.accel_max_mps2) == ("vehicle", v, a)
        assert (limits.speed_xy, limits.accel_xy) == (10.0, 2.5) if m is flight else (20.0, 5.0)
        if m is not fast_plan:  # the policy's settings, the user's own on top
            assert setup.planner == policy.planning.planner == "lookahead"
            assert setup.regularise_bandwidth == policy.tracking.regularise_bandwidth
            assert isinstance(particle_steering(setup), SideSteering)  # the side-aware filter (docs/TRACKING.md)
            assert setup.n_particles == 300 and setup.lookahead_steps == 20
    # the airframe's cap applies: the flight default on the demo's 20 m/s plans at its cap
    capped, _, _ = ev._setup_for(ev.make_config(sc, 1, 5, ["flight@demo"]), demo)
    airframe = load_scenario("paper", {**POLICIES["flight"], **user}).planning
    assert (capped.motion.speed_max_mps, capped.motion.accel_max_mps2) == (
        min(20.0, airframe.speed_max_mps), min(5.0, airframe.accel_max_mps2))
    tr = ev.run_trial(cfg, 0)
    t = tr.traces["lookahead_vehicle@demo"]
    assert t.plan_speed_mps.max() > 12.0  # it plans faster (up to 20 m/s, 5 m/s more than it flies) ...
    assert 9.0 < t.speed_mps.max() < 10.3  # ... and flies at the airframe's ceiling
    # each tick's plan starts from the vehicle (its telemetry), so the shortfall is a tick's worth
    assert np.median(t.plan_miss_m) > 1.5 > 1.0 > np.median(tr.traces["flight"].plan_miss_m)
    s = ev.summarise(cfg, [tr])
    md = ev.results_markdown(s, "x")
    assert "| lookahead_vehicle@demo | demo: 20 m/s, 5 m/s² | 20 m/s, 5 m/s² |" in md
    # the flight default against every other method of the run, paired (both flight methods)
    assert set(s.pairs) == {(a, b) for a in ("flight", "flight@demo") for b in names if b != a}
    (ratio, _, _), (diff, _, _) = s.pairs[("flight", "lookahead_vehicle@demo")]
    assert ratio == pytest.approx(s.methods["flight"].rmse_mean_m / s.methods["lookahead_vehicle@demo"].rmse_mean_m)
    assert diff == pytest.approx(s.methods["flight"].per_trial_rmse[0] - s.methods["lookahead_vehicle@demo"].per_trial_rmse[0])
    assert f"| flight | lookahead_vehicle@demo | {ratio:.2f} (" in md
    assert ev.headline(s)["flight_over"]["flight / lookahead_vehicle@demo"][0] == pytest.approx(ratio, abs=1e-4)
    assert ev.headline(s)["methods"]["flight"]["speed_peak_mps"] == pytest.approx(
        s.methods["flight"].flown["speed_peak_mps"], abs=1e-4)
    with pytest.raises(ValueError, match="greedy_l1 flies no vehicle"):
        ev.make_config(sc, 1, 5, ["greedy_l1@demo"])
    with pytest.raises(ValueError, match="unknown autopilot parameters 'x'"):
        ev.make_config(sc, 1, 5, ["flight@x"])


def test_the_evaluation_plans_with_the_autopilots_jerk_as_the_app_does(monkeypatch):
    """The flight default's jerk: min(the autopilot's, planning.jerk_max_mps3), as the app plans
    (onboard/policy.py vehicle_motion): ArduCopter's PSC_JERK_XY as its attitude loop caps it
    (stock 5; the demo's 20 capped at 15.3; 2 set), PX4's OFFBOARD none (the scenario's)."""
    from onboard.config import load_scenario

    monkeypatch.setitem(ev.AUTOPILOTS, "slowjerk", {"PSC_JERK_XY": 2.0})
    sc = load_scenario("paper", {"planning.jerk_max_mps3": 8.0, "tracking.particles": 300})
    want = {"flight": 5.0, "flight@demo": 8.0, "flight@px4": 8.0, "flight@slowjerk": 2.0}
    cfg = ev.make_config(sc, 1, 5, list(want))
    for m in cfg.methods:
        setup, _, _ = ev._setup_for(cfg, m)
        assert setup.motion.jerk_max_mps3 == want[m.name], m.name
    steps = load_scenario("paper", {"planning.jerk_max_mps3": 0.0, "tracking.particles": 300})
    cfg = ev.make_config(steps, 1, 5, ["flight@slowjerk"])
    assert ev._setup_for(cfg, cfg.methods[0])[0].motion.jerk_max_mps3 == 0.0  # steps stay steps


@pytest.mark.slow
def test_the_ceiling_is_a_bound_only_method_below_every_flown_path_at_its_limits(tmp_path):
    """``ceiling``: no filter runs (RMSE, NEES NaN; no RMSE rows), its path is a vehicle's at the
    flight default's limits from the trial's start, its bound is the evaluation's PCRB of that
    path and at most the flight's own path's (one of its search's starts), and adding it changes
    no other method's number. The summary pairs each UAV path's PCRB with it. ``ceiling_flown``
    flies that same path with the filter on its bearings."""
    from onboard.config import load_scenario

    sc = load_scenario("paper", {"guidance.horizon": 20, "planning.lookahead_steps": 20, "tracking.particles": 300})
    cfg = ev.make_config(sc, 2, 5, ["greedy_l1", "flight", "ceiling", "ceiling_flown"], duration_s=30)
    bare = ev.make_config(sc, 2, 5, ["greedy_l1", "flight"], duration_s=30)
    trials = [ev.run_trial(cfg, i) for i in range(2)]
    w0 = cfg.window_start
    for tr in trials:
        c, f = tr.traces["ceiling"], tr.traces["flight"]
        assert np.isnan(c.error_m).all() and np.isnan(c.nees).all()
        assert np.array_equal(c.uav[0], tr.start)
        setup, _, _ = ev._setup_for(cfg, cfg.methods[2])
        assert (setup.motion.speed_max_mps, setup.motion.accel_max_mps2) == (9.0, 2.5)  # the flight's, capped
        speed = np.linalg.norm(np.diff(c.uav[:, :2], axis=0), axis=1) / cfg.dt_s
        assert speed.max() <= 9.0 + 1e-6 and speed[0] <= 2.5 / 2 + 1e-6  # from rest, within the limits
        q = ev.information_reduction_factor(setup.sensor.p_detect, 1.0, setup.sensor.sigma_rad)
        again = ev.pcrb_position(setup.model, setup.initial_cov, tr.truth, tr.gains, c.uav[:, None, :2],
                                 setup.sensor.sigma_rad, q)
        assert np.allclose(again, c.bound_m2, rtol=1e-12)
        assert np.sqrt(c.bound_m2[w0:]).mean() < np.sqrt(f.bound_m2[w0:]).mean()
        cf = tr.traces["ceiling_flown"]
        assert np.array_equal(cf.uav, c.uav) and np.allclose(cf.bound_m2, c.bound_m2, rtol=1e-12)
        assert np.isfinite(cf.error_m).all() and cf.error_m[w0:].mean() < 100.0
        without = ev.run_trial(bare, tr.trial)
        for n in ("greedy_l1", "flight"):
            assert np.array_equal(without.traces[n].error_m, tr.traces[n].error_m)
    s = ev.summarise(cfg, trials)
    (r, lo, hi), per = s.ceiling["ratios"]["flight"]
    assert s.ceiling["name"] == "ceiling" and set(s.ceiling["ratios"]) == {"greedy_l1", "flight", "ceiling_flown"}
    assert 1.0 < r and lo <= r <= hi and (per > 1.0).all()
    assert r == pytest.approx(s.methods["flight"].bound_mean_m / s.methods["ceiling"].bound_mean_m)
    assert ("flight", "ceiling") not in s.pairs and s.methods["ceiling"].ratio_vs_ref is None
    head = ev.write_outputs(s, trials, tmp_path, "x", figures=False)
    assert head["methods"]["ceiling"]["rmse_mean_m"] is None
    assert head["pcrb_over_ceiling"]["flight"][0] == pytest.approx(r, abs=1e-4)
    assert ",ceiling," not in (tmp_path / "per_trial.csv").read_text() + (tmp_path / "rmse.csv").read_text()
    assert ",ceiling_flown," in (tmp_path / "per_trial.csv").read_text()
    assert f"| flight | 9 m/s, 2.5 m/s² | {s.methods['flight'].bound_mean_m:.2f} | {r:.3f} (" in \
        (tmp_path / "results.md").read_text()
    with pytest.raises(ValueError, match="a ceiling is a vehicle's"):
        ev.Method("c", "x", sensing="ceiling", motion="jump")


@pytest.mark.parametrize("kw, says", [({"planner": "astar"}, "planner must be one of"),
                                       ({"motion": "teleport"}, "motion must be"),
                                       ({"autopilot": "inav"}, "autopilot must be one of")])
def test_a_method_naming_an_unknown_planner_motion_or_autopilot_is_refused(kw, says):
    """A method is checked when declared (register_method, --methods), not when a worker runs it."""
    with pytest.raises(ValueError, match=says):
        ev.Method("m", "x", **kw)


def test_a_planner_a_bench_registers_is_the_one_its_method_flies(quick):
    """bench/ceiling_greedy.py's way: a Planner put in PLANNERS (not a setting the app accepts)
    and a method naming it; the evaluation flies that planner, not the scenario's."""
    from onboard.core.planner_choice import PLANNERS
    from onboard.core.planning.planners import Planner
    from onboard.core.planning.next_position import PlanningResult

    class East(Planner):
        def plan(self, inputs, rng):
            here = np.asarray(inputs.position, float) + [4.0, 0.0, 0.0]
            return PlanningResult(here[None], np.ones(1, bool), np.zeros((1, len(inputs.beliefs))), np.zeros(1), 0)

    PLANNERS["east4"] = lambda setup: East()
    try:
        ev.register_method(ev.Method("east4", "x", planner="east4", clutter_rate=1.0))
        cfg = ev.make_config(quick, 1, 3, ["east4"], duration_s=4, particles=100)
        uav = ev.run_trial(cfg, 0).traces["east4"].uav
        assert np.allclose(np.diff(uav[:, 0]), 4.0) and np.allclose(np.diff(uav[:, 1:], axis=0), 0.0)
        with pytest.raises(ConfigError, match="planning.planner"):
            override(quick, {"planning.planner": "east4"})  # the app's setting still refuses it
    finally:
        PLANNERS.pop("east4")
        ev.METHODS.pop("east4", None)


def test_workers_load_the_avx2_kernels_where_the_cpu_has_them():
    """sim.evaluation.numerics: OpenBLAS's and numpy's AVX-512 kernels round differently from their AVX2
    ones, so the evaluation's workers load the AVX2 ones on every x86-64 that has them (a
    variable the user set stays); a process started with them has no AVX-512 dispatch."""
    from sim.evaluation import numerics

    env: dict = {}
    if not numerics.pin_kernels(env):
        assert env == {} and not numerics.can_pin()
        pytest.skip("no AVX2 and FMA here: nothing is pinned")
    assert env == numerics.PINNED and numerics.kernels_description(env).startswith("kernels pinned to AVX2")
    own = {"OPENBLAS_CORETYPE": "Zen"}
    numerics.pin_kernels(own)
    assert own["OPENBLAS_CORETYPE"] == "Zen" and "OPENBLAS_CORETYPE=Zen" in numerics.kernels_description(own)
    probe = ("import numpy\ntry:\n from numpy._core._multiarray_umath import __cpu_features__ as f\n"
             "except ImportError:\n from numpy.core._multiarray_umath import __cpu_features__ as f\n"
             "print(bool(f.get('X86_V4') or f.get('AVX512_SKX')), bool(f.get('AVX2')))")
    clean = {k: v for k, v in os.environ.items() if k not in numerics.PINNED}
    got = subprocess.run([sys.executable, "-c", probe], env={**clean, **env}, capture_output=True, text=True,
                         timeout=60)
    assert got.stdout.split() == ["False", "True"], got.stderr


def _pinned_packages() -> bool:
    from importlib.metadata import version
    pins = dict(line.split("==") for line in (Path(__file__).parents[2] / "constraints.txt").read_text().split()
                if "==" in line)
    return all(version(p) == pins[p] for p in ("numpy", "scipy", "daqp", "osqp"))


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_docs_results_trial_0_reproduces_here(tmp_path):
    """README's claim: with the packages of constraints.txt, on any x86-64 with AVX2 and FMA,
    `pmon eval paper` gives the stored runs to the last digit (docs/results_flight_default/, the
    current code's truths). Trial 0 is one that the AVX-512 kernels give otherwise (fixed3 7.6431
    m against 7.6033, measured on this VM's EPYC with OPENBLAS_CORETYPE=SkylakeX and
    NPY_DISABLE_CPU_FEATURES empty)."""
    from sim.evaluation import numerics

    if not (numerics.can_pin() and _pinned_packages()):
        pytest.skip("needs the packages of constraints.txt on an x86-64 with AVX2 and FMA")
    out = tmp_path / "ev"
    res = run_cli("eval", "paper", "--trials", "1", "--seed", "2024", "--methods", "greedy_l1,fixed3",
                  "--workers", "1", "--no-figures", "--quiet", "--out", str(out))
    assert res.returncode == 0, res.stderr
    docs = Path(__file__).parents[2] / "docs" / "results_flight_default" / "per_trial.csv"
    want = {ln for ln in docs.read_text().splitlines() if ln.startswith(("0,greedy_l1,", "0,fixed3,"))}
    got = {ln for ln in (out / "per_trial.csv").read_text().splitlines() if ln.startswith("0,")}
    assert got == want and len(got) == 2


def test_orbit_converges_to_its_circle(quick):
    cfg = ev.make_config(quick, 1, 3, ["orbit"], duration_s=60, particles=100)
    tr = ev.run_trial(cfg, 0)
    u = tr.traces["orbit"].uav[:, :2]
    r = np.linalg.norm(u - cfg.orbit_center, axis=1)
    # from anywhere in the 1 km area it is on the circle within 1 km / 20 m/s = 50 s
    assert np.all(np.abs(r[-5:] - cfg.orbit_radius_m) < 5.0)


def test_nees_band_and_t_interval():
    lo, hi = ev.nees_band(100)
    assert lo < 2.0 < hi and hi - lo < 1.0
    m, a, b = ev.t_interval(np.array([1.0, 2.0, 3.0]))
    assert m == 2.0 and a < 2.0 < b


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "onboard.cli", *args], capture_output=True, text=True, timeout=240)


def test_pmon_eval_writes_csv_table_figures_and_a_json_line(tmp_path):
    """... and says where its results went, in a table, and warns of few trials (one run for both:
    this was two runs of the same kind, one in tests/app/test_cli.py)."""
    out = tmp_path / "ev"
    res = run_cli("eval", "--trials", "2", "--duration", "4", "--particles", "100", "--workers", "1",
                  "--methods", "greedy_l1,fixed3,hover", "--out", str(out), "--quiet")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    head = json.loads(lines[-1])  # the JSON line stays last
    assert lines[0].split()[:2] == ["method", "RMSE"]
    hover = next(x for x in lines if x.startswith("hover "))
    assert f"{head['methods']['hover']['rmse_mean_m']:.1f}" in hover
    assert f"results in {out}/: results.md" in res.stdout
    assert "warning: 2 trials: a 95 % confidence interval means little below about 10" in res.stderr
    assert set(head["methods"]) == {"greedy_l1", "fixed3", "hover"}
    assert all(set(v) >= {"rmse_mean_m", "nees_mean", "bound_m", "rmse_over_bound", "ratio_vs_ref"}
               for v in head["methods"].values())
    assert head["uav_vs_fixed_ratio"] == pytest.approx(
        head["methods"]["greedy_l1"]["rmse_mean_m"] / head["methods"]["fixed3"]["rmse_mean_m"], rel=1e-3)
    rows = (out / "rmse.csv").read_text().splitlines()
    assert rows[0] == "step,time_s,method,target,rmse_m"
    assert len(rows) == 1 + 4 * 3 * 5  # 4 steps x 3 methods x (4 targets + mean)
    for f in ("results.md", "rmse_vs_time.png", "scenario_3d.png", "scenario_top.png", "flight.png"):
        assert (out / f).stat().st_size > 1000, f
    md = (out / "results.md").read_text()
    assert "| greedy_l1 |" in md
    # the figures depend on the numerical stack to the last bit: a reader must be able to match it
    assert f"numpy {np.__version__}, scipy {scipy.__version__}" in md
    from sim.evaluation.numerics import can_pin
    assert ("kernels pinned to AVX2" in md) == can_pin()


@pytest.mark.parametrize("args, message", [
    (("--trials", "0"), "argument --trials: must be in 1..1000000"),
    (("--methods", "greedy_l1,teleport"), "unknown method 'teleport'"),
    (("--duration", "0.5"), "--duration must be at least"),
    (("--workers", "0"), "argument --workers: must be in 1..4096"),
    (("--scheduler", "not an address"), "--scheduler"),
    (("--set", "planning.speed_max_mps"), "expected KEY=VALUE"),
    (("--set", "planning.speed_max_mps=-1"), "planning.speed_max_mps: must be in (0, 30] m/s, got -1.0"),
    (("--particles", "50"), "argument --particles: must be in 100..20000"),
    (("--methods", "lookahead", "--set", "planning.planner=greedy", "--set", "guidance.horizon=20"),
     "method lookahead: planning.lookahead_steps: must be <= guidance.horizon (20)"),
    (("--set", "guidance.horizon=20"),  # the declared lookahead follows the guidance plans
     "planning.lookahead_steps: must be <= guidance.horizon (20) with the lookahead planner"),
])
def test_pmon_eval_bad_arguments(tmp_path, args, message, capsys):
    """Through pmon's main(argv) in this process (no Python start-up per case; the real program
    runs in the other tests here)."""
    from onboard.cli import main
    try:
        rc = main(["eval", "--out", str(tmp_path / "x"), *args])
    except SystemExit as exc:  # argparse
        rc = exc.code
    err = capsys.readouterr().err
    assert rc == 2
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "x").exists()


def _state_and_parent(pid: int) -> tuple[str, int] | None:
    """(state letter, parent pid) of a process from /proc, None once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return fields[0], int(fields[1])


def _alive(pid: int) -> bool:
    st = _state_and_parent(pid)
    return st is not None and st[0] != "Z"


def _children(pid: int) -> list[int]:
    """Live (not zombie) processes whose parent is pid."""
    out = []
    for d in Path("/proc").iterdir():
        st = _state_and_parent(int(d.name)) if d.name.isdigit() else None
        if st is not None and st[0] != "Z" and st[1] == pid:
            out.append(int(d.name))
    return out


def _workers(pid: int) -> list[int]:
    """pid's multiprocessing workers (its resource tracker is a child too, not a worker)."""
    out = []
    for k in _children(pid):
        try:
            if b"--multiprocessing-fork" in Path(f"/proc/{k}/cmdline").read_bytes():
                out.append(k)
        except OSError:
            continue
    return out


def test_a_sigterm_while_the_worker_pool_starts_stops_the_run_and_the_pool():
    """SIGTERM in the milliseconds while the pool starts is recorded, not raised half-way
    through building it: it stops the run as soon as the pool exists, and the pool is terminated.
    (Before, the main thread blocked SIGTERM; this process's other threads did not, so the signal
    could land on one and raise inside the pool's constructor, leaving started workers behind.)"""
    class Pool:
        terminated = False

        def terminate(self):
            self.terminated = True

    class Ctx:
        def Pool(self, workers, initializer):
            os.kill(os.getpid(), signal.SIGTERM)  # a service manager stops the run now
            time.sleep(0.05)  # still starting
            self.pool = Pool()
            return self.pool

    ctx, ran = Ctx(), []
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as stop:
        with ev._worker_pool(ctx, 2):
            ran.append(True)
    assert stop.value.code == 143
    assert ctx.pool.terminated and not ran
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
@pytest.mark.parametrize("how, code", [("sigterm", 143), ("ctrl-c", 130)])
def test_pmon_eval_stopped_midway_stops_its_workers(tmp_path, how, code):
    """SIGTERM to pmon eval, or Ctrl-C to its process group, while two workers run trials: it
    exits with 128 + the signal, says how far it got, writes nothing, no worker prints a
    traceback (they ignore SIGINT from birth) and none is left computing (before: SIGTERM
    orphaned them, Ctrl-C waited for the running trials)."""
    out = tmp_path / "ev"
    p = subprocess.Popen([sys.executable, "-m", "onboard.cli", "eval", "--trials", "8", "--methods", "greedy_l1",
                          "--workers", "2", "--no-figures", "--quiet", "--out", str(out)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 60
        while len(_workers(p.pid)) < 2 and time.monotonic() < deadline and p.poll() is None:
            time.sleep(0.1)
        kids = _children(p.pid)
        assert len(_workers(p.pid)) >= 2, "the workers never started"
        time.sleep(1.0)  # importing or inside their first trials (several seconds each): either way
        if how == "sigterm":
            os.kill(p.pid, signal.SIGTERM)
        else:
            os.killpg(p.pid, signal.SIGINT)
        _, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
    assert p.returncode == code, err
    assert re.search(r"stopped after [0-7] of 8 trials", err) and "Traceback" not in err
    assert not out.exists()
    deadline = time.monotonic() + 5
    while any(_alive(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(k) for k in kids)
