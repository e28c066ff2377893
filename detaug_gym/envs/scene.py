"""A compiled robosuite scene and the MuJoCo bookkeeping every env in the package needs.

``Scene`` wraps one robosuite environment (a LIBERO task or the Newton table) after its model is compiled:
robot indices, the obstacles and pedestals, task-relevant objects, state get/set in LIBERO's flattened
layout, footprints for obstacle placement, contacts and clearances. The gymnasium env classes hold one
``Scene`` per task and never touch robosuite internals directly.
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass

import mujoco
import numpy as np

from detaug_gym.envs.obstacles import (
    ObstacleHandle,
    PedestalHandle,
    base_handles,
    obstacle_handles,
    park_all,
    pedestal_handles,
)
from detaug_gym.envs.placement import Footprint
from detaug_gym.geometry.meshes import body_collision_mesh, sample_surface

ARM_JOINTS = tuple(f"robot0_joint{i}" for i in range(1, 8))
GRIPPER_JOINTS = ("gripper0_finger_joint1", "gripper0_finger_joint2")
EEF_SITE = "gripper0_grip_site"
ROBOT_PREFIXES = ("robot0_", "gripper0_")
OBJECT_POINTS = 64  # surface samples per tracked object in the observation (``object_points``)
SETTLE_ACTION = np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float64)


def quiet():
    """LIBERO and robosuite print banners on import and benchmark lookup; keep the user's terminal clean."""
    return contextlib.redirect_stdout(io.StringIO())


@dataclass(frozen=True)
class PickPlace:
    """One sub-goal of a task: move ``obj`` (a body) onto/into ``target`` (a body or a site)."""

    obj: str
    target: str
    relation: str = "on"


class Scene:
    """A compiled robosuite env plus indices.

    Args:
        sim_env: a robosuite ``MujocoEnv`` already reset once.
        pick_places: the task's sub-goals in order.
        tracked: names (bodies or sites) whose poses fill ``object_poses``.
        obstacle_bodies: ``{kind: root body name}`` of the obstacles in the model, may be empty.
        state_size: ``(nq, nv)`` of the state layout without obstacles (LIBERO's init-state layout).
        goals_fn: ``() -> tuple[bool, ...]``, one flag per sub-goal of ``pick_places`` (in order): whether it
            holds in the current sim state. The task succeeds when all of them hold.
        parked: the obstacles are the procedural set (:mod:`~detaug_gym.envs.obstacles`), parked out of the
            scene until an episode activates one; ``False`` when the init state poses them (official scenarios).
        upright_x: ``{kind: rotation about x (rad)}`` that stands an obstacle type upright (default none).
    """

    def __init__(self, sim_env, pick_places: list[PickPlace], tracked: list[str], obstacle_bodies: dict[str, str],
                 state_size: tuple[int, int], goals_fn, parked: bool = True,
                 upright_x: dict[str, float] | None = None) -> None:
        self.sim_env = sim_env
        self.model: mujoco.MjModel = sim_env.sim.model._model
        self.data: mujoco.MjData = sim_env.sim.data._data
        self.robot = sim_env.robots[0]
        self.pick_places = pick_places
        self.tracked = tracked
        self.goals_fn = goals_fn
        self.nq0, self.nv0 = state_size
        m = self.model
        self.arm_qpos = np.array([m.jnt_qposadr[self._joint(j)] for j in ARM_JOINTS])
        self.arm_qvel = np.array([m.jnt_dofadr[self._joint(j)] for j in ARM_JOINTS])
        self.gripper_qpos = np.array([m.jnt_qposadr[self._joint(j)] for j in GRIPPER_JOINTS])
        self.eef_site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, EEF_SITE)
        body_names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in range(m.nbody)]
        robot_body = np.array([name.startswith(ROBOT_PREFIXES) for name in body_names])
        self.robot_geom = robot_body[m.geom_bodyid] & ((m.geom_contype | m.geom_conaffinity) > 0)
        self.robot_geom_ids = np.flatnonzero(self.robot_geom)
        gripper_body = np.array([name.startswith("gripper0_") for name in body_names])
        self.gripper_geom = self.robot_geom & gripper_body[m.geom_bodyid]
        self._body_names = body_names
        self._movable = _movable_bodies(m)
        self.obstacles: dict[str, ObstacleHandle] = (obstacle_handles(m, obstacle_bodies, upright_x)
                                                     if obstacle_bodies else {})
        self.pedestals: dict[str, PedestalHandle] = pedestal_handles(m)
        self.bases: dict[str, ObstacleHandle] = base_handles(m) if self.obstacles and parked else {}
        self.parked = parked and bool(self.obstacles)
        self._tracked_refs = [self._pose_ref(name) for name in tracked]
        self._tracked_local = [self._local_points(ref) for ref in self._tracked_refs]
        # Snapshot of the compiled model's static poses; fixtures are re-drawn per episode on top of it.
        self.nominal_body_pos = m.body_pos.copy()
        self.nominal_body_quat = m.body_quat.copy()
        if self.parked:
            park_all(m, self.data, self.obstacles, self.pedestals, self.bases)

    # ------------------------------------------------------------------ indices
    def _joint(self, name: str) -> int:
        jid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise KeyError(f"joint {name!r} not in the model")
        return jid

    def _pose_ref(self, name: str) -> tuple[str, int]:
        m = self.model
        for candidate in (f"{name}_main", name):
            bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, candidate)
            if bid >= 0:
                return "body", bid
        sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, name)
        if sid >= 0:
            return "site", sid
        raise KeyError(f"{name!r} is neither a body nor a site of this scene")

    def _local_points(self, ref: tuple[str, int]) -> np.ndarray | None:
        """:data:`OBJECT_POINTS` surface samples of a tracked body's collision geometry (with its subtree) in
        its frame; None for a site or a body without collision geometry."""
        kind, idx = ref
        if kind != "body":
            return None
        try:
            mesh = body_collision_mesh(self.model, idx, include_children=True)
        except ValueError:
            return None
        return sample_surface(mesh, OBJECT_POINTS, seed=0)

    def body_id(self, name: str) -> int:
        kind, idx = self._pose_ref(name)
        if kind == "site":
            return int(self.model.site_bodyid[idx])
        return idx

    # ------------------------------------------------------------------ state
    def get_state(self) -> np.ndarray:
        """Flattened ``[time, qpos, qvel]`` (robosuite/LIBERO layout), shape ``(1 + nq + nv,)``."""
        d = self.data
        return np.concatenate([[d.time], d.qpos, d.qvel])

    def set_state(self, state: np.ndarray) -> None:
        """Load a flattened state. A LIBERO-sized state (no obstacle joints) fills the leading entries.

        Raises:
            ValueError: the state size matches neither this model nor LIBERO's layout.
        """
        state = np.asarray(state, dtype=np.float64).ravel()
        m, d = self.model, self.data
        if state.size == 1 + m.nq + m.nv:
            nq, nv = m.nq, m.nv
        elif state.size == 1 + self.nq0 + self.nv0:
            nq, nv = self.nq0, self.nv0
        else:
            raise ValueError(
                f"state has {state.size} entries; this scene takes {1 + m.nq + m.nv} (full) "
                f"or {1 + self.nq0 + self.nv0} (LIBERO layout without obstacles)"
            )
        d.time = state[0]
        d.qpos[:nq] = state[1 : 1 + nq]
        d.qvel[:nv] = state[1 + nq : 1 + nq + nv]

    def reset_dynamics(self) -> None:
        """Clear everything a previous episode leaves behind in ``MjData`` and the robot's controllers."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qacc_warmstart[:] = 0.0
        gripper = self.robot.gripper
        gripper.current_action = np.zeros(gripper.dof)
        m.body_pos[:] = self.nominal_body_pos
        m.body_quat[:] = self.nominal_body_quat
        if self.parked:  # mj_resetData put the obstacles back at their compiled pose, inside the scene
            park_all(m, d, self.obstacles, self.pedestals, self.bases)

    # ------------------------------------------------------------------ reading
    def eef_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """End-effector (grip site) position ``(3,)`` and quaternion ``(4,)`` in xyzw order."""
        d = self.data
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, d.site_xmat[self.eef_site])
        return d.site_xpos[self.eef_site].copy(), quat[[1, 2, 3, 0]]

    def pose_of(self, name: str) -> np.ndarray:
        """World pose ``(7,)``: position and xyzw quaternion of a body or site."""
        return self._pose(self._pose_ref(name))

    def _pose(self, ref: tuple[str, int]) -> np.ndarray:
        kind, idx = ref
        d = self.data
        quat = np.zeros(4)
        if kind == "body":
            pos, quat = d.xpos[idx], d.xquat[idx]
        else:
            pos = d.site_xpos[idx]
            mujoco.mju_mat2Quat(quat, d.site_xmat[idx])
        return np.concatenate([pos, quat[[1, 2, 3, 0]]])

    def tracked_poses(self, slots: int) -> tuple[np.ndarray, np.ndarray]:
        """Poses of the tracked objects, ``(slots, 7)``, and their presence mask ``(slots,)``."""
        poses = np.zeros((slots, 7))
        mask = np.zeros(slots)
        for i, ref in enumerate(self._tracked_refs[:slots]):
            poses[i] = self._pose(ref)
            mask[i] = 1.0
        return poses, mask

    def tracked_points(self, slots: int) -> np.ndarray:
        """World-frame surface samples of the tracked objects, ``(slots, OBJECT_POINTS, 3)``; zeros for empty
        slots and for tracked sites (regions without a body)."""
        points = np.zeros((slots, OBJECT_POINTS, 3))
        d = self.data
        for i, (ref, local) in enumerate(zip(self._tracked_refs[:slots], self._tracked_local)):
            if local is not None:
                idx = ref[1]
                points[i] = local @ d.xmat[idx].reshape(3, 3).T + d.xpos[idx]
        return points

    def subtree_bodies(self, root: int) -> np.ndarray:
        """Ids of ``root`` and all its descendants."""
        parent = self.model.body_parentid
        inside = np.zeros(self.model.nbody, dtype=bool)
        inside[root] = True
        for b in range(root + 1, self.model.nbody):  # bodies are numbered parents first
            inside[b] = inside[parent[b]]
        return np.flatnonzero(inside)

    def collision_geoms(self, body: int) -> np.ndarray:
        """Ids of the collision geoms of ``body`` and its descendants."""
        m = self.model
        return np.flatnonzero(np.isin(m.geom_bodyid, self.subtree_bodies(body))
                              & ((m.geom_contype | m.geom_conaffinity) > 0))

    def world_aabb(self, body_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Axis-aligned world bounds of the collision geoms of ``body_ids``; ``None`` if they have none."""
        m, d = self.model, self.data
        geoms = np.flatnonzero(np.isin(m.geom_bodyid, body_ids) & ((m.geom_contype | m.geom_conaffinity) > 0))
        if geoms.size == 0:
            return None
        centre_local = m.geom_aabb[geoms, :3]
        half_local = m.geom_aabb[geoms, 3:]
        rot = d.geom_xmat[geoms].reshape(-1, 3, 3)
        centre = d.geom_xpos[geoms] + np.einsum("nij,nj->ni", rot, centre_local)
        half = np.einsum("nij,nj->ni", np.abs(rot), half_local)
        return (centre - half).min(axis=0), (centre + half).max(axis=0)

    def footprint(self, name: str) -> Footprint:
        """xy footprint of a body (with its subtree) or of a site's owning body."""
        kind, idx = self._pose_ref(name)
        if kind == "site":
            size = self.model.site_size[idx]
            pos = self.data.site_xpos[idx]
            half = np.maximum(size[:2], 0.02)
            return Footprint(name, pos[:2] - half, pos[:2] + half, float(pos[2]))
        bounds = self.world_aabb(self.subtree_bodies(idx))
        if bounds is None:
            pos = self.data.xpos[idx]
            return Footprint(name, pos[:2] - 0.02, pos[:2] + 0.02, float(pos[2]))
        lo, hi = bounds
        return Footprint(name, lo[:2], hi[:2], float(hi[2]))

    def support_heights(self, fp: Footprint) -> list[float]:
        """:meth:`support_height` under the centre and the four corners of a footprint (centre first)."""
        corners = [fp.center, fp.lo, fp.hi, np.array([fp.lo[0], fp.hi[1]]), np.array([fp.hi[0], fp.lo[1]])]
        return [self.support_height(c) for c in corners]

    def support_height(self, xy: np.ndarray) -> float:
        """Height of the first collision surface below ``xy`` that is not the robot, by downward rays."""
        m = self.model
        geomid = np.zeros(1, dtype=np.int32)
        down = np.array([0.0, 0.0, -1.0])
        z, exclude, passed = 3.0, -1, set()
        for _ in range(50):  # step through robot and visual-only geoms above the spot, one body at a time
            dist = mujoco.mj_ray(m, self.data, np.array([xy[0], xy[1], z]), down, None, 1, exclude, geomid)
            if dist < 0:
                break
            g = geomid[0]
            if not self.robot_geom[g] and (m.geom_contype[g] or m.geom_conaffinity[g]):
                return float(z - dist)
            body = int(m.geom_bodyid[g])
            # Restart just above the hit with that body excluded; when the ray is back on a body it already
            # passed (two overlapping robot links send it to and fro), restart just below the hit instead.
            z, exclude = z - dist + (-1e-4 if body in passed else 1e-6), body
            passed.add(body)
        raise RuntimeError(f"no support surface below {xy}")

    # ------------------------------------------------------------------ contacts
    def contact_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Geom ids of the active contacts, two arrays of shape ``(ncon,)``."""
        n = self.data.ncon
        return self.data.contact.geom1[:n].copy(), self.data.contact.geom2[:n].copy()

    def touching_geoms(self, geom_mask: np.ndarray) -> np.ndarray:
        """Ids of the geoms (outside ``geom_mask``) in contact with a geom where ``geom_mask`` is True."""
        g1, g2 = self.contact_pairs()
        partners = np.concatenate([g2[geom_mask[g1]], g1[geom_mask[g2]]])
        return np.unique(partners[~geom_mask[partners]])

    def contact_labels(self, geom_mask: np.ndarray, within: float = 0.0) -> tuple[str, ...]:
        """Who touches the geoms where ``geom_mask`` is True, sorted: ``"link:<body>"`` (an arm link),
        ``"gripper:<body>"`` (hand or finger), ``"held:<object>"`` (an object that the gripper touches too) or
        ``"object:<object>"`` (another movable object, named by its root body as LIBERO names objects). Static
        geometry (the table, fixtures) is left out: it holds the obstacle up, it does not push it.

        With ``within > 0`` the robot and movable geoms closer than ``within`` (m) count too, not only those in
        contact now: a fast hit can start and end between two control steps' contact lists.
        """
        partners = set(self.touching_geoms(geom_mask).tolist())
        if within > 0.0:
            partners |= self._geoms_near(geom_mask, within)
        labels = set()
        held_roots = None
        m = self.model
        for geom in partners:
            body = int(m.geom_bodyid[geom])
            if self.robot_geom[geom]:
                labels.add(f"{'gripper' if self.gripper_geom[geom] else 'link'}:{self._body_names[body]}")
            elif self._movable[body]:
                root = int(m.body_rootid[body])
                if held_roots is None:
                    held_roots = set(m.body_rootid[m.geom_bodyid[self.touching_geoms(self.gripper_geom)]].tolist())
                kind = "held" if root in held_roots else "object"
                labels.add(f"{kind}:{self._body_names[root].removesuffix('_main')}")
        return tuple(sorted(labels))

    def _geoms_near(self, geom_mask: np.ndarray, within: float) -> set[int]:
        """Robot and movable collision geoms (outside ``geom_mask``) closer than ``within`` to a masked geom."""
        m, d = self.model, self.data
        collides = (m.geom_contype | m.geom_conaffinity) > 0
        others = np.flatnonzero(collides & ~geom_mask & (self.robot_geom | self._movable[m.geom_bodyid]))
        targets = np.flatnonzero(geom_mask)
        gap = (np.linalg.norm(d.geom_xpos[others][:, None] - d.geom_xpos[targets][None], axis=-1)
               - m.geom_rbound[others][:, None] - m.geom_rbound[targets][None])
        fromto = np.zeros(6)
        near = set()
        for i, j in zip(*np.nonzero(gap < within)):
            if mujoco.mj_geomDistance(m, d, int(others[i]), int(targets[j]), within, fromto) < within:
                near.add(int(others[i]))
        return near

    def min_distance(self, geom_ids: np.ndarray, cap: float = 1.0) -> float:
        """Exact minimum distance between the robot's collision geoms and ``geom_ids`` (``cap`` if farther).

        Pairs are visited nearest bounding-sphere first and skipped once their sphere gap exceeds the best
        exact distance so far, so the result is exact at the cost of a handful of narrow-phase calls.
        """
        m, d = self.model, self.data
        robot = self.robot_geom_ids
        centre_gap = np.linalg.norm(d.geom_xpos[robot][:, None, :] - d.geom_xpos[geom_ids][None, :, :], axis=-1)
        sphere_gap = centre_gap - m.geom_rbound[robot][:, None] - m.geom_rbound[geom_ids][None, :]
        order = np.argsort(sphere_gap, axis=None)
        best = cap
        fromto = np.zeros(6)
        for flat in order:
            i, j = np.unravel_index(flat, sphere_gap.shape)
            if sphere_gap[i, j] >= best:
                break
            dist = mujoco.mj_geomDistance(m, d, int(robot[i]), int(geom_ids[j]), best, fromto)
            best = min(best, dist)
        return float(best)


def _movable_bodies(model: mujoco.MjModel) -> np.ndarray:
    """``(nbody,)`` whether a body can move: it or one of its ancestors has a joint."""
    movable = np.zeros(model.nbody, dtype=bool)
    for b in range(1, model.nbody):  # parents come first
        movable[b] = model.body_jntnum[b] > 0 or movable[model.body_parentid[b]]
    return movable
