"""Circular detour arcs, their labels, timing and orientation interpolation (pure numpy).

An arc replaces a transit's end-effector path between ``p0`` and ``p1``: a circular arc through both
points with half-angle ``phi`` (the arc subtends ``2 phi`` at its centre; ``phi -> 0`` is the straight
chord, ``phi = pi / 2`` a half circle, larger values bulge past the endpoints) whose plane is rotated by
``theta`` about the chord. The bulge direction is

    b(theta) = cos(theta) * e_side + sin(theta) * e_up,

with ``e_up`` world +z made perpendicular to the chord and ``e_side = e_up x d`` (``d`` the chord's unit
direction), so ``theta in [0, pi]`` sweeps from one side over the top to the other side and never into
the table. ``arc_label(phi, theta) = phi * (cos theta, sin theta)`` is zero only for an unbent transit.

Duration rule (:func:`arc_steps`): an arc keeps the source transit's mean speed, so its number of control
steps is ``round(n_source * arc_length / source_path_length)``, but never plans a peak speed above what
robosuite's OSC can follow (``max_speed``, m per step; with actions clipped to 1 per axis the controller's
steady speed is about 1.5 cm per step along an axis). Progress along the arc follows a smooth trapezoid
by default (:func:`smooth_trapezoid`: smoothstep speed ramps over ``ramp`` of the time at each end, constant
speed between, zero speed and acceleration at both ends, peak = mean / (1 - ramp)), or a minimum-jerk
profile (peak = 1.875 x mean), or the source's own timing.
"""

from __future__ import annotations

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])


def arc_frame(p0: np.ndarray, p1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit chord direction ``d`` and the two bulge axes ``(e_side, e_up)``, all perpendicular.

    For a (near) vertical chord, "up" is undefined; world +x stands in for it so the frame stays defined.
    """
    chord = np.asarray(p1, dtype=np.float64) - np.asarray(p0, dtype=np.float64)
    length = float(np.linalg.norm(chord))
    if length < 1e-12:
        raise ValueError("an arc needs two distinct endpoints")
    d = chord / length
    up = WORLD_UP - d * (d @ WORLD_UP)
    if np.linalg.norm(up) < 1e-6:
        ref = np.array([1.0, 0.0, 0.0])
        up = ref - d * (d @ ref)
    e_up = up / np.linalg.norm(up)
    e_side = np.cross(e_up, d)
    return d, e_side, e_up


def bulge_direction(p0: np.ndarray, p1: np.ndarray, theta: float) -> np.ndarray:
    """Unit vector, perpendicular to the chord, towards which the arc of plane rotation ``theta`` bulges."""
    _, e_side, e_up = arc_frame(p0, p1)
    return np.cos(theta) * e_side + np.sin(theta) * e_up


def arc_points(p0: np.ndarray, p1: np.ndarray, phi: float, theta: float, s: np.ndarray) -> np.ndarray:
    """Points at arc-length fractions ``s`` (N,) in [0, 1] of the arc from ``p0`` to ``p1``; (N, 3).

    With ``alpha = (2 s - 1) phi`` the point is ``m + c/2 * [sin(alpha) d + (cos(alpha) - cos(phi)) b] /
    sin(phi)`` (``m`` the chord midpoint, ``c`` its length), which is uniform in arc length and tends to the
    straight chord ``p0 + s (p1 - p0)`` as ``phi -> 0``; ``s = 0`` and ``s = 1`` give the endpoints exactly.
    """
    p0 = np.asarray(p0, dtype=np.float64)
    p1 = np.asarray(p1, dtype=np.float64)
    s = np.atleast_1d(np.asarray(s, dtype=np.float64))
    line = p0 + s[:, None] * (p1 - p0)
    if abs(phi) < 1e-9:
        out = line
    else:
        d, _, _ = arc_frame(p0, p1)
        b = bulge_direction(p0, p1, theta)
        half = 0.5 * float(np.linalg.norm(p1 - p0))
        alpha = (2.0 * s - 1.0) * phi
        along = half * (np.sin(alpha) / np.sin(phi) - (2.0 * s - 1.0))  # deviation from the straight line
        side = half * (np.cos(alpha) - np.cos(phi)) / np.sin(phi)
        out = line + along[:, None] * d + side[:, None] * b
    out[s == 0.0] = p0
    out[s == 1.0] = p1
    return out


def arc_length(chord: float, phi: float) -> float:
    """Length of the arc of half-angle ``phi`` over a chord of length ``chord``: ``chord * phi / sin(phi)``."""
    return float(chord) if abs(phi) < 1e-9 else float(chord * phi / np.sin(phi))


def arc_label(phi: float, theta: float) -> np.ndarray:
    """The paper's 2-D arc label ``phi * (cos theta, sin theta)``; zero for an unbent transit (phi = 0)."""
    return np.array([phi * np.cos(theta), phi * np.sin(theta)])


def label_to_arc(label: np.ndarray) -> tuple[float, float]:
    """Inverse of :func:`arc_label` for ``theta in [0, pi]``: ``(phi, theta)``."""
    x, y = float(label[0]), float(label[1])
    phi = float(np.hypot(x, y))
    return phi, (float(np.arctan2(y, x)) if phi > 0 else 0.0)


def min_jerk(u: np.ndarray) -> np.ndarray:
    """Minimum-jerk progress ``10u^3 - 15u^4 + 6u^5``: 0 -> 1 with zero speed and acceleration at both ends."""
    u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
    return u ** 3 * (10.0 - 15.0 * u + 6.0 * u * u)


def smooth_trapezoid(u: np.ndarray, ramp: float = 0.3) -> np.ndarray:
    """Progress 0 -> 1 whose speed rises by a smoothstep over the first ``ramp`` of the time, stays
    constant, and falls symmetrically; peak speed is ``1 / (1 - ramp)`` times the mean."""
    u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
    if ramp <= 0.0:
        return u
    r = min(float(ramp), 0.5)

    def ramp_area(x):  # integral of smoothstep(x / r) from 0 to x, for 0 <= x <= r
        y = np.clip(x / r, 0.0, 1.0)
        return r * (y ** 3 - 0.5 * y ** 4)

    total = 1.0 - r  # area under the whole speed profile (peak 1)
    head = ramp_area(np.minimum(u, r))
    middle = np.clip(u - r, 0.0, 1.0 - 2 * r)
    tail = 0.5 * r - ramp_area(np.clip(1.0 - u, 0.0, r))
    tail = np.where(u > 1.0 - r, tail, 0.0)
    return (head + middle + tail) / total


def peak_factor(timing: str, ramp: float = 0.3) -> float:
    """Peak speed over mean speed of a timing profile (the source's own is taken as min-jerk's)."""
    return 1.0 / (1.0 - min(ramp, 0.5)) if timing == "trapezoid" else 1.875


def source_profile(path: np.ndarray, n_steps: int) -> np.ndarray:
    """The source's own timing: its cumulative path-length fraction, resampled at ``n_steps + 1`` instants."""
    seg = np.linalg.norm(np.diff(np.asarray(path, dtype=np.float64), axis=0), axis=1)
    total = seg.sum()
    if total < 1e-9:
        return min_jerk(np.linspace(0.0, 1.0, n_steps + 1))
    cum = np.concatenate([[0.0], np.cumsum(seg)]) / total
    grid = np.linspace(0.0, 1.0, len(cum))
    return np.interp(np.linspace(0.0, 1.0, n_steps + 1), grid, cum)


def arc_steps(n_source: int, source_length: float, new_length: float, max_speed: float = np.inf,
              peak: float = 1.875, min_steps: int = 2) -> int:
    """Control steps for a replaced transit: the source's mean speed, capped so that the profile's peak
    (``peak`` x mean) stays below ``max_speed`` (m per step); see the module docstring."""
    keep_speed = n_source if source_length < 1e-9 else int(round(n_source * new_length / source_length))
    controller_cap = int(np.ceil(peak * new_length / max_speed - 1e-9)) if np.isfinite(max_speed) else 0
    return max(keep_speed, controller_cap, min_steps)


def sample_arc(rng: np.random.Generator, phi_range: tuple[float, float],
               theta_range: tuple[float, float]) -> tuple[float, float]:
    """One ``(phi, theta)`` drawn uniformly from the given ranges (radians)."""
    return float(rng.uniform(*phi_range)), float(rng.uniform(*theta_range))
