"""An augmented demo before replay: which source steps are copied, and the arc targets that replace the rest.

The new timeline keeps the source's frames outside the bent transits (interaction windows, margins and
anything not assigned to a transit) and, for each bent transit ``[start, end]``, inserts ``n`` steps whose
end-effector targets follow the arc from the source pose at ``start`` to the source pose at ``end``
(position on the arc, orientation slerped between the two endpoint orientations, both with the same
progress profile). Copied steps reuse the source's actions bit for bit; transit steps get their actions
from the tracking controller at replay (:mod:`detaug_gym.augment.replay`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from detaug_gym.augment.arcs import (
    arc_length,
    arc_points,
    arc_steps,
    min_jerk,
    peak_factor,
    smooth_trapezoid,
    source_profile,
)
from detaug_gym.augment.segment import Transit
from detaug_gym.rotations import slerp


@dataclass(frozen=True)
class Timing:
    """How fast an arc is executed (see :mod:`detaug_gym.augment.arcs`).

    Attributes:
        profile: ``"trapezoid"`` (smooth trapezoid), ``"min_jerk"`` or ``"source"``.
        max_speed: planned peak speed cap (m per control step), what the OSC can follow.
        ramp: fraction of the time spent speeding up (and slowing down) in the trapezoid.
    """

    profile: str = "trapezoid"
    max_speed: float = 0.012
    ramp: float = 0.3


@dataclass(frozen=True)
class ArcSample:
    """The arc drawn for one transit (``phi = 0``: left unbent)."""

    transit: Transit
    phi: float
    theta: float


@dataclass
class BentSpan:
    """Where a bent transit lies in the new timeline: frames ``start..end`` (inclusive) are the arc."""

    sample: ArcSample
    start: int
    end: int
    arc_len: float
    chord: float


@dataclass
class Plan:
    """The augmented timeline.

    Attributes:
        source_step: (N,) index of the source action copied at each new step, -1 where the tracker acts.
        source_frame: (N,) source frame each new frame copies, -1 on arc interiors.
        target_pos: (N + 1, 3) grip-site targets per new frame (plus the pose after the last step).
        target_quat: (N + 1, 4) xyzw targets.
        gripper: (N,) gripper command per new step.
        spans: the bent transits.
    """

    source_step: np.ndarray
    source_frame: np.ndarray
    target_pos: np.ndarray
    target_quat: np.ndarray
    gripper: np.ndarray
    spans: list[BentSpan] = field(default_factory=list)

    @property
    def n_steps(self) -> int:
        return int(self.source_step.size)


def path_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


def transit_targets(pos: np.ndarray, quat: np.ndarray, transit: Transit, phi: float, theta: float,
                    timing: Timing = Timing()) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Arc targets for one transit of the source eef path ``pos`` (T, 3) / ``quat`` (T, 4, xyzw).

    Returns ``(positions (n + 1, 3), quats (n + 1, 4), arc length, chord length)``; row 0 and row n are the
    source poses at the transit's endpoints, exactly.
    """
    s, e = transit.start, transit.end
    p0, p1 = pos[s], pos[e]
    chord = float(np.linalg.norm(p1 - p0))
    src_len = path_length(pos[s:e + 1])
    new_len = arc_length(chord, phi)
    n = arc_steps(transit.steps, src_len, new_len, timing.max_speed, peak_factor(timing.profile, timing.ramp))
    u = np.linspace(0.0, 1.0, n + 1)
    if timing.profile == "trapezoid":
        progress = smooth_trapezoid(u, timing.ramp)
    elif timing.profile == "min_jerk":
        progress = min_jerk(u)
    elif timing.profile == "source":
        progress = source_profile(pos[s:e + 1], n)
    else:
        raise ValueError(f"unknown timing profile {timing.profile!r}; valid: trapezoid, min_jerk, source")
    points = arc_points(p0, p1, phi, theta, progress)
    quats = slerp(quat[s], quat[e], progress)
    quats[0], quats[-1] = quat[s], quat[e]
    return points, quats, new_len, chord


@dataclass
class Replacement:
    """New eef targets for one transit: ``points`` (n+1, 3) and ``quats`` (n+1, 4) from start to end pose."""

    sample: ArcSample
    points: np.ndarray
    quats: np.ndarray
    length: float
    chord: float


def build_plan(pos: np.ndarray, quat: np.ndarray, command: np.ndarray, samples: list[ArcSample],
               timing: Timing = Timing()) -> Plan:
    """Assemble the new timeline from the source eef path, its gripper command (T,) and the arc samples.

    Samples with ``phi == 0`` leave their transit as in the source.
    """
    replacements = []
    for sample in samples:
        if sample.phi != 0.0:
            points, quats, arc_len, chord = transit_targets(pos, quat, sample.transit, sample.phi, sample.theta,
                                                            timing)
            replacements.append(Replacement(sample, points, quats, arc_len, chord))
    return splice_transits(pos, quat, command, replacements)


def splice_transits(pos: np.ndarray, quat: np.ndarray, command: np.ndarray,
                    replacements: list[Replacement]) -> Plan:
    """The source timeline (eef ``pos`` (T, 3), ``quat`` (T, 4), gripper ``command`` (T,)) with each replaced
    transit's frames swapped for its new targets; every other frame is copied. Shared by DetAug's arcs and
    DemoGen's planned detours."""
    steps: list[np.ndarray] = []
    frames: list[np.ndarray] = []
    tpos: list[np.ndarray] = []
    tquat: list[np.ndarray] = []
    grip: list[np.ndarray] = []
    spans: list[BentSpan] = []
    cursor, length = 0, 0
    for rep in sorted(replacements, key=lambda r: r.sample.transit.start):
        tr = rep.sample.transit
        copied = np.arange(cursor, tr.start)
        steps.append(copied)
        frames.append(copied)
        tpos.append(pos[copied])
        tquat.append(quat[copied])
        grip.append(command[copied])
        length += copied.size
        n = len(rep.points) - 1
        steps.append(np.full(n, -1))
        frames.append(np.concatenate([[tr.start], np.full(n - 1, -1)]))
        tpos.append(rep.points[:-1])
        tquat.append(rep.quats[:-1])
        grip.append(np.full(n, command[tr.start]))
        spans.append(BentSpan(rep.sample, length, length + n, rep.length, rep.chord))
        length += n
        cursor = tr.end
    rest = np.arange(cursor, len(command))
    steps.append(rest)
    frames.append(rest)
    tpos.append(pos[rest])
    tquat.append(quat[rest])
    grip.append(command[rest])
    # the pose after the last step is unknown in the source; hold the last one
    tpos.append(pos[-1:])
    tquat.append(quat[-1:])
    return Plan(np.concatenate(steps).astype(np.int64), np.concatenate(frames).astype(np.int64),
                np.concatenate(tpos), np.concatenate(tquat), np.concatenate(grip).astype(np.float64), spans)

