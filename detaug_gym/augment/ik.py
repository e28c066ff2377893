"""Damped-least-squares inverse kinematics of the Panda arm on the env's own MuJoCo model.

Works on a scratch ``MjData`` (the env's ``data`` is never touched), so the rest of the scene (objects,
fixtures, the gripper opening) sits wherever the caller put it: the same model serves IK and the contact
checks of :mod:`detaug_gym.augment.feasibility`. Poses are the grip site's (``eef_pos``/``eef_quat`` of the
observation); quaternions are xyzw as everywhere in the package (:mod:`detaug_gym.rotations`).

Each solve starts from the previous configuration (warm start along the path) and iterates

    dq = J^T (J J^T + lambda^2 I)^-1 e  +  k_null (I - J^+ J) (q_rest - q),

with ``e`` the 6-D pose error (position, rotation vector), clipped per iteration, until the error is below
tolerance. The nullspace term pulls the elbow towards the posture the OSC controller itself holds, so the
IK arm looks like the arm the controller will produce on replay.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from detaug_gym.rotations import rotation_error


@dataclass(frozen=True)
class IKConfig:
    """Solver settings.

    Attributes:
        damping: lambda of the damped least squares (m / rad scale).
        max_iters: iterations per target pose.
        pos_tol: position error accepted as solved (m).
        rot_tol: rotation error accepted as solved (rad).
        max_step: largest joint change per iteration (rad), keeps the linearisation honest.
        null_gain: weight of the pull towards the rest posture in the nullspace.
    """

    damping: float = 0.02
    max_iters: int = 60
    pos_tol: float = 1e-3
    rot_tol: float = 1e-2
    max_step: float = 0.2
    null_gain: float = 0.05


@dataclass
class IKResult:
    """Joint path (N, 7) and the remaining pose errors per target, (N,) m and (N,) rad."""

    q: np.ndarray
    pos_err: np.ndarray
    rot_err: np.ndarray

    def solved(self, config: IKConfig) -> bool:
        return bool(np.all(self.pos_err <= config.pos_tol) and np.all(self.rot_err <= config.rot_tol))


class ArmIK:
    """IK of the arm joints for the grip site of a scene's model.

    Args:
        model: the env's ``MjModel`` (read only).
        arm_qpos: qpos addresses of the 7 arm joints; ``arm_dofs`` their dof addresses.
        site: id of the grip site.
        rest: rest posture for the nullspace pull (the OSC controller's ``initial_joint``).
    """

    def __init__(self, model: mujoco.MjModel, arm_qpos: np.ndarray, arm_dofs: np.ndarray, site: int,
                 rest: np.ndarray | None = None, config: IKConfig | None = None) -> None:
        self.model = model
        self.data = mujoco.MjData(model)
        self.arm_qpos = np.asarray(arm_qpos)
        self.arm_dofs = np.asarray(arm_dofs)
        self.site = int(site)
        self.config = config or IKConfig()
        joints = [int(np.flatnonzero(model.jnt_qposadr == a)[0]) for a in self.arm_qpos]
        self.lower, self.upper = model.jnt_range[joints, 0].copy(), model.jnt_range[joints, 1].copy()
        self.rest = None if rest is None else np.asarray(rest, dtype=np.float64)
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))

    def load(self, qpos: np.ndarray) -> None:
        """Put the whole scene configuration ``qpos`` (nq,) into the scratch data."""
        self.data.qpos[:] = qpos
        mujoco.mj_kinematics(self.model, self.data)

    def site_pose(self, q: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Grip-site position (3,) and rotation (3, 3) at arm configuration ``q`` (default: as loaded)."""
        if q is not None:
            self.data.qpos[self.arm_qpos] = q
            mujoco.mj_kinematics(self.model, self.data)
        return self.data.site_xpos[self.site].copy(), self.data.site_xmat[self.site].reshape(3, 3).copy()

    def solve_path(self, q_start: np.ndarray, positions: np.ndarray, rotations: np.ndarray) -> IKResult:
        """Solve every target in order, warm-starting each from the previous solution.

        Args:
            q_start: arm configuration (7,) to start from (the source's at the transit start).
            positions: (N, 3) grip-site targets; ``rotations``: (N, 3, 3).
        """
        q = np.asarray(q_start, dtype=np.float64).copy()
        n = len(positions)
        out = np.zeros((n, q.size))
        pos_err, rot_err = np.zeros(n), np.zeros(n)
        for i in range(n):
            q, pos_err[i], rot_err[i] = self.solve(q, positions[i], rotations[i])
            out[i] = q
        return IKResult(out, pos_err, rot_err)

    def solve(self, q: np.ndarray, target_pos: np.ndarray, target_rot: np.ndarray) -> tuple[np.ndarray, float, float]:
        """One target: returns the configuration and its position / rotation errors."""
        cfg, m, d = self.config, self.model, self.data
        q = np.clip(np.asarray(q, dtype=np.float64).copy(), self.lower, self.upper)
        lam2 = cfg.damping ** 2
        for _ in range(cfg.max_iters + 1):
            d.qpos[self.arm_qpos] = q
            mujoco.mj_kinematics(m, d)
            err = np.concatenate([target_pos - d.site_xpos[self.site],
                                  rotation_error(target_rot, d.site_xmat[self.site].reshape(3, 3))])
            pos_err, rot_err = float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:]))
            if pos_err <= 0.1 * cfg.pos_tol and rot_err <= 0.1 * cfg.rot_tol:
                break
            mujoco.mj_comPos(m, d)
            mujoco.mj_jacSite(m, d, self._jacp, self._jacr, self.site)
            jac = np.vstack([self._jacp[:, self.arm_dofs], self._jacr[:, self.arm_dofs]])
            jjt = jac @ jac.T
            dq = jac.T @ np.linalg.solve(jjt + lam2 * np.eye(6), err)
            if self.rest is not None and cfg.null_gain > 0:
                null = np.eye(q.size) - np.linalg.pinv(jac) @ jac
                dq += cfg.null_gain * null @ (self.rest - q)
            biggest = np.abs(dq).max()
            if biggest > cfg.max_step:
                dq *= cfg.max_step / biggest
            q = np.clip(q + dq, self.lower, self.upper)
        return q, pos_err, rot_err
