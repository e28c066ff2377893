"""Collision costs of joint-space plans against the observed obstacle.

All costs are hinge sums over plan steps and robot points, in metres, differentiable in the points (and
so in the joint plan):

- ``penetration``: sum of ``max(0, -sdf)`` over surface points; zero for any plan that does not touch the
  obstacle. DetAug's selection score (the paper scores by penetration only: clearance scoring "games" the
  metric with circuitous paths).
- ``clearance``: sum of ``max(0, margin - sdf)``; also penalises near misses (the paper's ablation).
- ``spheres``: sum of ``max(0, margin + r - sdf(centre))`` over the end-effector spheres (CAPE's guidance).

:func:`held_object_cost` adds the object in the hand (its observed surface points), which the robot's
points do not cover: a carried bowl can push the obstacle while the arm stays clear of it.

Shapes: ``B`` plans (DetAug's K candidates), ``T`` plan steps, ``P`` robot points, ``S`` spheres.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from detaug_gym.geometry.kinematics import KinematicsResult
from detaug_gym.geometry.robot_points import RobotGeometry, RobotSurfacePoints
from detaug_gym.geometry.sdf import ObstacleSDF, obstacle_sdf

COST_KINDS = ("penetration", "clearance", "spheres")
DEFAULT_MARGIN = {"penetration": 0.0, "clearance": 0.05, "spheres": 0.02}
SDF = Callable[[torch.Tensor], torch.Tensor]
_default_robot: RobotGeometry | None = None


def penetration_cost(points: torch.Tensor, sdf: SDF) -> torch.Tensor:
    """Sum over plan steps and points of ``max(0, -sdf)``: points ``(..., T, P, 3)`` -> cost ``(...)``."""
    return torch.relu(-sdf(points)).sum(dim=(-2, -1))


def clearance_cost(points: torch.Tensor, sdf: SDF, margin: float = DEFAULT_MARGIN["clearance"]) -> torch.Tensor:
    """Sum over plan steps and points of ``max(0, margin - sdf)``: ``(..., T, P, 3)`` -> ``(...)``."""
    return torch.relu(margin - sdf(points)).sum(dim=(-2, -1))


def sphere_cost(centres: torch.Tensor, radii: torch.Tensor, sdf: SDF,
                margin: float = DEFAULT_MARGIN["spheres"]) -> torch.Tensor:
    """Sum over plan steps and spheres of ``max(0, margin + r - sdf(centre))``.

    Args:
        centres: ``(..., T, S, 3)`` sphere centres in the world.
        radii: ``(S,)`` radii.

    Returns:
        ``(...)`` cost.
    """
    return torch.relu(margin + radii - sdf(centres)).sum(dim=(-2, -1))


def surface_hinge_cost(fk: KinematicsResult, surface: RobotSurfacePoints, sdf: ObstacleSDF,
                       margin: float = 0.0) -> torch.Tensor:
    """Sum over points of ``max(0, margin - sdf)`` per configuration, skipping links far from the obstacle.

    Equal to ``clearance_cost`` (``penetration_cost`` at ``margin = 0``) on ``surface.world(fk)`` summed
    over points, but only the links whose bounding ball comes within ``margin`` of the obstacle's are
    placed and queried: far points contribute exactly zero, and usually most points are far.

    Args:
        fk: link poses ``(..., L, 3, 3)`` / ``(..., L, 3)``.

    Returns:
        ``(...)`` cost per configuration (sum over ``T`` yourself for a plan cost).
    """
    rot, pos = fk.rotations, fk.positions
    batch = rot.shape[:-3]
    num_links = rot.shape[-3]
    rot, pos = rot.reshape(-1, num_links, 3, 3), pos.reshape(-1, num_links, 3)
    total = torch.zeros(rot.shape[0], dtype=rot.dtype, device=rot.device)
    if sdf.empty:
        return (total + 0.0 * pos.sum(dim=(-2, -1))).view(batch)
    near = _near_links(rot, pos, surface, sdf, margin)  # (N, G) bool
    pair_config, pair_group = torch.nonzero(near, as_tuple=True)  # (M,) each: the (config, link) pairs to place
    if pair_config.numel() == 0:
        return (total + 0.0 * pos.sum(dim=(-2, -1))).view(batch)
    # Flatten every point of every near pair into one batch of Q queries (no per-link loop, no padding).
    counts, starts = (torch.as_tensor(x, device=rot.device) for x in (surface.group_counts, surface.group_starts))
    pair_counts = counts[pair_group]
    point_pair = torch.repeat_interleave(torch.arange(len(pair_group), device=rot.device), pair_counts)  # (Q,)
    first = torch.cumsum(pair_counts, 0) - pair_counts  # position of each pair's first query
    point_index = starts[pair_group][point_pair] + torch.arange(len(point_pair), device=rot.device) - first[point_pair]
    link = torch.as_tensor(surface.group_links, device=rot.device)[pair_group]
    pose_index = (pair_config * num_links + link)[point_pair]  # (Q,) into the flattened (N * L) poses
    r = rot.reshape(-1, 3, 3).index_select(0, pose_index)  # (Q, 3, 3); index_select beats fancy indexing
    local = surface.local_tensor(rot.dtype, rot.device).index_select(0, point_index)  # (Q, 3)
    world = (r[:, :, 0] * local[:, 0:1] + r[:, :, 1] * local[:, 1:2] + r[:, :, 2] * local[:, 2:3]
             + pos.reshape(-1, 3).index_select(0, pose_index))
    hinge = torch.relu(margin - sdf(world))
    return total.index_add(0, pair_config[point_pair], hinge).view(batch)


def _near_links(rot: torch.Tensor, pos: torch.Tensor, surface: RobotSurfacePoints, sdf: ObstacleSDF,
                margin: float) -> torch.Tensor:
    """``(N, G)`` whether link group g of configuration n can have a point with ``sdf < margin``."""
    with torch.no_grad():
        centre, radius = sdf.bounding_sphere()
        links = surface.group_links
        if not np.array_equal(links, np.arange(rot.shape[1])):
            index = torch.as_tensor(links, device=rot.device)
            rot, pos = rot.index_select(1, index), pos.index_select(1, index)
        local = torch.as_tensor(surface.group_centres, dtype=rot.dtype, device=rot.device)  # (G, 3)
        offset = pos - torch.as_tensor(centre, dtype=rot.dtype, device=rot.device)
        world = offset + rot[..., 0] * local[:, 0:1] + rot[..., 1] * local[:, 1:2] + rot[..., 2] * local[:, 2:3]
        reach = torch.as_tensor(surface.group_radii + radius + max(margin, 0.0), dtype=rot.dtype, device=rot.device)
        return (world * world).sum(-1) < reach * reach


def plan_collision_cost(joint_plan: torch.Tensor, obs: dict[str, np.ndarray] | None = None,
                        robot: RobotGeometry | None = None, kind: str = "penetration", margin: float | None = None,
                        finger_pos: torch.Tensor | None = None, sdf: ObstacleSDF | None = None) -> torch.Tensor:
    """Collision cost of each plan: FK, robot points (or spheres), obstacle SDF, hinge, sum over steps.

    Args:
        joint_plan: ``(B, T, 7)`` arm joint positions (any leading shape ``(..., T, 7)`` works).
        obs: the env observation (one env). Gives the obstacle (unless ``sdf`` is passed), the finger
            positions (``gripper_qpos``, unless ``finger_pos`` is passed) and, without ``robot``, the
            robot's base (see ``RobotGeometry.aligned_to``).
        robot: the robot's geometry; default robosuite's Panda aligned to ``obs``.
        kind: one of :data:`COST_KINDS`.
        margin: hinge margin (m); default :data:`DEFAULT_MARGIN` of ``kind``.
        finger_pos: ``(..., 2)`` finger positions, broadcastable to the plan's batch shape.
        sdf: a prebuilt obstacle SDF (e.g. kept for the episode); default :func:`obstacle_sdf` of ``obs``.

    Returns:
        ``(B,)`` cost (``(...)`` in general) in ``joint_plan``'s dtype, differentiable in it.
    """
    if kind not in COST_KINDS:
        raise ValueError(f"unknown cost kind {kind!r}; valid: {', '.join(COST_KINDS)}")
    if obs is None and (sdf is None or robot is None):
        raise ValueError("pass obs, or both sdf and robot")
    margin = DEFAULT_MARGIN[kind] if margin is None else float(margin)
    sdf = obstacle_sdf(obs) if sdf is None else sdf
    robot = _aligned_default(obs) if robot is None else robot
    joint_plan = torch.as_tensor(joint_plan)
    if finger_pos is None and obs is not None and "gripper_qpos" in obs:
        finger_pos = torch.as_tensor(np.asarray(obs["gripper_qpos"], np.float64))
    fk = robot.kinematics(joint_plan, finger_pos)
    if kind == "spheres":
        centres = robot.spheres.world(fk)
        return sphere_cost(centres, robot.spheres.radii_tensor(centres), sdf, margin)
    return surface_hinge_cost(fk, robot.points, sdf, margin).sum(-1)


def robot_clearance(joint_pos: torch.Tensor, obs: dict[str, np.ndarray], sdf: ObstacleSDF | None = None,
                    robot: RobotGeometry | None = None) -> torch.Tensor:
    """The scorer's distance (m) from the robot to the observed obstacle: the smallest SDF value over the
    robot's surface points, joint positions ``(..., 7)`` -> ``(...)`` (negative: a point is inside). What
    :func:`plan_collision_cost` sees of a configuration; compare it with the env's exact ``min_clearance``."""
    sdf = obstacle_sdf(obs) if sdf is None else sdf
    robot = _aligned_default(obs) if robot is None else robot
    fingers = torch.as_tensor(np.asarray(obs["gripper_qpos"], np.float64)) if "gripper_qpos" in obs else None
    joint_pos = torch.as_tensor(joint_pos, dtype=torch.float64)
    return sdf(robot.surface_points(joint_pos, fingers)).amin(dim=-1)


HELD_REACH = 0.10  # m: an object whose origin is this close to the grip site, with the fingers closed, is held
HELD_WIDTH = 0.06  # m: finger opening below which the hand counts as closed (open: ~0.08)


def held_object(obs: dict[str, np.ndarray]) -> np.ndarray | None:
    """The object in the hand at this observation, as its surface points relative to the grip site ``(N, 3)``.

    Held = fingers closed (opening < :data:`HELD_WIDTH`) and the nearest present object's origin within
    :data:`HELD_REACH` of the grip site; its points are the observation's ``object_points`` of that slot.
    ``None`` when nothing is held.
    """
    if "object_poses" not in obs or "gripper_qpos" not in obs:
        return None
    fingers = np.asarray(obs["gripper_qpos"], np.float64).reshape(-1)
    if abs(fingers[0] - fingers[-1]) >= HELD_WIDTH:
        return None
    if "object_points" not in obs:
        raise KeyError("held_object reads 'object_points' (the tracked objects' surface samples) from the "
                       "observation; every env of this package provides it")
    eef = np.asarray(obs["eef_pos"], np.float64)
    poses = np.asarray(obs["object_poses"], np.float64).reshape(-1, 7)
    points = np.asarray(obs["object_points"], np.float64).reshape(len(poses), -1, 3)
    mask = np.asarray(obs.get("object_mask", np.ones(len(poses))), np.float64).reshape(-1) > 0.5
    mask &= np.abs(points).sum(axis=(1, 2)) > 0  # slots without a body (a target region) hold nothing
    if not mask.any():
        return None
    slots = np.flatnonzero(mask)
    distance = np.linalg.norm(poses[slots, :3] - eef, axis=1)
    nearest = int(slots[np.argmin(distance)])
    if distance.min() > HELD_REACH:
        return None
    return points[nearest] - eef


def held_object_cost(eef_plan: torch.Tensor, finger_plan: torch.Tensor, obs: dict[str, np.ndarray],
                     sdf: SDF | None = None, kind: str = "penetration", margin: float | None = None) -> torch.Tensor:
    """Cost of the held object (its surface points carried rigidly with the grip site) along each plan.

    Args:
        eef_plan: ``(..., T, 3)`` planned grip-site positions.
        finger_plan: ``(..., T, 2)`` planned finger positions; the object counts only while they stay closed.
        obs: the observation at the replan (what is held, where, the obstacle).
        sdf: a prebuilt obstacle SDF; default :func:`obstacle_sdf` of ``obs``.
        kind, margin: as :func:`plan_collision_cost` (``spheres`` is treated like ``clearance``).

    Returns:
        ``(...)`` sum over plan steps and the object's points of ``max(0, margin - sdf)``; zeros when nothing
        is held.
    """
    if kind not in COST_KINDS:
        raise ValueError(f"unknown cost kind {kind!r}; valid: {', '.join(COST_KINDS)}")
    eef_plan = torch.as_tensor(eef_plan)
    held = held_object(obs)
    if held is None:
        return eef_plan.new_zeros(eef_plan.shape[:-2])
    margin = DEFAULT_MARGIN[kind] if margin is None else float(margin)
    sdf = obstacle_sdf(obs) if sdf is None else sdf
    points = eef_plan[..., None, :] + eef_plan.new_tensor(held)  # (..., T, N, 3): the grasp keeps the offsets
    finger_plan = torch.as_tensor(finger_plan, dtype=eef_plan.dtype)
    closed = ((finger_plan[..., 0] - finger_plan[..., -1]).abs() < HELD_WIDTH).to(eef_plan.dtype)
    return (torch.relu(margin - sdf(points)).sum(-1) * closed).sum(-1)


def _aligned_default(obs: dict[str, np.ndarray]) -> RobotGeometry:
    global _default_robot
    if _default_robot is None:
        _default_robot = RobotGeometry.panda()
    return _default_robot.aligned_to(obs)
