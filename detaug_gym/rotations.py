"""Rotation conventions of the package, one implementation each: quaternions, rotation vectors, matrices.

Quaternions are **xyzw** (scalar last) everywhere the package speaks (observations ``eef_quat``,
``object_poses[..., 3:7]``, ``obstacle_pose[3:7]``, plan targets); MuJoCo's model and qpos quaternions are
**wxyz** (scalar first) and are converted at the boundary with the ``*_wxyz`` functions. Matrices are
``(3, 3)`` with the rotated frame's axes as columns; rotation vectors are ``axis * angle`` (rad), in the
world frame.

Everything is float64 numpy. :func:`quat_xyzw_to_mat` is vectorised over leading axes (the training
features convert whole demos at once); the matrix -> quaternion / rotation vector conversions go through
MuJoCo's ``mju_mat2Quat`` / ``mju_quat2Vel`` (robust at every angle) and loop over leading axes.
"""

from __future__ import annotations

import mujoco
import numpy as np

_MIN_NORM = 1e-12  # below this a quaternion counts as zero (masked slots): it maps to the identity


def quat_xyzw_to_mat(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of xyzw quaternions ``(..., 4)``, normalised first.

    A zero quaternion (an empty observation slot) gives the identity instead of NaNs. Agrees with MuJoCo's
    ``mju_quat2Mat`` to ~1e-15 (the diagonal is written ``1 - 2 (y^2 + z^2)``, MuJoCo's ``w^2 + x^2 - ...``).
    """
    q = np.asarray(quat, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), _MIN_NORM)
    x, y, z, w = np.moveaxis(q, -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def quat_wxyz_to_mat(quat: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of MuJoCo (wxyz) quaternions ``(..., 4)``; see :func:`quat_xyzw_to_mat`."""
    return quat_xyzw_to_mat(np.asarray(quat, dtype=np.float64)[..., [1, 2, 3, 0]])


def mat_to_quat_wxyz(mat: np.ndarray) -> np.ndarray:
    """MuJoCo (wxyz) unit quaternions ``(..., 4)`` of rotation matrices ``(..., 3, 3)`` (``mju_mat2Quat``)."""
    mats = np.asarray(mat, dtype=np.float64)
    flat = mats.reshape(-1, 9)
    out = np.zeros((len(flat), 4))
    for row, m in zip(out, flat):
        mujoco.mju_mat2Quat(row, m)
    return out.reshape(*mats.shape[:-2], 4)


def mat_to_quat_xyzw(mat: np.ndarray) -> np.ndarray:
    """xyzw unit quaternions ``(..., 4)`` of rotation matrices ``(..., 3, 3)``."""
    return mat_to_quat_wxyz(mat)[..., [1, 2, 3, 0]]


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix ``(3, 3)`` of ``v`` ``(3,)``: ``skew(v) @ u == np.cross(v, u)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotvec_to_mat(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix ``(3, 3)`` of a rotation vector ``(3,)`` (axis * angle, rad), by Rodrigues' formula."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.eye(3)
    k = skew(rotvec / angle)
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * k @ k


def mat_to_rotvec(mat: np.ndarray) -> np.ndarray:
    """Rotation vector ``(3,)`` (axis * angle, angle in [0, pi]) of a rotation matrix ``(3, 3)``."""
    quat = mat_to_quat_wxyz(mat)
    vel = np.zeros(3)
    mujoco.mju_quat2Vel(vel, quat, 1.0)
    return vel


def rotation_error(target_rot: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """Rotation vector ``(3,)`` of ``target_rot @ rot.T``: the world-frame rotation taking ``rot`` onto
    ``target_rot`` (both ``(3, 3)``)."""
    return mat_to_rotvec(np.asarray(target_rot, dtype=np.float64) @ np.asarray(rot, dtype=np.float64).T)


def slerp(q0: np.ndarray, q1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Spherical interpolation of quaternions ``q0``, ``q1`` ``(4,)`` (either order convention, normalised
    first, the short way round) at fractions ``u`` ``(N,)``: unit quaternions ``(N, 4)``."""
    q0 = np.asarray(q0, dtype=np.float64) / np.linalg.norm(q0)
    q1 = np.asarray(q1, dtype=np.float64) / np.linalg.norm(q1)
    u = np.atleast_1d(np.asarray(u, dtype=np.float64))
    dot = float(q0 @ q1)
    if dot < 0.0:  # q and -q are the same rotation; take the short way round
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: normalised lerp is exact to rounding and avoids 0/0
        out = q0 + u[:, None] * (q1 - q0)
    else:
        omega = np.arccos(dot)
        out = (np.sin((1.0 - u) * omega)[:, None] * q0 + np.sin(u * omega)[:, None] * q1) / np.sin(omega)
    return out / np.linalg.norm(out, axis=1, keepdims=True)
