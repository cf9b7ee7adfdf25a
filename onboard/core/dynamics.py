"""Target motion model: eqs. (1), (2) and (6) of the paper.

State x = [px, py, pz, vx, vy, vz] (m, m/s); control u = [ux, uy, uz] (N).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

PLANAR = np.array([0, 1, 3, 4])  # indices of [px, py, vx, vy] in the 6-D state


@dataclass(frozen=True, eq=False)
class MotionModel:
    """x_t = A x_(t-1) + B u_(t-1) + nu,  nu ~ N(0, Q)."""

    A: np.ndarray  # (6, 6)
    B: np.ndarray  # (6, 3), N -> state increment
    Q: np.ndarray  # (6, 6), m^2 and (m/s)^2
    dt_s: float
    friction: float
    mass_kg: float

    @classmethod
    def create(cls, dt_s: float, friction: float, mass_kg: float, process_noise_diag) -> "MotionModel":
        eye, zero = np.eye(3), np.zeros((3, 3))
        A = np.block([[eye, dt_s * eye], [zero, (1.0 - friction) * eye]])
        B = np.vstack([zero, (dt_s / mass_kg) * eye])
        Q = np.diag(np.asarray(process_noise_diag, dtype=float))
        for m in (A, B, Q):
            m.setflags(write=False)
        return cls(A, B, Q, dt_s, friction, mass_kg)

    @property
    def Q_sqrt(self) -> np.ndarray:
        """A square root of Q (diagonal here, so elementwise) for sampling."""
        return np.sqrt(np.clip(np.diag(self.Q), 0.0, None))


def velocity_rollout(v0: np.ndarray, controls: np.ndarray, decay: float, gain: float) -> np.ndarray:
    """v_1..v_T (T, d) of v_(k+1) = decay v_k + gain u_k from v_0 (d,), controls (T, d).

    A first-order recursion: one ``lfilter`` call instead of a Python loop over the horizon.
    """
    u = np.asarray(controls, dtype=float)
    v0 = np.asarray(v0, dtype=float)
    return lfilter([gain], [1.0, -decay], u, axis=0, zi=(decay * v0)[None, :])[0]


def predict_mean(model: MotionModel, mean: np.ndarray, controls: np.ndarray) -> np.ndarray:
    """Predicted means mu_(t+tau+1|t), tau = 0..T-1, for controls (T, 3): returns (T, 6)."""
    controls = np.asarray(controls, dtype=float).reshape(-1, 3)
    x = np.asarray(mean, dtype=float)
    v = velocity_rollout(x[3:], controls, 1.0 - model.friction, model.dt_s / model.mass_kg)
    p = x[:3] + model.dt_s * np.cumsum(np.vstack([x[3:], v[:-1]]), axis=0)
    return np.hstack([p, v])


def predict_cov(model: MotionModel, cov: np.ndarray, steps: int) -> np.ndarray:
    """Predicted covariances Sigma_(t+tau+1|t), tau = 0..steps-1: returns (steps, 6, 6).

    They do not depend on the controls, so the guidance can compute them once per tick.
    """
    out = np.empty((steps, 6, 6))
    P = np.asarray(cov, dtype=float)
    for k in range(steps):
        P = model.A @ P @ model.A.T + model.Q
        out[k] = P
    return out
