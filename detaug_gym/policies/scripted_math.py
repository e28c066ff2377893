"""Small rotation and path helpers of the scripted expert (xyzw quaternions, axis-angle, min-jerk, Bezier)."""

from __future__ import annotations

import numpy as np


def quat_to_mat(quat_xyzw: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion in xyzw order."""
    x, y, z, w = np.asarray(quat_xyzw, dtype=np.float64) / max(np.linalg.norm(quat_xyzw), 1e-12)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def mat_to_rotvec(rot: np.ndarray) -> np.ndarray:
    """Axis-angle vector (axis * angle) of a rotation matrix."""
    cos = np.clip((np.trace(rot) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    vee = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    if angle < 1e-6:
        return 0.5 * vee
    if np.pi - angle < 1e-4:  # near pi: axis from the symmetric part
        axis = np.sqrt(np.maximum((np.diag(rot) + 1.0) / 2.0, 0.0))
        axis *= np.where(vee >= 0, 1.0, -1.0)
        return angle * axis / max(np.linalg.norm(axis), 1e-12)
    return angle * vee / (2.0 * np.sin(angle))


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def wrap_yaw(yaw: float, reference: float) -> float:
    """``yaw`` moved by multiples of pi (a parallel gripper is symmetric) to lie nearest ``reference``."""
    return float(reference + (yaw - reference + np.pi / 2) % np.pi - np.pi / 2)


def min_jerk(s: float) -> float:
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def bezier(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray, s: float) -> np.ndarray:
    """Quadratic Bezier through ``p0`` and ``p2`` pulled towards ``p1`` (a straight line when p1 is the midpoint)."""
    return (1 - s) ** 2 * p0 + 2 * (1 - s) * s * p1 + s * s * p2
