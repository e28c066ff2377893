"""Batched, differentiable forward kinematics of the Panda, read from a compiled MuJoCo model.

The chain (body offsets, joint anchors and axes, joint reference positions, the base pose in the world)
is taken from the model exactly as MuJoCo compiled it, so the poses agree with ``mj_kinematics`` to
machine precision. Everything is plain torch: any leading batch shape, float32 or float64, and
gradients flow from link poses back to the joint positions (CAPE's guidance needs them).

Shapes: ``...`` is any batch shape (e.g. ``(B, T)`` for B plans of T steps), ``L`` the number of links
with collision geometry (12 for robosuite's Panda + PandaGripper: link0..link6, the hand, two fingers
and two finger tips).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from detaug_gym.rotations import quat_wxyz_to_mat, quat_xyzw_to_mat, skew

ARM_JOINTS = tuple(f"robot0_joint{i}" for i in range(1, 8))
FINGER_JOINTS = ("gripper0_finger_joint1", "gripper0_finger_joint2")
EEF_SITE = "gripper0_grip_site"
ROBOT_PREFIXES = ("robot0_", "gripper0_")


@dataclass
class KinematicsResult:
    """World poses from one :meth:`PandaKinematics.forward` call.

    Attributes:
        rotations: ``(..., L, 3, 3)`` link orientations (columns are the link axes in the world).
        positions: ``(..., L, 3)`` link origins in the world.
        eef_rotation: ``(..., 3, 3)`` grip-site orientation.
        eef_position: ``(..., 3)`` grip-site position.
    """

    rotations: torch.Tensor
    positions: torch.Tensor
    eef_rotation: torch.Tensor
    eef_position: torch.Tensor


@dataclass(frozen=True)
class _Joint:
    slot: int  # index into the concatenated input [arm (7), fingers (2)]
    hinge: bool
    anchor: np.ndarray  # (3,) in the body frame
    axis: np.ndarray  # (3,) unit, body frame
    ref: float  # qpos0: MuJoCo measures joint motion from it


@dataclass(frozen=True)
class _Body:
    name: str
    parent: int  # index into the body list, -1 for the fixed base frame
    pos: np.ndarray  # (3,) offset in the parent frame
    rot: np.ndarray  # (3, 3) orientation in the parent frame
    joints: tuple[_Joint, ...]


class PandaKinematics:
    """Forward kinematics of the robot subtree (bodies named ``robot0_*`` / ``gripper0_*``).

    Build with :meth:`from_model`; call :meth:`forward` (or the object itself).

    Attributes:
        base_rotation, base_position: world pose ``(3, 3)``, ``(3,)`` of the frame the robot's root body
            (``robot0_base``) hangs from: the world itself for robosuite's models, whose mount offset is
            the root body's own (fixed) offset.
        link_names: the ``L`` bodies with collision geometry, in output order.
        link_body_ids: their body ids in the source model.
        default_fingers: ``(2,)`` finger positions used when none are given: fully open (the joint limit
            farther from zero).
    """

    def __init__(self, bodies: list[_Body], base_rot: np.ndarray, base_pos: np.ndarray, link_index: list[int],
                 link_body_ids: list[int], eef_body: int, eef_pos: np.ndarray, eef_rot: np.ndarray,
                 default_fingers: np.ndarray) -> None:
        self._bodies = bodies
        self.base_rotation = np.asarray(base_rot, dtype=np.float64)
        self.base_position = np.asarray(base_pos, dtype=np.float64)
        self._link_index = link_index
        self.link_names = [bodies[i].name for i in link_index]
        self.link_body_ids = link_body_ids
        self._eef = (eef_body, np.asarray(eef_pos, np.float64), np.asarray(eef_rot, np.float64))
        self.default_fingers = np.asarray(default_fingers, dtype=np.float64)
        self._consts: dict[tuple[torch.dtype, torch.device], dict] = {}  # shared by re-based copies

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_model(cls, model: mujoco.MjModel, arm_joints: tuple[str, ...] = ARM_JOINTS,
                   finger_joints: tuple[str, ...] = FINGER_JOINTS, eef_site: str = EEF_SITE,
                   prefixes: tuple[str, ...] = ROBOT_PREFIXES) -> PandaKinematics:
        """Read the chain from a compiled model (a LIBERO scene, a robosuite env, :func:`panda_model`).

        Raises:
            KeyError: a named joint or the site is missing.
            ValueError: the robot's root body hangs below a moving body, or a robot joint is neither a
                named arm/finger joint nor a hinge/slide.
        """
        slots = {_id(model, mujoco.mjtObj.mjOBJ_JOINT, name): k for k, name in enumerate(arm_joints + finger_joints)}
        names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in range(model.nbody)]
        robot = [b for b in range(model.nbody) if names[b].startswith(prefixes)]
        order = {b: i for i, b in enumerate(robot)}  # MuJoCo numbers parents before children
        root_parent = int(model.body_parentid[robot[0]])
        base = _static_world_pose(model, root_parent)
        bodies = []
        for b in robot:
            parent = int(model.body_parentid[b])
            if parent not in order and parent != root_parent:
                raise ValueError(f"robot body {names[b]!r} is not under the robot's root")
            bodies.append(_Body(names[b], order.get(parent, -1), model.body_pos[b].copy(),
                                quat_wxyz_to_mat(model.body_quat[b]), _body_joints(model, b, slots)))
        links = [i for i, b in enumerate(robot) if _has_collision_geom(model, b)]
        site = _id(model, mujoco.mjtObj.mjOBJ_SITE, eef_site)
        eef_body = int(model.site_bodyid[site])
        if eef_body not in order:
            raise ValueError(f"site {eef_site!r} is not on a robot body")
        fingers = [_open_limit(model, _id(model, mujoco.mjtObj.mjOBJ_JOINT, j)) for j in finger_joints]
        return cls(bodies, base[0], base[1], links, [robot[i] for i in links], order[eef_body],
                   model.site_pos[site].copy(), quat_wxyz_to_mat(model.site_quat[site]), np.array(fingers))

    def with_base(self, rotation: np.ndarray, position: np.ndarray) -> PandaKinematics:
        """A copy whose base frame (see :attr:`base_rotation`) sits at the given world pose."""
        eef_body, eef_pos, eef_rot = self._eef
        out = PandaKinematics(self._bodies, rotation, position, self._link_index, self.link_body_ids, eef_body,
                              eef_pos, eef_rot, self.default_fingers)
        out._consts = self._consts
        return out

    def base_from_eef(self, joint_pos: np.ndarray, eef_pos: np.ndarray, eef_quat_xyzw: np.ndarray,
                      finger_pos: np.ndarray | None = None) -> PandaKinematics:
        """A copy re-based so that ``joint_pos`` (7,) puts the grip site at the observed pose.

        This lets a policy that only sees observations (``robot_joint_pos``, ``eef_pos``, ``eef_quat``)
        place a kinematics built from another model of the same robot where the env's robot stands.
        """
        origin = self.with_base(np.eye(3), np.zeros(3))
        res = origin.forward(torch.as_tensor(np.asarray(joint_pos, np.float64)),
                             None if finger_pos is None else torch.as_tensor(np.asarray(finger_pos, np.float64)))
        r_be, p_be = res.eef_rotation.numpy(), res.eef_position.numpy()  # eef in the base frame
        r_we = quat_xyzw_to_mat(eef_quat_xyzw)
        r_wb = r_we @ r_be.T
        return self.with_base(r_wb, np.asarray(eef_pos, np.float64) - r_wb @ p_be)

    # ------------------------------------------------------------------ evaluation
    def __call__(self, joint_pos: torch.Tensor, finger_pos: torch.Tensor | None = None) -> KinematicsResult:
        return self.forward(joint_pos, finger_pos)

    def forward(self, joint_pos: torch.Tensor, finger_pos: torch.Tensor | None = None) -> KinematicsResult:
        """World poses of the links and the grip site.

        Args:
            joint_pos: ``(..., 7)`` arm joint positions (rad), float32 or float64.
            finger_pos: ``(..., 2)`` finger joint positions (m), or anything broadcastable to it; ``None``
                uses :attr:`default_fingers` (open).

        Returns:
            :class:`KinematicsResult` with ``(..., L, 3, 3)`` / ``(..., L, 3)`` link poses and the
            ``(..., 3, 3)`` / ``(..., 3)`` grip-site pose, in ``joint_pos``'s dtype.
        """
        joint_pos = torch.as_tensor(joint_pos)
        if not joint_pos.is_floating_point():
            joint_pos = joint_pos.to(torch.get_default_dtype())
        if joint_pos.shape[-1] != 7:
            raise ValueError(f"joint_pos must end in 7 entries, got shape {tuple(joint_pos.shape)}")
        dtype, device = joint_pos.dtype, joint_pos.device
        c = self._constants(dtype, device)
        fingers = c["fingers"] if finger_pos is None else torch.as_tensor(finger_pos, dtype=dtype, device=device)
        # Internally the batch is the last, contiguous axis: rotations (3, 3, N), positions (3, N). Tiny
        # per-element 3x3 products are then a few vectorised multiply-adds over N instead of a slow bmm.
        batch = torch.broadcast_shapes(joint_pos.shape[:-1], fingers.shape[:-1])
        q = torch.cat([joint_pos.expand(*batch, 7), fingers.expand(*batch, 2)], dim=-1).reshape(-1, 9).T  # (9, N)
        base_r = torch.as_tensor(self.base_rotation, dtype=dtype, device=device)[..., None]
        base_p = torch.as_tensor(self.base_position, dtype=dtype, device=device)[..., None]
        rots: list[torch.Tensor] = []
        poss: list[torch.Tensor] = []
        for body, bc in zip(self._bodies, c["bodies"]):
            parent_r, parent_p = (base_r, base_p) if body.parent < 0 else (rots[body.parent], poss[body.parent])
            pos = parent_p if bc["zero_offset"] else parent_p + _matvec(parent_r, bc["pos"])
            if bc["rigid_same_axes"]:  # no joint and no rotation offset: the parent's orientation
                rot = parent_r
            elif "fused" in bc:  # one hinge through the body origin: rot = parent @ offset @ Rodrigues
                a, b, k2 = bc["fused"]
                angle = q[body.joints[0].slot] - body.joints[0].ref
                rot = _matmul(parent_r, a + torch.sin(angle) * b + (1.0 - torch.cos(angle)) * k2)
            else:
                rot = _matmul(parent_r, bc["rot"])
                for joint, jc in zip(body.joints, bc["joints"]):
                    rot, pos = _apply_joint(rot, pos, q[joint.slot] - joint.ref, joint.hinge, jc)
            rots.append(rot)
            poss.append(pos)
        n = q.shape[1]
        eef_body = self._eef[0]
        eef_rot = _matmul(rots[eef_body], c["eef_rot"]).expand(3, 3, n).permute(2, 0, 1).reshape(*batch, 3, 3)
        eef_pos = (poss[eef_body] + _matvec(rots[eef_body], c["eef_pos"])).expand(3, n).T.reshape(*batch, 3)
        link_rot = torch.stack([rots[i].expand(3, 3, n) for i in self._link_index]).permute(3, 0, 1, 2)
        link_pos = torch.stack([poss[i].expand(3, n) for i in self._link_index]).permute(2, 0, 1)
        num_links = len(self._link_index)
        return KinematicsResult(link_rot.reshape(*batch, num_links, 3, 3), link_pos.reshape(*batch, num_links, 3),
                                eef_rot, eef_pos)

    def _constants(self, dtype: torch.dtype, device: torch.device) -> dict:
        key = (dtype, device)
        if key not in self._consts:
            def t(x):  # constants carry a trailing batch axis of 1: (3, 3, 1) or (3, 1)
                return torch.as_tensor(np.asarray(x, np.float64), dtype=dtype, device=device)[..., None]
            bodies = []
            for body in self._bodies:
                joints = [{"anchor": t(j.anchor), "axis": t(j.axis), "cross": t(skew(j.axis)),
                           "cross2": t(skew(j.axis) @ skew(j.axis)), "eye": t(np.eye(3))}
                          for j in body.joints]
                bodies.append({"rot": t(body.rot), "pos": t(body.pos), "joints": joints,
                               "zero_offset": not np.any(body.pos),
                               "rigid_same_axes": not body.joints and np.array_equal(body.rot, np.eye(3))})
                if len(body.joints) == 1 and body.joints[0].hinge and not np.any(body.joints[0].anchor):
                    k = skew(body.joints[0].axis)
                    bodies[-1]["fused"] = (t(body.rot), t(body.rot @ k), t(body.rot @ k @ k))
            self._consts[key] = {"bodies": bodies, "eef_rot": t(self._eef[2]), "eef_pos": t(self._eef[1]),
                                 "fingers": t(self.default_fingers)[:, 0]}
        return self._consts[key]


def _apply_joint(rot: torch.Tensor, pos: torch.Tensor, angle: torch.Tensor, hinge: bool,
                 jc: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """One MuJoCo hinge (rotation about the axis through the anchor) or slide joint, as mj_kinematics does.

    Batch-last layout: ``rot`` (3, 3, N), ``pos`` (3, N), ``angle`` (N,) measured from the joint's qpos0.
    """
    if not hinge:
        return rot, pos + _matvec(rot, jc["axis"]) * angle
    anchor_world = pos + _matvec(rot, jc["anchor"])
    local = jc["eye"] + torch.sin(angle) * jc["cross"] + (1.0 - torch.cos(angle)) * jc["cross2"]  # Rodrigues
    new_rot = _matmul(rot, local)
    return new_rot, anchor_world - _matvec(new_rot, jc["anchor"])


def _matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` per batch element for batch-last stacks ``(3, 3, N)`` (N may be 1 and broadcast).

    One broadcast product and one reduction: the FK is bound by per-op overhead, not arithmetic.
    """
    return (a[:, :, None] * b[None]).sum(1)


def _matvec(a: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``a @ v`` per batch element for ``a`` (3, 3, N) and ``v`` (3, N), batch last."""
    return (a * v[None]).sum(1)


def _body_joints(model: mujoco.MjModel, body: int, slots: dict[int, int]) -> tuple[_Joint, ...]:
    joints = []
    for j in range(int(model.body_jntadr[body]), int(model.body_jntadr[body]) + int(model.body_jntnum[body])):
        jtype = int(model.jnt_type[j])
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
        if j not in slots or jtype not in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            raise ValueError(f"robot joint {name!r} is not one of the arm/finger hinge or slide joints")
        axis = np.asarray(model.jnt_axis[j], np.float64)
        joints.append(_Joint(slots[j], jtype == int(mujoco.mjtJoint.mjJNT_HINGE), model.jnt_pos[j].copy(),
                             axis / np.linalg.norm(axis), float(model.qpos0[model.jnt_qposadr[j]])))
    return tuple(joints)


def _static_world_pose(model: mujoco.MjModel, body: int) -> tuple[np.ndarray, np.ndarray]:
    """World pose of a body from the compiled offsets; its ancestors must not have joints."""
    rot, pos = np.eye(3), np.zeros(3)
    chain = []
    while body > 0:
        if model.body_jntnum[body]:
            raise ValueError("the robot's root body is mounted on a moving body")
        chain.append(body)
        body = int(model.body_parentid[body])
    for b in reversed(chain):
        pos = pos + rot @ model.body_pos[b]
        rot = rot @ quat_wxyz_to_mat(model.body_quat[b])
    return rot, pos


def _has_collision_geom(model: mujoco.MjModel, body: int) -> bool:
    start, count = int(model.body_geomadr[body]), int(model.body_geomnum[body])
    return any(model.geom_contype[g] or model.geom_conaffinity[g] for g in range(start, start + count))


def _open_limit(model: mujoco.MjModel, joint: int) -> float:
    lo, hi = model.jnt_range[joint]
    return float(hi if abs(hi) >= abs(lo) else lo)


def _id(model: mujoco.MjModel, kind: mujoco.mjtObj, name: str) -> int:
    idx = mujoco.mj_name2id(model, kind, name)
    if idx < 0:
        raise KeyError(f"{name!r} not in the model")
    return idx


def panda_model() -> mujoco.MjModel:
    """robosuite's Panda + PandaGripper on an empty arena, base at the world origin (compiled, ~1 s).

    The same robot, with the same body/joint names, as the envs' scenes; use it (with
    :meth:`PandaKinematics.base_from_eef`) where only observations are at hand, and in tests.
    """
    from robosuite.models.arenas import EmptyArena
    from robosuite.models.grippers import PandaGripper
    from robosuite.models.robots import Panda
    from robosuite.models.tasks import ManipulationTask

    robot = Panda()
    robot.add_gripper(PandaGripper())
    robot.set_base_xpos([0.0, 0.0, 0.0])
    task = ManipulationTask(mujoco_arena=EmptyArena(), mujoco_robots=[robot])
    return task.get_model(mode="mujoco")
