import numpy as np
import pytest

from onboard.core.guidance.predictor import Feedback, GuidanceParams, Plan, PlanAsk, Solver, plan_guidance, winding
from onboard.core.obstacles import Obstacles
from sim.evaluation.miqp_reference import random_instance

from onboard.settings.sections import Guidance  # noqa: E402  (the declared defaults)

PARAMS = GuidanceParams.from_config(Guidance(horizon=25, obstacle_margin_m=5.0, max_qp_solves=16))


def check_plan(plan, obs, mean0, params):
    pts = np.vstack([mean0[:3], plan.means[:, :3]])
    inflated = obs.inflate(params.obstacle_margin_m - 0.01)
    assert not inflated.contains(pts[1:]).any()
    assert not inflated.segments_cross(pts[1:-1], pts[2:]).any()  # p_0 -> p_1 is not controllable
    assert np.all(np.abs(plan.controls[:, :2]) <= params.u_max_n + 1e-6)
    assert np.all(plan.controls[:, 2] == 0)
    speed = np.linalg.norm(plan.means[:, 3:5], axis=1)
    assert np.all(speed <= params.speed_max_mps + 1e-3)


def test_plans_on_random_layouts_are_safe_and_within_bounds():
    rng = np.random.default_rng(7)
    statuses = []
    for _ in range(200):
        obs, mean0, goal = random_instance(rng, PARAMS.obstacle_margin_m)
        plan = plan_guidance(_model(), PARAMS, obs, mean0, goal)
        statuses.append(plan.status)
        if plan.feasible:
            check_plan(plan, obs, mean0, PARAMS)
    assert statuses.count("fallback_coast") <= 4, statuses  # at most 2 % without a plan


def _model():
    from onboard.core.dynamics import MotionModel
    return MotionModel.create(1.0, 0.2, 1300.0, [30, 30, 1e-10, 3, 3, 1e-10])


def test_receding_horizon_target_arrives_at_goal(paper, model):
    """Replanned every second along its own plan, each paper target reaches the goal region."""
    params = GuidanceParams.from_config(paper.guidance)
    obs = Obstacles.from_boxes(paper.obstacles)
    for target in paper.targets:
        goal = np.array(paper.goal_of(target).center_m)
        x, plan, fallbacks = target.mean, None, 0
        for _ in range(110):
            plan = plan_guidance(model, params, obs, x, goal, previous=plan)
            fallbacks += not plan.feasible
            x = plan.means[0]
            assert not obs.contains(x[:3]).any()
        assert np.linalg.norm(x[:2] - goal[:2]) < 10.0, target.name
        assert fallbacks <= 5, (target.name, fallbacks)


def test_plan_reports_cost_time_and_warm_start(paper, model):
    params = GuidanceParams.from_config(paper.guidance)
    obs = Obstacles.from_boxes(paper.obstacles)
    t = paper.targets[3]
    goal = np.array(paper.goal_of(t).center_m)
    first = plan_guidance(model, params, obs, t.mean, goal)
    second = plan_guidance(model, params, obs, first.means[0], goal, previous=first)
    assert first.feasible and np.isfinite(first.cost) and first.solve_time_s > 0
    assert second.qp_solves <= first.qp_solves  # the shifted assignment is reused
    assert second.cost < first.cost


@pytest.mark.slow
def test_cost_matches_exact_miqp_on_small_instances():
    """The same problem as an exact MIQP (SCIP): never infeasible where it found a solution, never
    cheaper (same constraints), within 1 % on most instances (bench/guidance_vs_miqp.py measures
    the fraction on 100)."""
    from sim.evaluation.miqp_reference import solve_p1_exact
    rng = np.random.default_rng(3)
    params = GuidanceParams.from_config(Guidance(horizon=10, obstacle_margin_m=5.0))
    ratios = []
    for _ in range(8):
        obs, mean0, goal = random_instance(rng, params.obstacle_margin_m, blocked=True)
        ours = plan_guidance(_model(), params, obs, mean0, goal)
        ref = solve_p1_exact(_model(), params, obs, mean0, goal, time_limit_s=30)
        if not np.isfinite(ref["cost"]):
            continue
        assert ours.feasible, "infeasible where the exact solver found a solution"
        check_plan(ours, obs, mean0, params)
        assert ours.cost >= ref["cost"] * (1 - 1e-4)  # not better than exact: same problem
        ratios.append(ours.cost / ref["cost"])
    assert len(ratios) >= 6
    assert np.mean(np.array(ratios) <= 1.01) >= 0.75, ratios
    assert max(ratios) <= 1.10, ratios


def test_closed_loop_gain_matches_finite_differences(paper, model):
    """Plan.feedback (du_0/dx, for the bound of a target that steers by this guidance) comes from
    the QP's sensitivity with the active set held: it equals central differences of the QP's
    solution for the plan's own face assignment, and zero-gain directions are those the
    constraints pin."""
    from onboard.core.guidance.predictor import GuidanceWorkspace
    from onboard.core.guidance.faces import face_geometry
    from onboard.core.dynamics import predict_mean
    params = GuidanceParams.from_config(paper.guidance)
    obs = Obstacles.from_boxes(paper.obstacles)
    ws = GuidanceWorkspace()
    T = params.horizon
    for target in paper.targets:
        goal = np.array(paper.goal_of(target).center_m)
        x, plan = np.array(target.mean, float), None
        for _ in range(20):
            plan = plan_guidance(model, params, obs, x, goal, previous=plan, solver=Solver(ws))
            x = plan.means[0]
        plan = plan_guidance(model, params, obs, x, goal, previous=plan, ask=PlanAsk(Feedback.ALWAYS),
                             solver=Solver(ws))
        assert plan.feedback is not None and plan.feedback.shape == (3, 6)
        qp = ws.qp(T, len(obs), model, params)
        z = np.concatenate([[x[2]], predict_mean(model, x, np.zeros((T, 3)))[:, 2]])
        geo = face_geometry(obs, params.obstacle_margin_m, z)
        rows = geo.rows(plan.faces)

        def p2(state):
            x0 = state[[0, 1, 3, 4]]
            bound = np.maximum(params.speed_max_mps * np.cos(np.pi / params.speed_polygon_sides),
                               np.linalg.norm(x0[2:]) * (1 - model.friction) ** np.arange(1, T + 1) + 1e-6)
            return qp.solve(x0, goal[:2], bound, *rows), bound
        sol, bound = p2(x)
        dP = qp.sensitivity(x[[0, 1, 3, 4]], goal[:2], bound, *rows, sol)
        for col, i in enumerate((0, 1, 3, 4)):
            # the derivative with the active set held: a central difference, or a one-sided one
            # where the state sits on a kink (a row changes activity on one side)
            h = 1e-4
            up, down = x.copy(), x.copy()
            up[i] += h
            down[i] -= h
            s_up, s_down = p2(up)[0], p2(down)[0]
            same_up = np.array_equal(s_up.lam != 0, sol.lam != 0)
            same_down = np.array_equal(s_down.lam != 0, sol.lam != 0)
            assert same_up or same_down, f"{target.name} state {i}: active set changes both ways"
            if same_up and same_down:
                fd = (s_up.pts[1] - s_down.pts[1]) / (2 * h)
            elif same_up:
                fd = (s_up.pts[1] - sol.pts[1]) / h
            else:
                fd = (sol.pts[1] - s_down.pts[1]) / h
            np.testing.assert_allclose(dP[0, :, col], fd, atol=1e-3, err_msg=f"{target.name} state {i}")


def test_free_law_is_the_guidance_wherever_it_says_so(paper, model):
    """FreeLaw.is_optimal marks states whose unconstrained optimum is P1's optimum: there the
    guidance (solved in full, with the obstacles) commands exactly FreeLaw.controls. It recognises
    most states whose plan has no active row, and the free gain pulls deviations back."""
    from onboard.core.guidance.predictor import free_law
    params = GuidanceParams.from_config(paper.guidance)
    obs = Obstacles.from_boxes(paper.obstacles)
    law = free_law(model, params)
    closed = model.A + model.B @ law.gain
    planar = [0, 1, 3, 4]
    assert np.max(np.abs(np.linalg.eigvals(closed[np.ix_(planar, planar)]))) < 1.0
    goal = np.array(paper.goal_of(paper.targets[0]).center_m)
    rng = np.random.default_rng(7)
    # around the goal and the obstacle O3 north of it, slow and fast
    states = np.zeros((150, 6))
    states[:, :2] = goal[:2] + rng.uniform([-150, -60], [150, 270], (150, 2))
    states[:, 3:5] = rng.normal(0, 2, (150, 2))
    states = states[~obs.inflate(params.obstacle_margin_m).contains(states[:, :3]).any(axis=1)]
    ok = law.is_optimal(states, goal, obs)
    u = law.controls(states, goal)
    free_plans = 0
    for x, says, u_free in zip(states, ok, u):
        plan = plan_guidance(model, params, obs, x, goal)
        if says:
            assert plan.unconstrained
            np.testing.assert_allclose(plan.next_control, u_free, atol=1.0)
        free_plans += plan.unconstrained
    assert 10 < ok.sum() and ok.sum() >= 0.9 * free_plans
    # a small wall between an arriving target and its goal: the free path would cross it
    from onboard.settings.sections import Box
    wall = Obstacles.from_boxes([Box("wall", (goal[0], goal[1] + 30.0, 10.0), (30.0, 6.0, 20.0), 0.0)])
    x = np.r_[goal[:2] + [0.0, 60.0], 0, 0, 0, 0][None]
    assert law.is_optimal(x, goal, Obstacles.empty())[0] and not law.is_optimal(x, goal, wall)[0]
    assert plan_guidance(model, params, wall, x[0], goal).touches_obstacle


def test_feedback_says_which_plans_get_their_law(paper, model):
    """Feedback: NONE, no plan has a law; ALWAYS, every plan; CONSTRAINED, only a plan with an
    active row (the free law describes the others). A value that is none of them is refused."""
    from onboard.settings.sections import Box
    params = GuidanceParams.from_config(paper.guidance)
    goal = np.array(paper.goal_of(paper.targets[0]).center_m)
    wall = Obstacles.from_boxes([Box("wall", (goal[0], goal[1] + 30.0, 10.0), (30.0, 6.0, 20.0), 0.0)])
    at_goal, behind_wall = np.r_[goal[:2], 0, 0, 0, 0], np.r_[goal[:2] + [0.0, 60.0], 0, 0, 0, 0]
    for x, obs, constrained in ((at_goal, Obstacles.empty(), False), (behind_wall, wall, True)):
        plans = {f: plan_guidance(model, params, obs, x, goal, ask=PlanAsk(f)) for f in Feedback}
        assert plans[Feedback.NONE].unconstrained is not constrained
        assert plans[Feedback.NONE].law is None and plans[Feedback.ALWAYS].law is not None
        assert (plans[Feedback.CONSTRAINED].law is not None) is constrained
    with pytest.raises(ValueError, match="True is not a valid Feedback"):
        plan_guidance(model, params, wall, behind_wall, goal, ask=PlanAsk(True))


def test_free_particles_steer_by_the_free_law_the_rest_by_the_plan(paper, model, rng):
    """The free steering: a particle whose own plan is the free optimum gets its control;
    the others get the plan's u, and only they can draw the random control of the mixture."""
    from dataclasses import replace as dc_replace
    from onboard.core.guidance.qp import ActiveRows
    from onboard.core.monitor import MonitorSetup
    from onboard.core.tracking.steering import particle_controls
    sc = dc_replace(paper, tracking=dc_replace(paper.tracking, control_mix=0.5))
    setup = MonitorSetup.from_scenario(sc)
    goal = setup.goals[0]
    T, K = setup.guidance.horizon, len(setup.obstacles)
    u = np.array([100.0, -50.0, 0.0])
    plan = Plan("optimal", 0.0, 0.0, 1, np.tile(u, (T, 1)), np.zeros((T, 6)), np.zeros((T - 1, K), int),
                ActiveRows(np.zeros(10, bool), np.zeros((K, T - 1, 2), bool)))
    near = np.tile(np.r_[goal[:2] + [10.0, -5.0], 0, 0.5, 0, 0], (500, 1))  # arriving: free
    far = np.tile(np.r_[goal[:2] + [0.0, 500.0], 0, 0, 0, 0], (500, 1))  # behind O3: not free
    out = particle_controls(plan, np.vstack([near, far]), goal, setup, rng)
    np.testing.assert_allclose(out[:500], setup.free_steering.controls(near, goal))
    assert np.all(out[:500, 0] < 0) and np.all(out[:500, 1] > 0)  # back toward the goal
    n_plan = int(np.all(out[500:] == u, axis=1).sum())
    assert 150 < n_plan < 350  # the rest: half the plan's u, half random


def test_plan_law_steers_a_nearby_start_as_the_guidance_does(paper, model):
    """Plan.law (u_0 + gain (x - start), Feedback.ALWAYS): at its start it is the plan's
    control, and from a start a little off, in most directions (one can cross a kink where a
    speed-polygon row switches), it moves the control as the guidance itself does."""
    from onboard.core.guidance.predictor import GuidanceWorkspace
    params = GuidanceParams.from_config(paper.guidance)
    obs = Obstacles.from_boxes(paper.obstacles)
    ws = GuidanceWorkspace()
    target = paper.targets[0]
    goal = np.array(paper.goal_of(target).center_m)
    x, plan = np.array(target.mean, float), None
    for _ in range(20):  # T1 heads south-east, rounding O1 and then O3
        plan = plan_guidance(model, params, obs, x, goal, previous=plan, solver=Solver(ws))
        x = plan.means[0]
    assert plan.touches_obstacle and plan.law is None  # only asked for
    steered = plan_guidance(model, params, obs, x, goal, previous=plan, ask=PlanAsk(Feedback.ALWAYS),
                            solver=Solver(ws))
    assert steered.law is not None
    np.testing.assert_allclose(steered.law.controls(x[None])[0], steered.next_control, atol=1e-6)
    agree = 0
    for dx in ([0.02, 0, 0, 0, 0, 0], [0, -0.02, 0, 0, 0, 0], [0, 0, 0, 0.002, 0, 0], [0, 0, 0, 0, -0.002, 0]):
        x1 = x + np.array(dx)
        own = (plan_guidance(model, params, obs, x1, goal, previous=plan, solver=Solver(ws)).next_control
               - steered.next_control)
        law = steered.law.controls(x1[None])[0] - steered.next_control
        assert np.linalg.norm(own) > 1e-3  # the guidance does react
        agree += np.linalg.norm(law - own) <= 0.05 * np.linalg.norm(own)
    assert agree >= 3


def test_rounding_particles_steer_by_the_nearest_reference_law(paper, model, rng):
    """tracking.plan_steering: of the particles not on the free law, a share plan_steered_share
    takes the control of the nearest reference law (clipped to the input box) if within
    plan_trust_sigma of it; the others keep the plan's control (or the mixture's random one)."""
    from dataclasses import replace as dc_replace
    from onboard.core.guidance.predictor import LocalLaw
    from onboard.core.guidance.qp import ActiveRows
    from onboard.core.monitor import MonitorSetup
    from onboard.core.tracking.steering import particle_controls
    sc = dc_replace(paper, tracking=dc_replace(paper.tracking, control_mix=0.0, plan_steering=True,
                                               plan_steered_share=0.7))
    setup = MonitorSetup.from_scenario(sc)
    assert setup.plan_steering is not None and setup.plan_steering.steered_share == 0.7
    goal = setup.goals[0]
    T, K = setup.guidance.horizon, len(setup.obstacles)
    u = np.array([100.0, -50.0, 0.0])
    plan = Plan("optimal", 0.0, 0.0, 1, np.tile(u, (T, 1)), np.zeros((T, 6)), np.zeros((T - 1, K), int),
                ActiveRows(np.zeros(10, bool), np.ones((K, T - 1, 2), bool)))
    gain = np.zeros((3, 6))
    gain[0, 0] = -50.0  # N per m east of the reference
    a = LocalLaw(np.array([500.0, 600.0, 0.0, -10.0]), np.array([1000.0, 0.0, 0.0]), gain)
    b = LocalLaw(np.array([500.0, 700.0, 0.0, -10.0]), np.array([-1000.0, 0.0, 0.0]), gain)
    near_a = np.tile([504.0, 610.0, 0.0, 0.0, -10.0, 0.0], (1000, 1))
    near_b = np.tile([400.0, 690.0, 0.0, 0.0, -10.0, 0.0], (1000, 1))
    metric = np.eye(2) / 100.0 ** 2  # sigma 100 m
    out = particle_controls(plan, np.vstack([near_a, near_b]), goal, setup, rng, [a, b], metric)
    on_a = np.all(out[:1000] == [1000.0 - 200.0, 0.0, 0.0], axis=1)
    on_b = np.all(out[1000:] == [-1000.0 + 5000.0, 0.0, 0.0], axis=1)
    kept = np.all(out == u, axis=1)
    assert 620 < on_a.sum() < 780 and 620 < on_b.sum() < 780  # the steered share
    assert np.all(on_a | kept[:1000]) and np.all(on_b | kept[1000:])
    clipped = np.tile([320.0, 700.0, 0.0, 0.0, -10.0, 0.0], (100, 1))  # 1.8 sigma; law -1000 + 9000 N
    out = particle_controls(plan, clipped, goal, setup, rng, [b], metric)
    assert np.all(np.abs(out[:, :2]) <= setup.guidance.u_max_n) and (out[:, 0] == setup.guidance.u_max_n).any()
    far = np.tile([200.0, 690.0, 0.0, 0.0, -10.0, 0.0], (100, 1))  # 3 sigma > plan_trust_sigma = 2
    out = particle_controls(plan, far, goal, setup, rng, [b], metric)
    assert np.all(out == u)  # not pulled onto a plan linearised 300 m away


def test_reference_plans_spread_along_the_cloud_major_axis(paper, model):
    """tracking.plan_steering builds one law from the mean's plan and plan_references more, from
    points within +-plan_spread_sigma standard deviations along the cloud's major position axis,
    each a feasible plan of its own; the metric is the inverse position covariance."""
    from dataclasses import replace as dc_replace
    from onboard.core.guidance.predictor import GuidanceWorkspace
    from onboard.core.monitor import MonitorSetup, replanner
    from onboard.core.tracking.steering import TargetTick, reference_laws
    sc = dc_replace(paper, tracking=dc_replace(paper.tracking, plan_steering=True, plan_references=2,
                                               plan_spread_sigma=1.5))
    setup = MonitorSetup.from_scenario(sc)
    ws = GuidanceWorkspace()
    goal = setup.goals[1]
    mean = np.array([280.0, 680.0, 0.0, 8.0, -10.0, 0.0])  # T2 before O1 and O4
    plan = plan_guidance(setup.model, setup.guidance, setup.obstacles, mean, goal, ask=PlanAsk(Feedback.ALWAYS),
                         solver=Solver(ws))
    cov = np.diag([900.0, 100.0, 1e-10, 4.0, 4.0, 1e-10])  # 30 m east-west, 10 m north-south
    def target(setup, mean, plan, previous):  # reference_laws reads no particles
        return TargetTick(None, mean, cov, goal, plan, previous, replanner(setup, goal, ws, lambda: 0.0))
    laws, metric, refs = reference_laws(setup.plan_steering, target(setup, mean, plan, None), ())
    assert len(laws) == 3 and laws[0] is plan.law and len(refs) == 2
    np.testing.assert_allclose(metric, np.linalg.inv(cov[:2, :2] + 1e-6 * np.eye(2)))
    offsets = sorted(lw.x_ref[0] - mean[0] for lw in laws[1:])
    np.testing.assert_allclose(offsets, [-45.0, 45.0], atol=1e-6)  # 1.5 sigma east and west
    assert all(abs(lw.x_ref[1] - mean[1]) < 1e-6 for lw in laws[1:])
    four = MonitorSetup.from_scenario(dc_replace(sc, tracking=dc_replace(sc.tracking, plan_references=4)))
    laws, _, _ = reference_laws(four.plan_steering, target(four, mean, plan, None), ())
    np.testing.assert_allclose(sorted(lw.x_ref[0] - mean[0] for lw in laws[1:]), [-45.0, -22.5, 22.5, 45.0],
                               atol=1e-6)
    # next tick each reference is warm-started by its own plan from the same offset: it keeps
    # its way around the obstacles for fewer QP solves than when started from the mean's plan
    mean2 = plan.means[0]
    plan2 = plan_guidance(setup.model, setup.guidance, setup.obstacles, mean2, goal, previous=plan,
                          ask=PlanAsk(Feedback.ALWAYS), solver=Solver(ws))
    _, _, own = reference_laws(setup.plan_steering, target(setup, mean2, plan2, plan), refs)
    _, _, cold = reference_laws(setup.plan_steering, target(setup, mean2, plan2, plan), ())
    pairs = [(a, b, c) for a, b, c in zip(refs, own, cold) if b is not None and c is not None]
    assert pairs
    for before, warm, from_mean in pairs:
        np.testing.assert_array_equal(warm.faces[:-1], before.faces[1:])
    assert sum(w.qp_solves for _, w, _ in pairs) < sum(c.qp_solves for _, _, c in pairs)


def test_start_inside_an_inflated_obstacle_is_planned_from_just_outside(paper, model):
    """An estimate between particles on both sides of an obstacle can lie inside it: the plan
    starts from the nearest point outside (same velocity), is feasible, and avoids it."""
    params = GuidanceParams.from_config(paper.guidance)
    obs = Obstacles.from_boxes(paper.obstacles)
    box = paper.obstacles[0]
    centre = np.array(box.center_m, float)
    x = np.array([centre[0], centre[1], 0.0, 0.0, 0.0, 0.0])
    goal = np.array(paper.goal_of(paper.targets[0]).center_m)
    plan = plan_guidance(model, params, obs, x, goal)
    assert plan.feasible and plan.status in ("optimal", "budget")
    inflated = obs.inflate(params.obstacle_margin_m - 0.1)
    assert not inflated.contains(np.column_stack([plan.means[:, :2], np.zeros(len(plan.means))])).any()


def test_target_faster_than_its_speed_bound_gets_a_plan_that_slows_it(paper, model):
    """Noise can carry a target past speed_max / (1 - friction); its plan slows it down under
    the relaxed speed polygon (the bound friction alone meets) instead of failing: a failed plan
    leaves the target on stale controls and the predictor with no plan."""
    params = GuidanceParams.from_config(paper.guidance)
    n = params.speed_polygon_sides
    ang = -np.pi / 2 + np.pi / n  # toward a corner of the speed polygon, between two of its normals
    v0 = 21.0
    x = np.array([200.0, 900.0, 0.0, v0 * np.cos(ang), v0 * np.sin(ang), 0.0])  # clear of the obstacles
    goal = np.array(paper.goal_of(paper.targets[0]).center_m)
    for obs in (Obstacles.from_boxes(()), Obstacles.from_boxes(paper.obstacles)):
        plan = plan_guidance(model, params, obs, x, goal)
        assert plan.feasible and plan.status in ("optimal", "budget")
        speed = np.linalg.norm(plan.means[:, 3:5], axis=1)
        decay = 1.0 - model.friction
        relaxed = np.maximum(params.speed_max_mps, v0 * decay ** np.arange(1, len(speed) + 1) / np.cos(np.pi / n))
        assert np.all(speed <= relaxed + 1e-3)
        assert speed[0] < v0 and np.all(speed[5:] <= params.speed_max_mps + 1e-3)


def test_target_that_cannot_keep_the_margin_keeps_clear_of_the_obstacle(paper, model):
    """A target 13 m north of O3 closing at 9 m/s reaches its 5 m margin before any control
    can stop it: its plan keeps clear of the obstacle itself (margin_m 0), not a fallback that
    coasts into it; a target with room keeps the margin."""
    params = GuidanceParams.from_config(paper.guidance)
    obs = Obstacles.from_boxes(paper.obstacles)
    o3 = next(b for b in paper.obstacles if b.name == "O3")
    north = o3.center_m[1] + o3.size_m[1] / 2  # y of O3's north face
    goal = np.array(paper.goal_of(paper.targets[0]).center_m)
    x = np.array([o3.center_m[0], north + 13.0, 0.0, 0.0, -9.0, 0.0])
    plan = plan_guidance(model, params, obs, x, goal)
    assert plan.feasible and plan.margin_m == 0.0
    pts = np.vstack([x[:3], plan.means[:, :3]]) + [0.0, 0.0, 1.0]  # 1 m up: O3 stands on the ground
    assert not obs.contains(pts).any() and not obs.segments_cross(pts[1:-1], pts[2:]).any()
    coasting = model.A @ (model.A @ x)  # what a fallback without a previous plan does
    assert obs.contains(coasting[None, :3] + [0.0, 0.0, 1.0]).any()
    x_far = x.copy()
    x_far[1] += 60.0
    assert plan_guidance(model, params, obs, x_far, goal).margin_m == params.obstacle_margin_m


def _one_box(paper, **tracking):
    """The paper's setup with one 100 m box at the origin and T2's goal 300 m south of it."""
    from dataclasses import replace as dc_replace
    from onboard.settings.sections import Box
    from onboard.core.monitor import MonitorSetup
    sc = dc_replace(paper, tracking=dc_replace(paper.tracking, **tracking))
    obs = Obstacles.from_boxes([Box("B", (0.0, 0.0, 25.0), (100.0, 100.0, 50.0))])
    goals = np.tile([0.0, -300.0, 0.0], (len(paper.targets), 1))
    return dc_replace(MonitorSetup.from_scenario(sc), obstacles=obs, goals=goals)


def test_winding_is_the_side_a_plan_rounds_an_obstacle_and_sides_hold_it(paper, model):
    """A target heading south toward a box: passing it on the west is counterclockwise about the
    box (winding > 0, the box on the path's left), on the east clockwise; ``sides`` with
    ``strict_sides`` makes P1 plan the best path round the side asked for, and the unrestricted
    plan is the cheaper one. Without ``strict_sides`` holding back (winding 0) is allowed."""
    from onboard.core.guidance.predictor import in_class, winding
    setup = _one_box(paper)
    x = np.array([-20.0, 300.0, 0.0, 0.0, -10.0, 0.0])  # a little west of the box's axis
    goal = setup.goals[0]
    free = plan_guidance(model, setup.guidance, setup.obstacles, x, goal)
    west = plan_guidance(model, setup.guidance, setup.obstacles, x, goal,
                         ask=PlanAsk(sides=np.array([1]), strict_sides=True))
    east = plan_guidance(model, setup.guidance, setup.obstacles, x, goal,
                         ask=PlanAsk(sides=np.array([-1]), strict_sides=True))
    assert west.feasible and east.feasible
    assert winding(west.faces)[0] > 0 > winding(east.faces)[0]
    assert in_class(west.faces, np.array([1])) and not in_class(west.faces, np.array([-1]))
    holding = np.ones_like(west.faces)  # north of the box all along
    assert winding(holding)[0] == 0
    assert in_class(holding, np.array([-1])) and not in_class(holding, np.array([-1]), strict=True)
    beside = np.abs(west.means[:, 1]) < 50.0  # abreast of the box
    assert np.all(west.means[beside, 0] < -50.0) and np.all(east.means[beside, 0] > 50.0)
    for plan in (west, east):
        check_plan(plan, setup.obstacles, x, setup.guidance)
    assert west.cost < east.cost  # it starts on the west
    assert winding(free.faces)[0] > 0 and free.cost == pytest.approx(west.cost, rel=1e-6)


def test_side_modes_split_the_cloud_at_a_knife_edge_and_keep_each_particle_side(paper, model, rng):
    """tracking.plan_sides: a cloud heading straight at a box, where both sides cost P1 the same,
    gets one mode per side, each holding about half of the particles; next tick every particle
    keeps its side (the true target keeps the side its plan took), each mode re-planned from its
    own particles and steering them by its own law."""
    from dataclasses import replace as dc_replace
    from onboard.core.tracking import filter as tracking
    from onboard.core.guidance.predictor import GuidanceWorkspace, winding
    from onboard.core.monitor import replanner
    from onboard.core.tracking.steering import TargetTick, particle_controls, side_modes
    setup = _one_box(paper, plan_steering=True, plan_sides=True, control_mix=0.0)
    ws = GuidanceWorkspace()
    goal = setup.goals[0]
    mean = np.array([0.0, 300.0, 0.0, 0.0, -10.0, 0.0])
    cov = np.diag([400.0, 400.0, 1e-10, 1.0, 1.0, 1e-10])
    ps = tracking.initialise(mean, cov, 2000, rng)
    m, c = tracking.estimate(ps)
    plan = plan_guidance(model, setup.guidance, setup.obstacles, m, goal, ask=PlanAsk(Feedback.ALWAYS),
                         solver=Solver(ws))
    laws, modes = side_modes(setup, TargetTick(ps, m, c, goal, plan, None, replanner(setup, goal, ws, lambda: 0.0)),
                             (), rng)
    labels = laws.labels
    assert len(modes) == 2 and modes[0].plan is plan
    assert winding(modes[0].plan.faces)[0] * winding(modes[1].plan.faces)[0] < 0
    assert modes[0].sides[0] == -modes[1].sides[0] != 0
    assert modes[1].plan.cost == pytest.approx(plan.cost, rel=0.01)  # the knife edge
    assert 0.4 < np.mean(labels == 1) < 0.6
    # mode 0: its plan's law and its two spread references; mode 1, born now: its plan's law
    np.testing.assert_array_equal(laws.group, [0, 0, 0, 1])
    assert laws.laws[0] is plan.law and laws.laws[3] is modes[1].plan.law
    u = particle_controls(plan, ps.particles, goal, setup, rng, sides=laws)
    east = np.sign(modes[0].plan.means[25, 0])  # mode 0's side (+1: east)
    # each side's particles are pushed toward its own side of the box
    assert np.mean(np.sign(u[labels == 0, 0]) == east) > 0.9
    assert np.mean(np.sign(u[labels == 1, 0]) == -east) > 0.9

    # a tick later: resampled (labels follow their particles) and predicted, the sides are kept
    weighted = tracking.ParticleSet(ps.particles, ps.log_weights - np.log(np.exp(ps.log_weights).sum()), labels)
    skew = weighted.log_weights + np.where(ps.particles[:, 0] > 0, 0.0, -3.0)
    post = tracking.resample_if_needed(dc_replace(weighted, log_weights=skew - tracking.logsumexp(skew)), 0.99, rng)
    assert post.labels is not None and len(post.labels) == len(post)
    nxt = tracking.predict(post, setup.model, u[0], rng)
    m2, c2 = tracking.estimate(nxt)
    plan2 = plan_guidance(model, setup.guidance, setup.obstacles, m2, goal, previous=plan,
                          ask=PlanAsk(Feedback.ALWAYS), solver=Solver(ws))
    laws2, modes2 = side_modes(setup, TargetTick(nxt, m2, c2, goal, plan2, plan,
                                                 replanner(setup, goal, ws, lambda: 0.0)), modes, rng)
    assert len(modes2) == 2
    np.testing.assert_array_equal(laws2.labels, nxt.labels)
    np.testing.assert_array_equal(laws2.group, [0, 0, 0, 1, 1, 1])
    for i in range(2):
        assert modes2[i].sides[0] == modes[i].sides[0]
        assert winding(modes2[i].plan.faces)[0] * modes[i].sides[0] > 0
        sel = nxt.labels == i
        centre = nxt.weights[sel] @ nxt.particles[sel] / nxt.weights[sel].sum()
        np.testing.assert_allclose(modes2[i].plan.law.x_ref, centre[[0, 1, 3, 4]], atol=1e-6)


def test_a_plan_shifted_by_a_tick_steers_as_the_plan_made_there(paper, model):
    """Plan.shifted (the side-aware tracker's reuse of last tick's plans): the plan one tick on,
    from the state it predicted, with its second control as the law's reference and that
    control's gain (``ahead``), which is the law of the plan P1 makes from there while the active
    set holds (the principle of optimality); two shifts use both ``ahead`` laws, a third has none."""
    from onboard.core.guidance.predictor import GuidanceWorkspace
    params = GuidanceParams.from_config(paper.guidance)
    obs = Obstacles.from_boxes(paper.obstacles)
    ws = GuidanceWorkspace()
    exact = 0
    for target in paper.targets:
        goal = np.array(paper.goal_of(target).center_m)
        x, plan = np.array(target.mean, float), None
        for _ in range(12):  # every target is rounding an obstacle or cruising at its speed limit
            plan = plan_guidance(model, params, obs, x, goal, previous=plan, solver=Solver(ws))
            x = plan.means[0]
        p = plan_guidance(model, params, obs, x, goal, previous=plan, ask=PlanAsk(Feedback.ALWAYS, ahead=2),
                          solver=Solver(ws))
        assert not p.unconstrained and len(p.ahead) == 2
        s = p.shifted()
        assert s.status == "shifted" and s.feasible and s.law is p.ahead[0] and s.ahead == p.ahead[1:]
        np.testing.assert_array_equal(s.law.u_ref, p.controls[1])
        np.testing.assert_array_equal(s.law.x_ref, p.means[0][[0, 1, 3, 4]])
        np.testing.assert_array_equal(s.faces[:-1], p.faces[1:])
        fresh = plan_guidance(model, params, obs, p.means[0], goal, previous=p, ask=PlanAsk(Feedback.ALWAYS),
                              solver=Solver(ws))
        start = np.zeros(6)
        start[[0, 1, 3, 4]] = fresh.law.x_ref
        u = s.law.controls(start[None])[0]
        assert np.linalg.norm(u - fresh.next_control) <= 0.02 * np.linalg.norm(fresh.next_control)
        exact += np.linalg.norm(s.law.gain - fresh.law.gain) <= 1e-6 * np.linalg.norm(fresh.law.gain)
        twice = s.shifted()
        assert twice.law is p.ahead[1] and twice.shifted().law is None
    assert exact >= 2  # where the plan keeps its active set one tick on, the gain is exact


def test_the_side_aware_tick_is_deterministic_and_within_its_budget(paper, monkeypatch):
    """plan_sides: the steering's plans are held to a count of QP solves per tick, never wall
    time: the same inputs give the same estimates whatever the clock says, and the tracker's own
    plans (modes, births, references) spend at most the tick's budget and a bounded overshoot."""
    import time
    from dataclasses import replace as dc_replace
    from onboard.core import monitor
    from onboard.core.tracking import steering
    from onboard.core.guidance.predictor import GuidanceWorkspace
    from onboard.core.monitor import MonitorSetup, Scan, initial_state, particle_steering, tick
    sc = dc_replace(paper, tracking=dc_replace(paper.tracking, plan_steering=True, plan_sides=True))
    setup = MonitorSetup.from_scenario(sc)
    spent: list[int] = []
    plan = monitor.plan_guidance

    def counting(*a, **k):
        p = plan(*a, **k)
        if k["ask"].feedback is Feedback.ALWAYS:  # the steering's own plans (replanner)
            spent[-1] += p.qp_solves + (steering.LAW_COST if p.law is not None else 0)
        return p
    monkeypatch.setattr(monitor, "plan_guidance", counting)

    def run(timer):
        rng = np.random.default_rng(3)
        state, ws, out = initial_state(setup, rng), GuidanceWorkspace(), []
        uav = np.array([300.0, 300.0, setup.grid.altitude_m])
        truth = setup.initial_means.copy()
        for _ in range(8):
            spent.append(0)
            bearings = tuple(np.array([np.arctan2(truth[j, 0] - uav[0], truth[j, 1] - uav[1]) + rng.normal(0, 0.017)])
                             for j in range(setup.n_targets))
            state, res = tick(setup, state, [Scan(uav, bearings)], rng, workspace=ws, timer=timer)
            shares = [b for b in particle_steering(setup).budgets(res.plans) if b is not None]
            # each target's steering stops when its share is spent; one plan (a search that gave up
            # the margin once) can overshoot it by its own cap, and each mode whose plan cannot be
            # shifted again is re-planned with its own cap past the budget
            over = (1 + steering.MAX_SIDE_MODES) * (max(steering.MODE_QPS, steering.BIRTH_QPS) + steering.LAW_COST)
            assert spent[-1] <= sum(shares) + len(shares) * over
            out.append(res.means)
            truth = np.array([p.means[0] for p in res.plans])
        return np.stack(out)

    clock = iter(np.cumsum(np.random.default_rng(0).uniform(0, 10, 100000)))
    a, b = run(time.perf_counter), run(lambda: float(next(clock)))
    np.testing.assert_array_equal(a, b)


def test_a_target_at_a_corner_keeps_rounding_it_when_its_shifted_plan_is_a_step_early(paper, model):
    """Trial 65 of seed 2024, T4 at t = 24 s (docs/GUIDANCE.md, "Cost jumps near corners"), as plain
    arrays: 5 m north of O3's margin, 13 m west of its north-east corner, closing at 7.6 m/s. No
    plan keeps the margin; without it, last tick's assignment shifted rounds the corner a step too
    early (infeasible) and the re-pick repeats it, so the search used to end on a plan holding
    back in front of O3 (winding 0, cost 2.23e6). Its switch moved a step later rounds O3 east as
    before, at a third of that cost."""
    params = GuidanceParams.from_config(paper.guidance)
    obs = Obstacles.from_boxes(paper.obstacles)
    goal = np.array([550.0, 150.0, 0.0])
    x = np.array([692.40, 364.74, 0.0, 1.03, -7.61, 0.0])
    T = params.horizon
    faces = np.zeros((T - 1, 4), dtype=int)  # east 0, north 1, west 2, south 3
    faces[:, 0] = [0] * 9 + [3] * 40  # O1, O2 passed; O3 north, east, south; O4 passed
    faces[:, 1] = 3
    faces[:, 2] = [1] * 2 + [0] * 6 + [3] * 41
    faces[:, 3] = [0] * 18 + [3] * 31
    means = np.zeros((T, 6))
    means[:, :2] = x[:2] + np.linspace(0.0, 1.0, T)[:, None] * (goal[:2] - x[:2])
    previous = Plan("optimal", 8.449e5, 0.0, 80, np.zeros((T, 3)), means, faces)
    plan = plan_guidance(model, params, obs, x, goal, previous=previous)
    assert plan.feasible and plan.margin_m == 0.0
    assert winding(plan.faces)[2] < 0  # it rounds O3 clockwise (east), as last tick's plan did
    assert plan.cost < 1.0e6


def test_a_warm_plan_holding_back_at_no_lower_cost_is_explored_past(paper, model):
    """Trial 65 of seed 2024, T4 at t = 25 s, as plain arrays: last tick's plan held it back in front
    of O3 (every obstacle on one face, winding 0, cost 2.23e6). Shifted, it is feasible and pressed
    against O3's north face, and costs more than it did (2.30e6): the search used to accept it
    (1 QP) for 15 s while rounding O3 cost about a third. It explores, and rounds O3."""
    params = GuidanceParams.from_config(paper.guidance)
    obs = Obstacles.from_boxes(paper.obstacles)
    goal = np.array([550.0, 150.0, 0.0])
    x = np.array([690.65, 369.23, 0.0, -4.44, -1.71, 0.0])
    T = params.horizon
    faces = np.tile([0, 3, 1, 0], (T - 1, 1))  # O1 east, O2 south, O3 north, O4 east: held back
    means = np.tile(x, (T, 1))
    previous = Plan("optimal", 2.227e6, 0.0, 55, np.zeros((T, 3)), means, faces)
    plan = plan_guidance(model, params, obs, x, goal, previous=previous)
    assert plan.feasible and plan.margin_m == params.obstacle_margin_m
    assert winding(plan.faces)[2] != 0  # it rounds O3
    assert plan.cost < 1.0e6
