"""What an env observation says about the obstacle, read in one place.

The env reports (``ObstacleManipulationEnv``): ``obstacle_mask`` (1,) 1 with an obstacle and 0 without
(then every other obstacle entry is zero), ``obstacle_pose`` (7,) position + xyzw quaternion of the
obstacle's frame, ``obstacle_points`` (N, 3) world-frame surface samples (N = 256) and ``obstacle_size``
(3,) half-extents. The samples are fixed in the obstacle's frame and move with its pose, so the points in
the obstacle frame (:func:`obstacle_local_points`; the env reports them as ``obstacle_local_points``) identify
its *shape* across episodes and pushes. What the obstacle stands on (a pedestal or base; touching it moves the
obstacle) is a second *part* of the view with the same entries under the prefix ``obstacle_support``
(``obstacle_support_points`` (128, 3), ``..._local_points``, ``..._pose``, ``..._mask``); :func:`obstacle_parts`
lists the parts an observation holds, and every reader takes the part (default the obstacle itself).

:data:`SHAPES` is the one cache of what is derived from a shape (the convex hull and SDF grids of
:func:`~detaug_gym.geometry.obstacle_sdf`, AEGIS's ellipsoid fit): a shape is looked up by its local
points to within :data:`SHAPE_TOLERANCE` (float32 poses jitter them by ~1e-6 m, far below it), so each is
baked once per process however the obstacle is posed. This module needs only numpy; what is cached is
built by the callers.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable, Mapping
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from detaug_gym.rotations import quat_xyzw_to_mat

MASK_THRESHOLD = 0.5  # obstacle_mask >= this: there is an obstacle (the env writes exactly 0 or 1)
SHAPE_TOLERANCE = 1e-3  # m: local points this close (max over points and axes) are the same shape
SHAPE_CACHE_SIZE = 32  # shapes kept, least recently used dropped first

T = TypeVar("T")


OBSTACLE, SUPPORT = "obstacle", "obstacle_support"  # the parts of the view: the obstacle, what it stands on


def has_obstacle(obs: Mapping[str, np.ndarray], part: str = OBSTACLE) -> bool:
    """Whether the observation holds an obstacle (``obstacle_mask`` >= 0.5; no mask: no obstacle), or with
    ``part=SUPPORT`` an obstacle standing on a support."""
    masks = [obs.get(f"{p}_mask") for p in dict.fromkeys((OBSTACLE, part))]
    return all(m is not None and float(np.asarray(m).reshape(-1)[0]) >= MASK_THRESHOLD for m in masks)


def obstacle_parts(obs: Mapping[str, np.ndarray]) -> tuple[str, ...]:
    """The parts of the obstacle view this observation holds: ``()``, ``(OBSTACLE,)`` or ``(OBSTACLE, SUPPORT)``."""
    return tuple(p for p in (OBSTACLE, SUPPORT) if has_obstacle(obs, p))


def obstacle_frame(obs: Mapping[str, np.ndarray], part: str = OBSTACLE) -> tuple[np.ndarray, np.ndarray]:
    """The part's frame in the world: position ``(3,)`` and rotation ``(3, 3)`` (float64), from ``<part>_pose``."""
    pose = np.asarray(obs[f"{part}_pose"], np.float64)
    return pose[:3], quat_xyzw_to_mat(pose[3:7])


def obstacle_local_points(obs: Mapping[str, np.ndarray], part: str = OBSTACLE) -> np.ndarray:
    """The part's surface samples in its own frame, ``(N, 3)`` float64: the env's ``<part>_local_points``
    (the same numbers every episode), or for an observation without them ``<part>_points`` taken into the
    part's frame (float32 poses jitter those by ~1e-7 m, so what is built from the first one seen then depends
    on which episode that was)."""
    if f"{part}_local_points" in obs:
        return np.asarray(obs[f"{part}_local_points"], np.float64)
    position, rotation = obstacle_frame(obs, part)
    return (np.asarray(obs[f"{part}_points"], np.float64) - position) @ rotation


@dataclass
class CachedShape:
    """One obstacle shape and what has been derived from it.

    Attributes:
        points: ``(N, 3)`` the shape's points in the obstacle frame, as first seen.
        products: derived objects by key (``"hull"``, ``("sdf", spacing, padding)``, ``"mvee"``, ...).
    """

    points: np.ndarray
    products: dict[Hashable, Any] = field(default_factory=dict)

    def matches(self, points: np.ndarray) -> bool:
        """``points`` ``(N, 3)`` are this shape to within :data:`SHAPE_TOLERANCE`."""
        return self.points.shape == points.shape and float(np.abs(self.points - points).max()) < SHAPE_TOLERANCE

    def product(self, key: Hashable, build: Callable[[np.ndarray], T]) -> T:
        """The product ``key``, made by ``build(points)`` the first time it is asked for."""
        if key not in self.products:
            self.products[key] = build(self.points)
        return self.products[key]


class ShapeCache:
    """Obstacle shapes by their local points, least recently used dropped beyond ``capacity``."""

    def __init__(self, capacity: int = SHAPE_CACHE_SIZE) -> None:
        self.capacity = int(capacity)
        self._shapes: list[CachedShape] = []  # most recently used first

    def __len__(self) -> int:
        return len(self._shapes)

    def lookup(self, points: np.ndarray) -> CachedShape:
        """The cached shape matching local ``points`` ``(N, 3)``, added when there is none."""
        points = np.asarray(points, np.float64)
        index = next((i for i, shape in enumerate(self._shapes) if shape.matches(points)), None)
        shape = CachedShape(points.copy()) if index is None else self._shapes.pop(index)
        self._shapes = [shape, *self._shapes[:self.capacity - 1]]
        return shape

    def clear(self) -> None:
        self._shapes = []


SHAPES = ShapeCache()


def obstacle_shape(obs: Mapping[str, np.ndarray], cache: ShapeCache | None = None, part: str = OBSTACLE
                   ) -> CachedShape:
    """The cached shape of the observation's obstacle or another part (default cache :data:`SHAPES`)."""
    return (SHAPES if cache is None else cache).lookup(obstacle_local_points(obs, part))
