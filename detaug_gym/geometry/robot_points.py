"""Points on the robot's collision geometry and sphere approximations, moved by the batched FK.

``RobotSurfacePoints`` samples the collision meshes of every link once (trimesh, fixed seed, counts
split by surface area) and places the samples in the world for any batch of joint configurations;
``RobotSpheres`` does the same for a few spheres (CAPE's end-effector spheres). ``RobotGeometry``
bundles the kinematics with both, which is what the collision costs take.

Shapes: ``...`` any batch shape (``(B, T)`` for B plans of T steps), ``L`` links, ``P`` surface points,
``S`` spheres.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from detaug_gym.geometry.kinematics import KinematicsResult, PandaKinematics, panda_model
from detaug_gym.geometry.meshes import body_collision_mesh, sample_surface

ROBOT_POINTS = 1000  # surface samples of the default robot geometry (see RobotGeometry.from_model)
HAND_LINK = "gripper0_right_gripper"
# Default end-effector spheres in the hand frame (z = tool axis, x = finger travel): two over the hand's
# 0.2 m wide palm, one over the fingers. With r = 0.065 m (CAPE uses r ~ 0.06-0.08 m) they cover every
# collision vertex of the hand and the open fingers (fitted on robosuite's Panda; see the tests).
EEF_SPHERE_CENTRES = ((-0.05, 0.0, 0.02), (0.05, 0.0, 0.02), (0.0, 0.0, 0.08))
EEF_SPHERE_RADIUS = 0.065


class RobotSurfacePoints:
    """Fixed surface samples of the links, stored per link in the link frame.

    Attributes:
        link_index: ``(P,)`` link of each point (index into ``PandaKinematics.link_names``), sorted.
        local_points: ``(P, 3)`` the points in their link's frame (float64 numpy).
        group_links, group_centres, group_radii: per covered link (``G`` of them), a ball in the link
            frame holding all its points (``(G,)``, ``(G, 3)``, ``(G,)``), for culling far links.
        group_counts, group_starts: ``(G,)`` each: the link's points are rows
            ``group_starts[g] : group_starts[g] + group_counts[g]`` of :attr:`local_points`.
    """

    def __init__(self, link_index: np.ndarray, local_points: np.ndarray) -> None:
        order = np.argsort(link_index, kind="stable")
        self.link_index = np.asarray(link_index)[order]
        self.local_points = np.asarray(local_points, np.float64)[order]
        self._groups = [(int(link), np.flatnonzero(self.link_index == link)) for link in np.unique(self.link_index)]
        self._consts: dict[tuple[torch.dtype, torch.device], list[tuple[int, torch.Tensor]]] = {}
        bounds = [(self.local_points[idx].min(0) + self.local_points[idx].max(0)) / 2 for _, idx in self._groups]
        self.group_links = np.array([link for link, _ in self._groups])
        self.group_centres = np.array(bounds)  # (G, 3) bounding-ball centres of each link's points, link frame
        self.group_radii = np.array([np.linalg.norm(self.local_points[idx] - c, axis=1).max()
                                     for (_, idx), c in zip(self._groups, bounds)])  # (G,)
        self.group_counts = np.array([len(idx) for _, idx in self._groups])  # (G,) points per group
        self.group_starts = np.array([idx[0] for _, idx in self._groups])  # (G,) first row in local_points
        self._flat: dict[tuple[torch.dtype, torch.device], torch.Tensor] = {}

    @classmethod
    def from_model(cls, model: mujoco.MjModel, kinematics: PandaKinematics, count: int = 300, seed: int = 0,
                   links: list[str] | None = None) -> RobotSurfacePoints:
        """Sample ``count`` points over the links' collision meshes, split by area (each link >= 1 point).

        Args:
            model: the model ``kinematics`` was built from (or one with the same robot meshes).
            links: names of the links to cover (default all of ``kinematics.link_names``). ``robot0_link0``
                never moves, but it is kept by default so that the cost sees the whole robot.
        """
        names = kinematics.link_names if links is None else list(links)
        unknown = set(names) - set(kinematics.link_names)
        if unknown:
            raise ValueError(f"unknown links {sorted(unknown)}; valid: {kinematics.link_names}")
        meshes = [body_collision_mesh(model, _body_id(model, name)) for name in names]
        counts = _split_by_area(np.array([mesh.area for mesh in meshes]), count)
        index, points = [], []
        for k, (name, mesh, n) in enumerate(zip(names, meshes, counts)):
            points.append(sample_surface(mesh, int(n), seed=seed + k))
            index.append(np.full(int(n), kinematics.link_names.index(name)))
        return cls(np.concatenate(index), np.concatenate(points))

    def __len__(self) -> int:
        return len(self.link_index)

    def world(self, fk: KinematicsResult) -> torch.Tensor:
        """The points in the world: ``(..., P, 3)`` from link poses ``(..., L, 3, 3)`` / ``(..., L, 3)``."""
        rot, pos = fk.rotations, fk.positions
        parts = []
        for link, local in self._local(rot.dtype, rot.device):
            r = rot[..., link, None, :, :]  # (..., 1, 3, 3)
            parts.append(r[..., 0] * local[:, 0:1] + r[..., 1] * local[:, 1:2] + r[..., 2] * local[:, 2:3]
                         + pos[..., link, None, :])
        return torch.cat(parts, dim=-2)

    def local_tensor(self, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
        """:attr:`local_points` as a ``(P, 3)`` tensor (cached per dtype and device)."""
        key = (dtype, device)
        if key not in self._flat:
            self._flat[key] = torch.as_tensor(self.local_points, dtype=dtype, device=device)
        return self._flat[key]

    def groups(self, dtype: torch.dtype, device: torch.device) -> list[tuple[int, torch.Tensor]]:
        """``(link, local points (n, 3))`` per covered link, as tensors."""
        return self._local(dtype, device)

    def _local(self, dtype: torch.dtype, device: torch.device) -> list[tuple[int, torch.Tensor]]:
        key = (dtype, device)
        if key not in self._consts:
            self._consts[key] = [(link, torch.as_tensor(self.local_points[idx], dtype=dtype, device=device))
                                 for link, idx in self._groups]
        return self._consts[key]


@dataclass
class RobotSpheres:
    """Spheres fixed to links.

    Attributes:
        link_index: ``(S,)`` link of each sphere (index into ``PandaKinematics.link_names``).
        centres: ``(S, 3)`` centres in the link frame.
        radii: ``(S,)`` radii in m.
    """

    link_index: np.ndarray
    centres: np.ndarray
    radii: np.ndarray

    @classmethod
    def end_effector(cls, kinematics: PandaKinematics, radius: float = EEF_SPHERE_RADIUS,
                     centres: tuple[tuple[float, float, float], ...] = EEF_SPHERE_CENTRES) -> RobotSpheres:
        """Spheres over the hand and fingers (hand frame; defaults :data:`EEF_SPHERE_CENTRES`)."""
        link = kinematics.link_names.index(HAND_LINK)
        n = len(centres)
        return cls(np.full(n, link), np.asarray(centres, np.float64), np.full(n, float(radius)))

    def world(self, fk: KinematicsResult) -> torch.Tensor:
        """Sphere centres in the world, ``(..., S, 3)``."""
        rot, pos = fk.rotations, fk.positions
        idx = torch.as_tensor(self.link_index, device=rot.device)
        local = torch.as_tensor(self.centres, dtype=rot.dtype, device=rot.device)
        r = rot.index_select(-3, idx)  # (..., S, 3, 3)
        return (r * local[:, None, :]).sum(-1) + pos.index_select(-2, idx)

    def radii_tensor(self, like: torch.Tensor) -> torch.Tensor:
        """``(S,)`` radii in ``like``'s dtype and device."""
        return torch.as_tensor(self.radii, dtype=like.dtype, device=like.device)


class RobotGeometry:
    """Kinematics + surface points + end-effector spheres of one robot: what the collision costs take.

    Build it from the env's model (``RobotGeometry.from_model(env.scene.model)``) or, where only
    observations are at hand, from robosuite's Panda re-based on an observation
    (``RobotGeometry.panda().aligned_to(obs)``).
    """

    def __init__(self, kinematics: PandaKinematics, points: RobotSurfacePoints, spheres: RobotSpheres) -> None:
        self.kinematics = kinematics
        self.points = points
        self.spheres = spheres

    @classmethod
    def from_model(cls, model: mujoco.MjModel, num_points: int = ROBOT_POINTS, seed: int = 0) -> RobotGeometry:
        """FK, ``num_points`` surface samples (fixed ``seed``) and the default end-effector spheres.

        :data:`ROBOT_POINTS` (1000) over the Panda's ~0.9 m^2 of collision surface leave ~3 cm between
        neighbours; at 300 (~5 cm) the scorer read grazing contacts as 1-2 cm of clearance
        (``benchmarks/scorer_fidelity.py``). The culled cost grows with near points only.
        """
        kin = PandaKinematics.from_model(model)
        return cls(kin, RobotSurfacePoints.from_model(model, kin, num_points, seed), RobotSpheres.end_effector(kin))

    @classmethod
    def panda(cls, num_points: int = ROBOT_POINTS, seed: int = 0) -> RobotGeometry:
        """robosuite's Panda with its base at the world origin (see :meth:`aligned_to`)."""
        return cls.from_model(panda_model(), num_points, seed)

    def aligned_to(self, obs: dict[str, np.ndarray]) -> RobotGeometry:
        """A copy whose base is placed so that the observed joints give the observed end-effector pose.

        Uses ``robot_joint_pos``, ``gripper_qpos``, ``eef_pos`` and ``eef_quat`` (xyzw).
        """
        kin = self.kinematics.base_from_eef(obs["robot_joint_pos"], obs["eef_pos"], obs["eef_quat"],
                                            obs.get("gripper_qpos"))
        return RobotGeometry(kin, self.points, self.spheres)

    def surface_points(self, joint_pos: torch.Tensor, finger_pos: torch.Tensor | None = None) -> torch.Tensor:
        """World surface points ``(..., P, 3)`` for joint positions ``(..., 7)`` (fingers ``(..., 2)``)."""
        return self.points.world(self.kinematics(joint_pos, finger_pos))

    def sphere_centres(self, joint_pos: torch.Tensor, finger_pos: torch.Tensor | None = None) -> torch.Tensor:
        """World end-effector sphere centres ``(..., S, 3)``; radii in ``self.spheres.radii``."""
        return self.spheres.world(self.kinematics(joint_pos, finger_pos))


def _split_by_area(areas: np.ndarray, count: int) -> np.ndarray:
    """Integer counts proportional to ``areas`` summing to ``count`` (largest remainders, >= 1 each)."""
    if count < len(areas):
        raise ValueError(f"count={count} is fewer than the {len(areas)} links to cover")
    spare = count - len(areas)
    share = spare * areas / areas.sum()
    counts = np.floor(share).astype(int)
    counts[np.argsort(counts - share)[: spare - counts.sum()]] += 1
    return counts + 1


def _body_id(model: mujoco.MjModel, name: str) -> int:
    idx = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
    if idx < 0:
        raise KeyError(f"body {name!r} not in the model")
    return idx
