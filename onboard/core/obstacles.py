"""Cuboid obstacles as six half-spaces each (Sec. II-D).

A point p is inside obstacle n when a_i . p <= b_i for all six faces i, with a_i the outward
unit normals. Faces are stored in a fixed order: the four lateral faces counter-clockwise
(+x, +y, -x, -y of the box frame, rotated by its yaw), then top (+z) and bottom (-z), so that
lateral faces i and i +- 1 (mod 4) are adjacent, which the guidance relies on.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

N_LATERAL = 4


@dataclass(frozen=True, eq=False)
class Obstacles:
    normals: np.ndarray  # (K, 6, 3) outward unit normals
    offsets: np.ndarray  # (K, 6): inside when normals @ p <= offsets

    @classmethod
    def from_boxes(cls, boxes) -> "Obstacles":
        """From objects with ``center_m``, ``size_m`` and ``yaw_rad`` (see ``onboard.config.Box``)."""
        normals = np.zeros((len(boxes), 6, 3))
        offsets = np.zeros((len(boxes), 6))
        for k, box in enumerate(boxes):
            c = np.asarray(box.center_m, dtype=float)
            half = 0.5 * np.asarray(box.size_m, dtype=float)
            cy, sy = np.cos(box.yaw_rad), np.sin(box.yaw_rad)
            ex, ey = np.array([cy, sy, 0.0]), np.array([-sy, cy, 0.0])
            ez = np.array([0.0, 0.0, 1.0])
            faces = [(ex, half[0]), (ey, half[1]), (-ex, half[0]), (-ey, half[1]), (ez, half[2]), (-ez, half[2])]
            for i, (a, h) in enumerate(faces):
                normals[k, i] = a
                offsets[k, i] = a @ c + h
        return cls(normals, offsets)

    @classmethod
    def empty(cls) -> "Obstacles":
        return cls(np.zeros((0, 6, 3)), np.zeros((0, 6)))

    def __len__(self) -> int:
        return len(self.offsets)

    def inflate(self, margin_m: float) -> "Obstacles":
        """Every face pushed out by margin_m (a box with square corners, conservative)."""
        return Obstacles(self.normals, self.offsets + float(margin_m))

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance-like clearance a_i . p - b_i per face: (P, K, 6). > 0: outside that face."""
        p = np.atleast_2d(np.asarray(points, dtype=float))
        return np.einsum("kfd,pd->pkf", self.normals, p) - self.offsets[None]

    def contains(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """(P, K) bool: point p strictly inside obstacle k (deeper than tol behind every face)."""
        return np.all(self.clearance(points) < -tol, axis=-1)

    def containing(self, point: np.ndarray) -> int | None:
        """Index of the first obstacle containing the point, or None."""
        hit = np.flatnonzero(self.contains(point)[0])
        return int(hit[0]) if hit.size else None

    def segments_cross(self, p0: np.ndarray, p1: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """(S, K) bool: the straight segment p0[s] -> p1[s] passes through obstacle k's interior.

        Liang-Barsky clipping of the segment against the six half-spaces, vectorised.
        """
        p0 = np.atleast_2d(np.asarray(p0, dtype=float))
        p1 = np.atleast_2d(np.asarray(p1, dtype=float))
        d = p1 - p0
        num = self.offsets[None] - np.einsum("kfd,sd->skf", self.normals, p0)  # b - a.p0
        den = np.einsum("kfd,sd->skf", self.normals, d)  # a.d
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num / den
        t_enter = np.where(den < 0, t, -np.inf).max(axis=-1)
        t_leave = np.where(den > 0, t, np.inf).min(axis=-1)
        t_enter = np.maximum(t_enter, 0.0)
        t_leave = np.minimum(t_leave, 1.0)
        parallel_outside = np.any((den == 0) & (num <= tol), axis=-1)
        return (t_leave - t_enter > tol) & ~parallel_outside

    def extruded(self, z: float, tol_m: float = 1.0) -> "Obstacles":
        """The obstacles whose height range covers altitude z (down to ``tol_m`` below the base),
        made infinitely tall: the ground-plane test for a ground target, which a box standing on
        the ground must contain although the target is on its bottom face."""
        _, _, z_lo, z_hi = self.lateral()
        level = (z >= z_lo - tol_m) & (z <= z_hi)
        offsets = self.offsets[level].copy()
        offsets[:, 4:] = np.inf  # top (+z) and bottom (-z) faces never separate
        return Obstacles(self.normals[level], offsets)

    def lateral(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Ground-plane view for the guidance: (normals (K,4,2), offsets (K,4), z_low (K,), z_high (K,)).

        Valid because boxes rotate about z only: lateral normals are horizontal and unit length.
        """
        return (self.normals[:, :N_LATERAL, :2], self.offsets[:, :N_LATERAL],
                -self.offsets[:, 5], self.offsets[:, 4])


def polygons_crossed(normals: np.ndarray, offsets: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(S,) True where the planar segment a[s] -> b[s] passes through the interior of any convex
    polygon {p : n_f . p < b_f for all faces f} (Liang-Barsky). normals (K, F, 2), offsets (K, F)."""
    if not len(offsets):
        return np.zeros(len(a), dtype=bool)
    d = b - a
    num = offsets[None] - np.einsum("kfd,sd->skf", normals, a)
    den = np.einsum("kfd,sd->skf", normals, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / den
    t_in = np.maximum(np.where(den < 0, t, -np.inf).max(axis=-1), 0.0)
    t_out = np.minimum(np.where(den > 0, t, np.inf).min(axis=-1), 1.0)
    parallel_out = np.any((den == 0) & (num <= 0), axis=-1)
    return ((t_out - t_in > 1e-9) & ~parallel_out).any(axis=-1)
