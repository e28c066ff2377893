"""Small rotation and path helpers of the scripted expert (elementary rotations, yaw wrapping, min-jerk, Bezier)."""

from __future__ import annotations

import numpy as np


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
