"""The search for the clairvoyant ceiling's path (``sim.evaluation.ceiling``: the problem, the bound and
its gradient, the vehicle and the rules).

``search``: multi-start local search. Starts: the vehicle chasing, at full speed and round the
obstacles, the targets' centroid now and ahead, each target, their final centroid, circles round
the centroid, and any given paths (the flight default's flown path, tracked). From each, SQP
(SLSQP) on the accelerations held for three ticks, the speed and acceleration limits as exact
constraints and the area and obstacles as a quadratic penalty; the best few are refined with one
acceleration per tick. The SQPs of the starts run in threads whose objective evaluations are
batched (one vectorised call of the adjoint for all starts: the cost is per call, not per path).

``cross_entropy``: an independent, gradient-free search (the cross-entropy method on
accelerations held for a few ticks, from the vehicle at rest), to show how near the search's
minimum is to the global one.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from onboard.core.obstacles import polygons_crossed
from onboard.core.planning.routes import route_polylines
from sim.evaluation.ceiling import (CeilingProblem, clearance, kinematics, bound_m2, check_path, fly, objective_gradient,
                         penalty_gradient, window_bound)


def pursuit(pb: CeilingProblem, refs: np.ndarray, clearance_m: float = 20.0) -> np.ndarray:
    """Accelerations (B, K-1, 2) of the vehicle chasing a moving point refs (B, K, 2) at full
    speed (its velocity turned toward the point at a_max, slowing to arrive), around the
    blocking obstacles: while the straight line to the point crosses one, it chases the next
    corner of the shortest way round (``route_polylines``, corners pushed out by clearance_m)."""
    Bn = refs.shape[0]
    p = np.broadcast_to(pb.start, (Bn, 2)).copy()
    v = np.zeros((Bn, 2))
    acc = np.empty((Bn, pb.K - 1, 2))
    for k in range(pb.K - 1):
        aim = refs[:, k + 1].copy()
        if len(pb.offsets):
            blocked = polygons_crossed(pb.normals, pb.offsets + clearance_m / 2, p, aim) if Bn else []
            for b in np.flatnonzero(blocked):
                poly = route_polylines(p[b], aim[b][None], pb.normals, pb.offsets, clearance_m)[0]
                if poly is not None and len(poly) > 2:
                    aim[b] = poly[1]
        to = aim - p
        dist = np.linalg.norm(to, axis=1, keepdims=True)
        v_des = to / np.maximum(dist, 1e-9) * np.minimum(pb.speed_max, np.sqrt(2 * pb.accel_max * dist))
        dv = v_des - v
        n = np.linalg.norm(dv, axis=1, keepdims=True)
        dv *= np.minimum(1.0, pb.accel_max * pb.dt / np.maximum(n, 1e-12))
        vn = v + dv
        vn *= np.minimum(1.0, pb.speed_max / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12))
        acc[:, k] = (vn - v) / pb.dt
        p = p + 0.5 * (v + vn) * pb.dt
        v = vn
    return acc


def starts(pb: CeilingProblem, radii_m: tuple[float, ...] = (30.0, 80.0),
           leads: tuple[int, ...] = (0, 15, 40)) -> tuple[np.ndarray, list[str]]:
    """Initial accelerations (B, K-1, 2) and their names: pursuits of the targets' centroid
    (now and ``leads`` ticks ahead: heading for where they will be), of each target, of the
    targets' final centroid, and of circles (both ways) of each radius round the centroid 15
    ticks ahead."""
    K = pb.K
    cen = pb.targets.mean(axis=1)  # (K, 2)
    idx = np.arange(K)
    refs, names = [], []
    for lead in leads:
        refs.append(cen[np.minimum(idx + lead, K - 1)])
        names.append(f"centroid+{lead}")
    for j in range(pb.targets.shape[1]):
        refs.append(pb.targets[:, j])
        names.append(f"target{j + 1}")
    refs.append(np.broadcast_to(cen[-1], (K, 2)))
    names.append("final centroid")
    for r in radii_m:
        w = pb.speed_max / r * pb.dt
        for side in (1.0, -1.0):
            refs.append(cen[np.minimum(idx + 15, K - 1)] + r * np.column_stack([np.cos(side * w * idx),
                                                                                   np.sin(side * w * idx)]))
            names.append(f"circle {r:g} m {'ccw' if side > 0 else 'cw'}")
    return pursuit(pb, np.array(refs)), names


def track(pb: CeilingProblem, path: np.ndarray) -> np.ndarray:
    """Accelerations (K-1, 2) of the vehicle following a given path (K, 2) (e.g. the flight
    default's flown one) as closely as its limits allow: each tick it asks for the velocity that
    ends the tick on the path's next point, clipped to a_max dt and v_max."""
    p, v = pb.start.copy(), np.zeros(2)
    acc = np.empty((pb.K - 1, 2))
    for k in range(pb.K - 1):
        dv = 2.0 * (path[k + 1] - p) / pb.dt - 2.0 * v
        dv *= min(1.0, pb.accel_max * pb.dt / max(float(np.linalg.norm(dv)), 1e-12))
        vn = v + dv
        vn *= min(1.0, pb.speed_max / max(float(np.linalg.norm(vn)), 1e-12))
        acc[k] = (vn - v) / pb.dt
        p, v = p + 0.5 * (v + vn) * pb.dt, vn
    return acc


# --------------------------------------------------------------------------- search


@dataclass(frozen=True, eq=False)
class Solutions:
    """A batch of searched paths, each flown through ``fly`` and checked."""

    acc: np.ndarray  # (B, K-1, 2) flown accelerations
    paths: np.ndarray  # (B, K, 2)
    bound_m2: np.ndarray  # (B, K, M)
    value: np.ndarray  # (B,) window_bound; inf where the check failed
    ok: np.ndarray  # (B,) check_path
    evaluations: int = 0  # batched objective evaluations of the search

    @property
    def best(self) -> int:
        return int(np.argmin(self.value))


def evaluate(pb: CeilingProblem, acc: np.ndarray, evaluations: int = 0) -> Solutions:
    """Fly acc, check the paths, and score them (inf where the check fails)."""
    paths, flown = fly(pb, acc)
    ok = check_path(pb, paths, flown)
    b = bound_m2(pb, paths)
    return Solutions(flown, paths, b, np.where(ok, window_bound(pb, b), np.inf), ok, evaluations)


def _violation(pb: CeilingProblem, paths_sub: np.ndarray) -> np.ndarray:
    """(B,) summed depth (m) of the sampled points outside the area or inside an obstacle."""
    v = np.sum(np.maximum(pb.area_lo - paths_sub, 0) + np.maximum(paths_sub - pb.area_hi, 0), axis=(1, 2))
    if len(pb.offsets):
        c, _ = clearance(pb, paths_sub)
        v += np.sum(np.maximum(-c, 0.0), axis=(1, 2))
    return v


def block_accelerations(z: np.ndarray, K: int, block: int) -> np.ndarray:
    """z (B, nb, 2) held for ``block`` ticks each -> (B, K-1, 2)."""
    return np.repeat(z, block, axis=1)[:, :K - 1]


@dataclass(frozen=True)
class CrossEntropyOptions:
    """The cross-entropy method's tuning (``cross_entropy``): accelerations held for ``block``
    ticks; ``population`` samples an iteration, the best ``elite`` of them kept; ``sigma``: the
    initial spread (a_max); ``smoothing``: the weight of the new elite's mean and spread;
    ``violation_cost``: per metre of depth outside the area or inside an obstacle."""

    block: int = 5
    population: int = 128
    elite: int = 12
    iterations: int = 40
    sigma: float = 1.0
    smoothing: float = 0.7
    violation_cost: float = 10.0


def cross_entropy(pb: CeilingProblem, rng: np.random.Generator,
                  options: CrossEntropyOptions = CrossEntropyOptions(),
                  mean: np.ndarray | None = None) -> Solutions:
    """An independent, gradient-free search: the cross-entropy method on accelerations held for
    ``block`` ticks (Gaussian over the blocks, the elite's mean and spread each iteration,
    smoothed), flown through ``fly`` (so always within the limits); leaving the area or
    entering an obstacle costs violation_cost per metre of depth summed over the sampled points.
    mean: (nb, 2) initial mean in units of a_max (default 0, the vehicle at rest). Returns the
    best checked path seen (and the final mean's)."""
    o = options
    block, population, elite, smoothing = o.block, o.population, o.elite, o.smoothing
    kin = kinematics(pb.K, pb.dt)
    nb = -(-(pb.K - 1) // block)
    mu = np.zeros((nb, 2)) if mean is None else np.asarray(mean, float).copy()
    sd = np.full((nb, 2), float(o.sigma))
    best_val, best_acc = np.inf, None
    for _ in range(o.iterations):
        z = mu + sd * rng.normal(size=(population, nb, 2))
        z[0] = mu
        acc = block_accelerations(z * pb.accel_max, pb.K, block)
        paths, flown = fly(pb, acc)
        val = window_bound(pb, bound_m2(pb, paths))
        cost = val + o.violation_cost * _violation(pb, pb.start + kin.Ls @ flown)
        order = np.argsort(cost)
        ok = check_path(pb, paths[order[:4]], flown[order[:4]])
        for i, good in zip(order[:4], ok):
            if good and val[i] < best_val:
                best_val, best_acc = val[i], flown[i]
        el = z[order[:elite]]
        mu = smoothing * el.mean(axis=0) + (1 - smoothing) * mu
        sd = smoothing * el.std(axis=0) + (1 - smoothing) * sd
    if best_acc is None:
        best_acc = block_accelerations(mu[None] * pb.accel_max, pb.K, block)[0]
    return evaluate(pb, best_acc[None], o.iterations)


def block_matrix(K: int, block: int) -> np.ndarray:
    """(K-1, nb): accelerations held for ``block`` ticks from nb block values."""
    nb = -(-(K - 1) // block)
    E = np.zeros((K - 1, nb))
    E[np.arange(K - 1), np.arange(K - 1) // block] = 1.0
    return E


class _Batcher:
    """Runs one batched evaluation for the requests of several optimiser threads: each thread
    asks and waits; when every live thread is waiting, the last to ask evaluates them all."""

    def __init__(self, evaluate_batch, n: int):
        import threading

        self.cv = threading.Condition()
        self.live, self.pending, self.results = n, {}, {}
        self.evaluate_batch = evaluate_batch
        self.calls = 0

    def request(self, i: int, x: np.ndarray):
        with self.cv:
            self.pending[i] = x
            self._run_if_all_waiting()
            while i not in self.results:
                self.cv.wait()
            return self.results.pop(i)

    def finished(self) -> None:
        with self.cv:
            self.live -= 1
            self._run_if_all_waiting()

    def _run_if_all_waiting(self) -> None:
        if self.pending and len(self.pending) == self.live:
            idx = list(self.pending)
            out = self.evaluate_batch(np.stack([self.pending[i] for i in idx]))
            self.pending.clear()
            self.calls += 1
            for n, i in enumerate(idx):
                self.results[i] = (out[0][n], out[1][n])
            self.cv.notify_all()


def sqp(pb: CeilingProblem, acc0: np.ndarray, block: int = 1, maxiter: int = 300, penalty: float = 1.0,
        buffer_m: float = 1.0, weights: np.ndarray | None = None, ftol: float = 1e-9) -> tuple[np.ndarray, np.ndarray, int]:
    """Local optima from each start acc0 (B, K-1, 2) by SLSQP on the accelerations held for
    ``block`` ticks: the speed and acceleration limits as exact constraints (|a| <= a_max per
    block, |v| <= v_max at the block ends, so at every instant: v is linear in a block), the area
    and obstacles as a quadratic penalty (``penalty`` per m^2 at the sub-steps, buffer_m inside
    the rules). One SLSQP per start, in threads whose objective evaluations are batched
    (``_Batcher``). Returns the accelerations (B, K-1, 2), each start's iterations (B,) and the
    batched evaluations; ``evaluate`` flies and checks them."""
    import threading

    kin = kinematics(pb.K, pb.dt)
    E = block_matrix(pb.K, block)
    nb = E.shape[1]
    ends = np.minimum(np.arange(1, nb + 1) * block, pb.K - 1)  # the ticks that end a block
    Lp, Lv = kin.Lp @ E, (kin.Lv @ E)[ends]
    am, vm = pb.accel_max, pb.speed_max
    acc0 = np.asarray(acc0, float)
    z0 = np.linalg.lstsq(E, acc0.transpose(1, 0, 2).reshape(pb.K - 1, -1), rcond=None)[0]
    z0 = z0.reshape(nb, len(acc0), 2).transpose(1, 0, 2) / am
    z0 /= np.maximum(1.0, np.linalg.norm(z0, axis=2, keepdims=True))

    def batch(x):  # (n, 2 nb) -> values (n,), gradients (n, 2 nb)
        a = x.reshape(len(x), nb, 2) * am
        f, gp = objective_gradient(pb, pb.start + Lp @ a, weights)
        pen, ga = penalty_gradient(pb, kin, E @ a, buffer_m)
        grad = Lp.T @ gp + penalty * (E.T @ ga)
        return f + penalty * pen, (grad * am).reshape(len(x), -1)

    limits = _limit_constraints(Lv, nb, am / vm)
    batcher = _Batcher(batch, len(acc0))
    out, nits = z0.copy(), np.zeros(len(acc0), dtype=int)

    def run(i):
        memo: dict = {}

        def fg(x):
            key = x.tobytes()
            if key not in memo:
                memo.clear()
                memo[key] = batcher.request(i, x)
            return memo[key]
        try:
            res = minimize(lambda x: float(fg(x)[0]), z0[i].ravel(), jac=lambda x: fg(x)[1], method="SLSQP",
                           constraints=[limits],
                           options=dict(maxiter=maxiter, ftol=ftol))
            out[i], nits[i] = res.x.reshape(nb, 2), res.nit
        finally:
            batcher.finished()

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(acc0))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return E @ (out * am), nits, batcher.calls


def _limit_constraints(Lv: np.ndarray, nb: int, c: float) -> dict:
    """SLSQP's inequality on ``sqp``'s scaled accelerations z (nb, 2): |z| <= 1 per block and
    |v| <= 1 at the block ends (``Lv``: z to velocity, scaled by ``c`` = a_max / v_max)."""
    def cons(x):
        z = x.reshape(nb, 2)
        v = Lv @ z * c
        return np.concatenate([1.0 - np.sum(z * z, axis=1), 1.0 - np.sum(v * v, axis=1)])

    def cjac(x):
        z = x.reshape(nb, 2)
        J1 = np.zeros((nb, nb, 2))
        J1[np.arange(nb), np.arange(nb)] = -2.0 * z
        v = Lv @ z * c
        J2 = -2.0 * v[:, None, :] * (Lv * c)[:, :, None]
        return np.concatenate([J1.reshape(nb, 2 * nb), J2.reshape(len(Lv), 2 * nb)])
    return dict(type="ineq", fun=cons, jac=cjac)


@dataclass(frozen=True, eq=False)
class Ceiling:
    """The best checked path of a search, and what each start gave (window_bound, m; inf where
    the path failed the check)."""

    path: np.ndarray  # (K, 2)
    acc: np.ndarray  # (K-1, 2)
    bound_m2: np.ndarray  # (K, M)
    value: float
    names: tuple[str, ...]  # the starts
    start_values: np.ndarray  # (S,) the starts as they are
    local_values: np.ndarray  # (S,) after the coarse SQP from each
    refined: np.ndarray  # (R,) indices of the starts refined at full resolution
    refined_values: np.ndarray  # (R,)


QUICK_STARTS = ("centroid+0", "centroid+15", "centroid+40", "final centroid", "circle 80 m ccw", "circle 80 m cw")


def search(pb: CeilingProblem, extra: tuple[np.ndarray, list[str]] | None = None,
           only: tuple[str, ...] | None = QUICK_STARTS, coarse_block: int = 3, coarse_iter: int = 80,
           keep: int = 2, fine_iter: int = 150, weights: np.ndarray | None = None) -> Ceiling:
    """Multi-start local search: from every start (``starts``, those named in ``only`` or all
    when None, and ``extra`` accelerations with names), SQP on accelerations held for
    coarse_block ticks; the ``keep`` best are refined with one acceleration per tick. The best
    checked path of all (the starts included)."""
    acc, names = starts(pb)
    if only is not None:
        sel = [i for i, n in enumerate(names) if n in only]
        acc, names = acc[sel], [names[i] for i in sel]
    if extra is not None:
        acc, names = np.concatenate([acc, extra[0]]), names + list(extra[1])
    first = evaluate(pb, acc)
    coarse = evaluate(pb, sqp(pb, acc, block=coarse_block, maxiter=coarse_iter, weights=weights)[0])
    order = np.argsort(coarse.value)[:keep]
    fine = evaluate(pb, sqp(pb, coarse.acc[order], block=1, maxiter=fine_iter, weights=weights)[0])
    pool = [first, coarse, fine]
    b, i = min(((n, int(np.argmin(p.value))) for n, p in enumerate(pool)), key=lambda t: pool[t[0]].value[t[1]])
    best = pool[b]
    return Ceiling(best.paths[i], best.acc[i], best.bound_m2[i], float(best.value[i]), tuple(names),
                   first.value, coarse.value, order, fine.value)


def ceiling_path(setup, truth: np.ndarray, gains: np.ndarray, start: np.ndarray, window_start: int,
                 given: list[np.ndarray] = ()) -> np.ndarray:
    """The ceiling's path (K, 2) of one evaluation trial (the evaluation's bound-only method
    ``ceiling``): ``search`` (the quick starts) at ``setup.motion``'s speed and acceleration, with
    Lambda and p_D of ``setup.sensor``, and each path of ``given`` ((K, 2), e.g. the run's flown
    paths) as the vehicle tracks it (``track``) as an extra start."""
    from sim.evaluation.ceiling import problem_for_trial

    pb = problem_for_trial(setup, truth, gains, start, window_start, setup.motion.speed_max_mps,
                           setup.motion.accel_max_mps2, setup.sensor.clutter_rate)
    extra = None
    if len(given):
        extra = (np.stack([track(pb, np.asarray(g, float)[:, :2]) for g in given]), [f"given {i}" for i in range(len(given))])
    return search(pb, extra).path
