"""Kinematic and collision checks of a planned arm path, before anything is replayed.

A sample is rejected (the reason names the first failed check, in this order):

- ``ik_failed``: some target pose could not be reached within the IK tolerance;
- ``joint_limit``: a joint came within ``limit_margin`` of its range;
- ``joint_speed`` / ``joint_accel``: finite differences at the control rate exceed the thresholds (rad/s,
  rad/s^2), which also catches an IK branch flip between neighbouring targets;
- ``collision``: at some IK configuration the robot or the held object penetrates anything else by more
  than ``penetration`` (MuJoCo contacts on a scratch ``MjData``). Gripper-held-object contacts are the
  grasp itself and never count; contact pairs already present in the source at the transit's two
  endpoints (the bowl resting on the table when the carry starts, on the plate when it ends) are tolerated
  down to ``allowed_depth`` (1 cm) of penetration.

The held object is found from the source: the free body that moves with the end effector during the
carry. During the planned carry it is placed rigidly at the end effector with the offset it had at the
carry's start, which is also what the replay later verifies physically.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from detaug_gym.actions import CONTROL_DT
from detaug_gym.rotations import mat_to_quat_wxyz

GRIPPER_PREFIXES = ("gripper0_", "robot0_right_hand")
ROBOT_PREFIXES = ("robot0_", "gripper0_")


@dataclass(frozen=True)
class FeasibilityConfig:
    """Thresholds of the checks.

    Attributes:
        limit_margin: rad kept away from each joint limit.
        max_joint_speed: rad/s, per joint or one value (Panda limits are 2.175-2.61 rad/s).
        max_joint_accel: rad/s^2 (Panda limits are 7.5-20 rad/s^2).
        penetration: m of interpenetration tolerated before a contact is a collision.
        dt: s per control step.
    """

    limit_margin: float = 0.02
    max_joint_speed: float = 1.5
    max_joint_accel: float = 12.0
    penetration: float = 0.002
    dt: float = CONTROL_DT


@dataclass(frozen=True)
class HeldObject:
    """A free body held in the gripper: its body id, free-joint qpos address and pose in the grip-site frame."""

    body: int
    qpos_adr: int
    offset_pos: np.ndarray  # (3,) in the grip-site frame
    offset_rot: np.ndarray  # (3, 3) body rotation in the grip-site frame

    def world_qpos(self, site_pos: np.ndarray, site_rot: np.ndarray) -> np.ndarray:
        """Free-joint qpos (7,): position and wxyz quaternion of the body for a grip-site pose."""
        return np.concatenate([site_pos + site_rot @ self.offset_pos, mat_to_quat_wxyz(site_rot @ self.offset_rot)])


def body_names(model: mujoco.MjModel) -> list[str]:
    return [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in range(model.nbody)]


def free_bodies(model: mujoco.MjModel) -> list[tuple[int, int]]:
    """``(body id, qpos address)`` of every body with a free joint."""
    joints = np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)
    return [(int(model.jnt_bodyid[j]), int(model.jnt_qposadr[j])) for j in joints]


def find_held_object(model: mujoco.MjModel, data: mujoco.MjData, qpos_path: np.ndarray, site: int,
                     min_travel: float = 0.02) -> HeldObject | None:
    """The free body that travels furthest with the grip site over ``qpos_path`` (N, nq), or None.

    ``data`` is a scratch ``MjData`` of the model (its state is overwritten). The offset is taken at the
    first frame.
    """
    best, best_travel = None, min_travel
    for body, adr in free_bodies(model):
        travel = float(np.linalg.norm(qpos_path[-1, adr:adr + 3] - qpos_path[0, adr:adr + 3]))
        if travel > best_travel:
            best, best_travel = (body, adr), travel
    if best is None:
        return None
    body, adr = best
    data.qpos[:] = qpos_path[0]
    mujoco.mj_kinematics(model, data)
    site_rot = data.site_xmat[site].reshape(3, 3)
    return HeldObject(body, adr, grip_frame_position(data, site, body), site_rot.T @ data.xmat[body].reshape(3, 3))


def grip_frame_position(data: mujoco.MjData, site: int, body: int) -> np.ndarray:
    """(3,) the body's origin in the grip-site frame, from ``data``'s current kinematics."""
    return data.site_xmat[site].reshape(3, 3).T @ (data.xpos[body] - data.site_xpos[site])


def held_offset_drift(model: mujoco.MjModel, data: mujoco.MjData, qpos_path: np.ndarray, site: int,
                      held: HeldObject) -> float:
    """Largest distance (m) the held body's origin moves in the grip-site frame over ``qpos_path`` (N, nq)."""
    local = np.zeros((len(qpos_path), 3))
    for t, qpos in enumerate(qpos_path):
        data.qpos[:] = qpos
        mujoco.mj_kinematics(model, data)
        local[t] = grip_frame_position(data, site, held.body)
    return float(np.linalg.norm(local - local[0], axis=1).max())


def articulated_motion(model: mujoco.MjModel, qpos_path: np.ndarray, robot_qpos: np.ndarray,
                       threshold: float = 0.01) -> bool:
    """Whether a hinge/slide joint outside the robot moves by more than ``threshold`` over ``qpos_path``.

    A carry that drags an articulated part (pulling a drawer) cannot be bent: the handle must follow the
    slide, so such a carry stays unbent.
    """
    for j in range(model.njnt):
        if model.jnt_type[j] not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            continue
        adr = int(model.jnt_qposadr[j])
        if adr in robot_qpos:
            continue
        if abs(qpos_path[-1, adr] - qpos_path[0, adr]) > threshold:
            return True
    return False


def path_kinematics_reason(q: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                           config: FeasibilityConfig) -> str | None:
    """``None`` if the joint path (N, 7) respects limits, speed and acceleration, else the failed check."""
    if np.any(q < lower + config.limit_margin) or np.any(q > upper - config.limit_margin):
        return "joint_limit"
    if len(q) >= 2 and np.any(np.abs(np.diff(q, axis=0)) / config.dt > config.max_joint_speed):
        return "joint_speed"
    if len(q) >= 3 and np.any(np.abs(np.diff(q, 2, axis=0)) / config.dt ** 2 > config.max_joint_accel):
        return "joint_accel"
    return None


class ContactChecker:
    """Penetrating contacts of the robot and a held object with the rest of the scene, on a scratch MjData."""

    def __init__(self, model: mujoco.MjModel, penetration: float = 0.002, allowed_depth: float = 0.01) -> None:
        self.model = model
        self.allowed_depth = allowed_depth
        self.data = mujoco.MjData(model)
        self.penetration = penetration
        names = body_names(model)
        self.robot_body = np.array([n.startswith(ROBOT_PREFIXES) for n in names])
        self.gripper_body = np.array([n.startswith(GRIPPER_PREFIXES) for n in names])
        self.geom_body = model.geom_bodyid
        self.held_body: int | None = None
        self.allowed: set[tuple[int, int]] = set()

    def set_held(self, held: HeldObject | None) -> None:
        self.held_body = None if held is None else held.body

    def _pairs(self, qpos: np.ndarray, max_dist: float) -> dict[tuple[int, int], float]:
        """Body pairs (sorted) closer than ``max_dist`` that involve the robot or the held body, with their
        deepest contact distance (negative: penetration)."""
        m, d = self.model, self.data
        d.qpos[:] = qpos
        mujoco.mj_fwdPosition(m, d)
        pairs: dict[tuple[int, int], float] = {}
        for i in range(d.ncon):
            c = d.contact[i]
            if c.dist >= max_dist:
                continue
            b1, b2 = int(self.geom_body[c.geom1]), int(self.geom_body[c.geom2])
            if self._ignored(b1, b2):
                continue
            key = (min(b1, b2), max(b1, b2))
            pairs[key] = min(pairs.get(key, 0.0), float(c.dist))
        return pairs

    def _ignored(self, b1: int, b2: int) -> bool:
        held = self.held_body
        involved = self.robot_body[b1] or self.robot_body[b2] or held in (b1, b2)
        if not involved:
            return True
        if held is not None and ((b1 == held and self.gripper_body[b2]) or (b2 == held and self.gripper_body[b1])):
            return True  # the grasp itself
        return bool(self.robot_body[b1] and self.robot_body[b2] and self.gripper_body[b1] and self.gripper_body[b2])

    def allow_from(self, qpos_list: list[np.ndarray]) -> None:
        """Allow the (touching) contact pairs present in these source configurations, down to ``allowed_depth``."""
        self.allowed = set()
        for qpos in qpos_list:
            self.allowed |= set(self._pairs(qpos, 1e-4))

    def collides(self, qpos: np.ndarray) -> tuple[int, int] | None:
        """The first body pair at ``qpos`` that penetrates deeper than tolerated, or None."""
        for pair, dist in sorted(self._pairs(qpos, -self.penetration).items()):
            if pair not in self.allowed or dist < -self.allowed_depth:
                return pair
        return None
