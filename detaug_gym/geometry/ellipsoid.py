"""Minimum-volume enclosing ellipsoid (MVEE) of a point set, by Khachiyan's algorithm (AEGIS's obstacle).

The ellipsoid is ``{x : (x - centre)^T shape (x - centre) <= 1}``. Khachiyan's iteration finds weights
``u`` on the points whose lifted scatter matrix defines the ellipsoid; each step moves weight towards the
point that lies farthest outside the current one (with Todd and Yildirim's away steps off the supporting
point that lies deepest inside), until the optimality conditions hold to within ``tol``. The result
is then scaled up, if needed, so that it encloses every point exactly (the iteration only approaches
enclosure). Only the convex hull's vertices matter, so the iteration runs on those.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError


@dataclass(frozen=True)
class Ellipsoid:
    """``{x : (x - centre)^T shape (x - centre) <= 1}``.

    Attributes:
        centre: ``(d,)``.
        shape: ``(d, d)`` symmetric positive definite.
    """

    centre: np.ndarray
    shape: np.ndarray

    def level(self, points: np.ndarray) -> np.ndarray:
        """``(x - c)^T A (x - c)`` for points ``(N, d)`` -> ``(N,)``; <= 1 inside."""
        diff = np.atleast_2d(points) - self.centre
        return np.einsum("ni,ij,nj->n", diff, self.shape, diff)

    def contains(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """``(N,)`` bool: the points lie inside (or on) the ellipsoid."""
        return self.level(points) <= 1.0 + tol

    @property
    def semi_axes(self) -> np.ndarray:
        """``(d,)`` semi-axis lengths, ascending, matching the columns of :attr:`axes`."""
        eigvals, _ = np.linalg.eigh(self.shape)
        return 1.0 / np.sqrt(eigvals[::-1])

    @property
    def axes(self) -> np.ndarray:
        """``(d, d)`` unit axis directions as columns, ordered like :attr:`semi_axes`."""
        _, eigvecs = np.linalg.eigh(self.shape)
        return eigvecs[:, ::-1]

    @property
    def volume(self) -> float:
        """Volume (area in 2-D)."""
        d = len(self.centre)
        unit_ball = np.pi ** (d / 2) / math.gamma(d / 2 + 1)
        return float(unit_ball / np.sqrt(np.linalg.det(self.shape)))


def min_volume_ellipsoid(points: np.ndarray, tol: float = 1e-6, max_iter: int = 20_000) -> Ellipsoid:
    """The minimum-volume ellipsoid enclosing ``(N, d)`` points (Khachiyan's algorithm).

    Args:
        points: ``(N, d)``, N >= d + 1, not all in one hyperplane.
        tol: relative optimality tolerance: every point within ``(1 + tol) (d + 1)`` of the lifted
            boundary, every supporting point at least ``(1 - tol) (d + 1)``; volume within ~``d tol / 2``.
        max_iter: iteration cap (the result still encloses every point when it is reached).

    Raises:
        ValueError: too few points, or the points are (nearly) flat, so no bounded ellipsoid encloses
            them with positive volume.
    """
    points = np.asarray(points, dtype=np.float64)
    n, d = points.shape
    if n < d + 1:
        raise ValueError(f"need at least {d + 1} points in {d}-D, got {n}")
    try:
        points = points[ConvexHull(points).vertices]
    except QhullError as err:
        raise ValueError(f"the points are flat (span no {d}-D volume): {err}") from err
    n = len(points)
    lifted = np.vstack([points.T, np.ones(n)])  # (d + 1, n)
    weights = np.full(n, 1.0 / n)
    for _ in range(max_iter):
        scatter = (lifted * weights) @ lifted.T
        farness = np.einsum("in,ij,jn->n", lifted, np.linalg.inv(scatter), lifted)  # d + 1 on the boundary
        far = int(np.argmax(farness))
        support = np.flatnonzero(weights > 0.0)
        near = int(support[np.argmin(farness[support])])
        if farness[far] <= (1.0 + tol) * (d + 1) and farness[near] >= (1.0 - tol) * (d + 1):
            break  # optimality conditions hold to within tol
        # Move weight towards the farthest point, or (Todd-Yildirim "away" step) off the supporting point
        # that lies deepest inside: the away steps make the iteration converge fast instead of crawling.
        j = far if farness[far] - (d + 1) >= (d + 1) - farness[near] else near
        step = (farness[j] - d - 1.0) / ((d + 1.0) * (farness[j] - 1.0))
        if j == near:
            step = max(step, -weights[j] / (1.0 - weights[j]))
        weights = (1.0 - step) * weights
        weights[j] += step
        weights[weights < 0.0] = 0.0
    centre = points.T @ weights
    spread = (points.T * weights) @ points - np.outer(centre, centre)
    shape = np.linalg.inv(spread) / d
    worst = float(Ellipsoid(centre, shape).level(points).max())
    if worst > 1.0:  # the iteration stops just short of enclosure: scale up to the farthest point
        shape = shape / worst
    return Ellipsoid(centre, 0.5 * (shape + shape.T))

