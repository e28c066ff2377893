"""Shared collision geometry: one definition of "collision" for every method in the zoo.

DetAug's selection scorer, CAPE's guidance, AEGIS's barrier and DemoGen's planner all go through here:

- :class:`PandaKinematics`: batched, differentiable torch FK of the Panda built from a MuJoCo model.
- :class:`RobotSurfacePoints` / :class:`RobotSpheres` / :class:`RobotGeometry`: points sampled on the
  robot's collision meshes and end-effector spheres, placed by the FK.
- :func:`has_obstacle`, :func:`obstacle_parts`, :func:`obstacle_frame`, :func:`obstacle_local_points`,
  :func:`obstacle_shape`: the obstacle entries of an observation (the obstacle and what it stands on), read
  in one place, and the one cache of per-shape products.
- :func:`obstacle_sdf` / :class:`ObstacleSDF` / :class:`UnionSDF`: signed distance (negative inside) to the
  observed obstacle's convex hull (and its support's), exact (trimesh + python-fcl) and baked on a grid for
  fast torch queries.
- :func:`penetration_cost`, :func:`clearance_cost`, :func:`sphere_cost`, :func:`plan_collision_cost`:
  hinge costs of ``(B, T, 7)`` joint plans.
- :func:`min_volume_ellipsoid`: Khachiyan's MVEE (AEGIS's obstacle ellipsoid).

Typical use inside a policy (observations only)::

    from detaug_gym.geometry import obstacle_sdf, plan_collision_cost
    cost = plan_collision_cost(joint_plans, obs)          # (K,), penetration in metres

Exports load lazily (PEP 562): ``detaug_gym.geometry.meshes``, which the envs use, stays free of torch.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "costs": ("COST_KINDS", "clearance_cost", "held_object", "held_object_cost", "penetration_cost",
              "plan_collision_cost", "robot_clearance", "sphere_cost", "surface_hinge_cost"),
    "ellipsoid": ("Ellipsoid", "min_volume_ellipsoid"),
    "kinematics": ("KinematicsResult", "PandaKinematics", "panda_model"),
    "obstacle_view": ("OBSTACLE", "SHAPES", "SUPPORT", "CachedShape", "ShapeCache", "has_obstacle",
                      "obstacle_frame", "obstacle_local_points", "obstacle_parts", "obstacle_shape"),
    "robot_points": ("RobotGeometry", "RobotSpheres", "RobotSurfacePoints"),
    "sdf": ("NO_OBSTACLE_DISTANCE", "ObstacleSDF", "SDFGrid", "UnionSDF", "bake_sdf_grid", "convex_hull",
            "exact_signed_distance", "obstacle_sdf"),
}
_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
__all__ = sorted(_WHERE)


def __getattr__(name: str) -> Any:
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
