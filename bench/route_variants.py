"""How the route planner scores and refines its routes: two experiments (not the flight path).

    python -m bench.route_variants --out DIR [--refine ITERATIONS] [--block TICKS] [--per-target trace|sqrt]
                                [--trials 100] [--seed 2024] [--methods flight@stock] [--workers 2]
                                [--set KEY=VALUE ...]

``pmon eval paper`` on the same trials (same truths, starts and DF draws) with the lookahead
planner changed in one of two ways (docs/LOG.md, "the best route refined by optimisation"):

- ``--refine N``: after the planner has chosen its best route, the route's accelerations (one per
  ``--block`` ticks over the horizon) are improved by N iterations of SLSQP on the planner's own
  score (the sum over the horizon and the targets of tr P_pos, EKF form, from the particles'
  covariance, against the targets' predicted plans), |a| <= a_max and |v| <= v_max as
  constraints, the area (1 m in) and the blocking obstacles (6 m clear) as a quadratic penalty;
  the first tick of the refined plan is flown (through the jerk-limited ``UavMotion.step``) when
  its score is lower than the route's and that step and its braking path are admissible. The
  gradient is the adjoint of the score's recursion with the bearing's regularising tr P_pos held
  fixed: exact at the horizon's last tick, elsewhere close to central differences in direction
  (tests/core/test_planning.py holds the cosine above 0.999, the largest error under 5 % of the
  largest component). Per tick (``refine_ticks.txt`` in --out): wall ms of the refinement, SLSQP
  iterations, the route's and the refined score.
- ``--per-target sqrt``: each route scored by the sum over the horizon and the targets of
  sqrt(tr P_pos) instead of tr P_pos: the targets weighed by 1 / their spread, as the evaluation's
  target-averaged RMSE weighs them, instead of the worst tracked one weighing most.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
from scipy.optimize import minimize

from onboard.core.planning import planners as _planners
from onboard.core.planning import next_position as _planning
from onboard.core.planning.information import bearing_update_components, predict_planar_components
from onboard.core.planning.information import PLANAR, planar_model
from onboard.core.planning.next_position import Moves, _first_step
from onboard.core.planning.routes import blocking_2d
from onboard.core.tracking.filter import logsumexp
from sim.evaluation.ceiling import clearance, kinematics
from sim.evaluation.route_score import score

# environment: the spawned workers import this module and read their settings from it
ITER, BLOCK, LOG, PER_TARGET = "PMON_REFINE_ITERATIONS", "PMON_REFINE_BLOCK", "PMON_REFINE_LOG", "PMON_PER_TARGET"
_plan = _planners.LookaheadPlanner.plan


def _route_accelerations(p0, v0, pos, dt, amax):
    """Accelerations (H, 2), constant through each tick, that fly p0, v0 through pos (H, 2)."""
    a = np.empty_like(pos)
    p, v = p0.copy(), v0.copy()
    for k in range(len(pos)):
        ak = 2.0 * (pos[k] - p - v * dt) / dt ** 2
        n = np.linalg.norm(ak)
        ak *= min(1.0, amax / max(n, 1e-12))
        a[k] = ak
        p, v = p + v * dt + 0.5 * ak * dt ** 2, v + ak * dt
    return a


def refine(self, inputs, res):
    """The refined next position and velocity, or None (the route's stays)."""
    if res.index is None or res.paths is None or self.motion.kind != "vehicle":
        return None
    t0 = time.perf_counter()
    iters, block = int(os.environ.get(ITER, "0")), int(os.environ.get(BLOCK, "3"))
    if iters <= 0:
        return None
    m = self.motion
    dt, amax, vmax = self.model.dt_s, m.accel_max_mps2, m.speed_max_mps
    p0 = np.asarray(inputs.position, float)[:2]
    v0 = np.asarray(inputs.velocity, float)[:2]
    a_cur = np.zeros(2) if inputs.acceleration is None else np.asarray(inputs.acceleration, float)[:2]
    targets, P0 = _belief(inputs, self.steps)
    H = len(targets)
    A, _, Q = planar_model(self.model)
    c_meas = self.sigma_rad ** 2 / max(self.reduction, 1e-12)
    kin = kinematics(H + 1, dt)
    E, nb = _blocks(H, block)
    tk = dt * np.arange(1, H + 1)
    Lp, Lv = kin.Lp[1:], kin.Lv[1:]
    sub_t, Ls = _sample_times(kin, H, dt), kin.Ls
    lo, hi = np.asarray(self.area.minimum, float)[:2], np.asarray(self.area.maximum, float)[:2]
    normals, offsets = blocking_2d(self.area.obstacles, self.grid.altitude_m)
    route = res.paths[res.index][:H, :2]

    def positions(a):
        return p0 + v0 * tk[:, None] + Lp @ a

    def fg(z):
        a = E @ z.reshape(nb, 2) * amax
        f, gp = score(P0, A, Q, targets, positions(a), c_meas, grad=True)
        pen, gpts = _keep_out(p0 + v0 * sub_t[:, None] + Ls @ a, lo, hi, normals, offsets)
        ga = Lp.T @ gp + 100.0 * (Ls.T @ gpts)
        return f + 100.0 * pen, (E.T @ ga * amax).ravel()

    a_route = _route_accelerations(p0, v0, route, dt, amax)
    f_route = score(P0, A, Q, targets, positions(a_route), c_meas)
    z0 = np.linalg.lstsq(E, a_route, rcond=None)[0] / amax
    z0 /= np.maximum(1.0, np.linalg.norm(z0, axis=1, keepdims=True))
    c = amax / vmax

    def cons(z):
        zz = z.reshape(nb, 2)
        v = v0 / vmax + Lv @ (E @ zz) * c
        return np.concatenate([1.0 - np.sum(zz * zz, axis=1), 1.0 - np.sum(v * v, axis=1)])

    out = _slsqp(fg, cons, z0, iters)
    a_ref = E @ out.x.reshape(nb, 2) * amax
    a_ref *= np.minimum(1.0, amax / np.maximum(np.linalg.norm(a_ref, axis=1, keepdims=True), 1e-12))
    f_ref = score(P0, A, Q, targets, positions(a_ref), c_meas)
    _log(t0, out.nit, f_route, f_ref)
    if not f_ref < f_route * (1 - 1e-4):
        return None
    p1, v1 = _first_move(m, p0, v0, a_cur, a_ref, dt)
    ok = _first_step(p1[:, None].copy(), v1[:, None].copy(), p0, Moves(self.grid, self.area, m), dt)
    if not ok[0]:
        return None
    return p1[0], v1[0]


def _blocks(H: int, block: int):
    """(H, nb) ones mapping each of the nb blocks of ``block`` steps to its steps: one acceleration per block."""
    nb = -(-H // block)
    E = np.zeros((H, nb))
    E[np.arange(H), np.arange(H) // block] = 1.0
    return E, nb


def _sample_times(kin, H: int, dt: float):
    """The times of the kinematics' sub-step samples (``kin.Ls``'s rows)."""
    return np.r_[np.repeat(np.arange(H), len(kin.Ls) // H) * dt
                 + np.tile(np.arange(len(kin.Ls) // H) / (len(kin.Ls) // H) * dt, H), H * dt][:len(kin.Ls)]


def _log(t0: float, nit: int, f_route: float, f_ref: float) -> None:
    """One line per refinement (ms, iterations, the route's and the refined score) to $LOG, if set."""
    if os.environ.get(LOG):
        with open(os.environ[LOG], "a") as fh:
            fh.write(f"{1e3 * (time.perf_counter() - t0):.2f} {nit} {f_route:.6g} {f_ref:.6g}\n")


def _belief(inputs, steps: int):
    """The targets' predicted planar means over the horizon (H, M, 2) and each target's planar
    particle covariance now (M, 4, 4)."""
    targets = np.stack([p.means[:steps, :2] for p in inputs.plans], axis=1)
    lw = inputs.log_weights
    w = np.exp(lw - logsumexp(lw, axis=1, keepdims=True))
    x = inputs.particles[:, :, PLANAR]
    mean = np.einsum("mn,mnd->md", w, x)
    dev = x - mean[:, None]
    return targets, np.einsum("mn,mni,mnj->mij", w, dev, dev)


def _keep_out(pts, lo, hi, normals, offsets):
    """The squared excursion of the sampled route past the area's edges (1 m inside) and into the
    obstacles (6 m clear), and its gradient per point."""
    buf = 1.0
    lo_ex = np.maximum(lo + buf - pts, 0.0)
    hi_ex = np.maximum(pts - hi + buf, 0.0)
    pen = np.sum(lo_ex ** 2 + hi_ex ** 2)
    gpts = -2 * lo_ex + 2 * hi_ex
    if len(offsets):
        cl, face = clearance(SimpleNamespace(normals=normals, offsets=offsets), pts)
        ex = np.maximum(buf + 5.0 - cl, 0.0)
        pen += np.sum(ex ** 2)
        nrm = normals[np.arange(len(offsets))[None], face]
        gpts += np.sum(-2 * ex[..., None] * nrm, axis=1)
    return pen, gpts


def _slsqp(fg, cons, z0, iters: int):
    """SLSQP on ``fg`` (value and gradient, evaluated once per point) under ``cons`` >= 0."""
    memo = {}

    def cached(z):
        k = z.tobytes()
        if k not in memo:
            memo.clear()
            memo[k] = fg(z)
        return memo[k]
    return minimize(lambda z: float(cached(z)[0]), z0.ravel(), jac=lambda z: cached(z)[1], method="SLSQP",
                    constraints=[dict(type="ineq", fun=cons)], options=dict(maxiter=iters, ftol=1e-9))


def _first_move(m, p0, v0, a_cur, a_ref, dt: float):
    """The vehicle's position and velocity after the refined plan's first step: the motion's own
    jerk-limited step, or the acceleration held with the speed capped."""
    if m.jerk_max_mps3 > 0.0:
        p1, v1, _ = m.step(p0[None], v0[None], a_cur[None], a_ref[:1], dt)
        return p1, v1
    vmax = m.speed_max_mps
    v1 = v0[None] + a_ref[:1] * dt
    v1 *= min(1.0, vmax / max(float(np.linalg.norm(v1)), 1e-12))
    return p0[None] + 0.5 * (v0[None] + v1) * dt, v1


def _refined_plan(self, inputs, rng):
    res = _plan(self, inputs, rng)
    new = refine(self, inputs, res)
    if new is None:
        return res
    p1, v1 = new
    cand, vel = res.candidates.copy(), res.velocities.copy()
    cand[res.index, :2] = p1
    vel[res.index] = v1
    return replace(res, candidates=cand, velocities=vel)


def _sqrt_route_traces(particles, log_weights, target_paths, pos, model, sigma_rad, reduction):
    """``planning._route_traces`` with sqrt(tr P_pos) summed instead of tr P_pos (the same recursion)."""
    w = np.exp(log_weights - logsumexp(log_weights, axis=1, keepdims=True))
    x = particles[:, :, PLANAR]
    mean = np.einsum("mn,mnd->md", w, x)
    dev = x - mean[:, None]
    P0 = np.einsum("mn,mni,mnj->ijm", w, dev, dev)
    C, H = pos.shape[:2]
    P = np.broadcast_to(P0[:, :, None], (4, 4, C, len(w))).copy()
    total = np.zeros(P.shape[2:])
    for i in range(H):
        if i:
            P = predict_planar_components(P, model)
        P = bearing_update_components(P, target_paths[None, :, i, :2], pos[:, None, i], sigma_rad, reduction)
        total += np.sqrt(P[0, 0] + P[1, 1])
    return total


# at import as the script (the evaluation's spawned workers import it as __mp_main__), not when
# a test imports its functions
if __name__ in ("__main__", "__mp_main__"):
    _planners.LookaheadPlanner.plan = _refined_plan
    if os.environ.get(PER_TARGET) == "sqrt":
        _planning._route_traces = _sqrt_route_traces


def main(argv=None) -> int:
    from bench import patched_eval_parser, run_patched_eval
    from onboard.argcheck import integer
    ap = patched_eval_parser(__doc__, "comma-separated; the lookahead ones are changed")
    ap.add_argument("--refine", type=integer(0, 1000), default=0, help="SLSQP iterations per tick (0: none)")
    ap.add_argument("--block", type=integer(1, 50), default=3, help="ticks each refined acceleration is held")
    ap.add_argument("--per-target", choices=("trace", "sqrt"), default="trace", help="each target's term per tick")
    a = ap.parse_args(argv)
    if a.refine == 0 and a.per_target == "trace":
        ap.error("nothing to change: give --refine N or --per-target sqrt")
    if a.refine and a.per_target == "sqrt":
        ap.error("--refine optimises the trace score: not with --per-target sqrt")
    os.environ[ITER], os.environ[BLOCK], os.environ[PER_TARGET] = str(a.refine), str(a.block), a.per_target
    if a.per_target == "sqrt":
        _planning._route_traces = _sqrt_route_traces
    log = os.path.join(a.out, "refine_ticks.txt")  # per tick: ms, SLSQP iterations, route and refined score
    if a.refine:
        os.makedirs(a.out, exist_ok=True)
        os.environ[LOG] = log
        open(log, "w").close()
    rc = run_patched_eval(a)
    if a.refine and os.path.getsize(log):
        d = np.loadtxt(log, ndmin=2)
        gain = 1.0 - d[:, 3] / d[:, 2]
        print(f"refinement: {len(d)} ticks, {np.median(d[:, 0]):.1f} ms median, {np.percentile(d[:, 0], 95):.1f} "
              f"ms p95, {np.median(d[:, 1]):.0f} SLSQP iterations median; the route's score lowered "
              f"{100 * np.median(gain):.1f} % median, by more than 0.01 % in {100 * np.mean(gain > 1e-4):.0f} % of "
              f"the ticks")
    return rc


if __name__ == "__main__":
    sys.exit(main())
