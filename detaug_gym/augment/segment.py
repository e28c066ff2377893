"""Split a demonstration into interaction windows and transit phases from its gripper command.

Frames are the demo's timesteps ``0..T-1`` (``obs[t]`` is seen before ``actions[t]``); a transit ``[start,
end]`` is the motion from the pose at frame ``start`` to the pose at frame ``end``, driven by actions
``start..end-1``, which is what an arc replaces.

Rules (times in control steps, 20 Hz; defaults in :class:`SegmentConfig`):

- The command is *closed* where it is > 0. A **grasp** is a run of closed frames at least ``min_closed``
  long (shorter blips are ignored); its **close** transition is the run's first frame, its **release** the
  first open frame after it (none when the demo ends holding, as a Spatial demo does when the success
  check fires with the bowl still in the hand).
- An **interaction window** spans ``window`` steps on both sides of a transition, and ``margin`` more steps
  are kept unchanged on both sides of it. A demo that ends holding treats its last frame as the release:
  the final placement stays intact.
- Per grasp ``k``: **approach** from frame 0 (or the previous release's window + margin) to the close
  transition's window - margin; **carry** from the close window + margin to the release window - margin.
  Transits shorter than ``min_steps`` steps are left unbent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detaug_gym.actions import CONTROL_DT

PHASES = ("approach", "grasp", "carry", "release", "retreat")


@dataclass(frozen=True)
class SegmentConfig:
    """How demos are cut.

    Attributes:
        margin_s: time kept unchanged on both sides of each interaction window (paper: 0.4 s).
        window_s: half-width of the interaction window around a gripper transition.
        min_closed: frames the gripper must stay closed to count as a grasp.
        min_steps: shortest transit (steps) worth bending.
        dt: seconds per control step.
    """

    margin_s: float = 0.4
    window_s: float = 0.25
    min_closed: int = 5
    min_steps: int = 4
    dt: float = CONTROL_DT

    @property
    def margin(self) -> int:
        return int(round(self.margin_s / self.dt))

    @property
    def window(self) -> int:
        return int(round(self.window_s / self.dt))


@dataclass(frozen=True)
class Transit:
    """One transit phase: ``kind`` is ``"approach"`` or ``"carry"``; frames ``start < end``."""

    kind: str
    grasp: int
    start: int
    end: int

    @property
    def steps(self) -> int:
        return self.end - self.start


@dataclass(frozen=True)
class Grasp:
    """A grasp: ``close`` is its first closed frame, ``release`` the first open frame after (None: held to the end)."""

    close: int
    release: int | None


@dataclass(frozen=True)
class Segmentation:
    """Everything the augmentation needs to know about a demo's structure.

    Attributes:
        n_frames: demo length T.
        grasps: in time order.
        windows: interaction windows ``(first, last)`` frame, inclusive, clipped to the demo.
        transits: per grasp, approach then carry, where long enough; slot ``2k`` / ``2k+1`` in the label.
    """

    n_frames: int
    grasps: tuple[Grasp, ...]
    windows: tuple[tuple[int, int], ...]
    transits: tuple[Transit, ...]

    def transit(self, grasp: int, kind: str) -> Transit | None:
        for t in self.transits:
            if t.grasp == grasp and t.kind == kind:
                return t
        return None

    def phase(self, frame: int) -> str:
        """What the motion is doing at ``frame``, one of :data:`PHASES`: ``"grasp"`` / ``"release"`` inside the
        interaction window of a grasp's close / release, ``"approach"`` before a close window, ``"carry"``
        between a grasp's two windows, ``"retreat"`` after the last release window."""
        for k in range(len(self.grasps)):
            (close_lo, close_hi), (release_lo, release_hi) = self.windows[2 * k], self.windows[2 * k + 1]
            if frame < close_lo:
                return "approach"
            if frame <= close_hi:
                return "grasp"
            if frame < release_lo:
                return "carry"
            if frame <= release_hi:
                return "release"
        return "retreat" if self.grasps else "approach"

    def frozen_mask(self) -> np.ndarray:
        """(T,) True at frames no transit replaces (windows, margins, anything outside transits)."""
        mask = np.ones(self.n_frames, dtype=bool)
        for t in self.transits:
            mask[t.start + 1:t.end] = False
        return mask


def closed_runs(command: np.ndarray, min_closed: int) -> list[tuple[int, int]]:
    """``(first, last)`` frames of the runs where ``command > 0`` lasting at least ``min_closed`` frames."""
    closed = np.asarray(command, dtype=np.float64).ravel() > 0.0
    edges = np.diff(np.concatenate([[0], closed.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(a), int(b) - 1) for a, b in zip(starts, stops) if b - a >= min_closed]


def segment_gripper(command: np.ndarray, config: SegmentConfig | None = None) -> Segmentation:
    """Interaction windows and transits of a demo from its gripper command ``(T,)`` (see module docstring)."""
    cfg = config or SegmentConfig()
    command = np.asarray(command, dtype=np.float64).ravel()
    n = int(command.size)
    w, m = cfg.window, cfg.margin
    grasps = []
    for first, last in closed_runs(command, cfg.min_closed):
        grasps.append(Grasp(first, last + 1 if last + 1 < n else None))
    windows: list[tuple[int, int]] = []
    transits: list[Transit] = []
    free_from = 0  # first frame after the previous release's window + margin
    for k, g in enumerate(grasps):
        windows.append((max(g.close - w, 0), min(g.close + w, n - 1)))
        release = g.release if g.release is not None else n - 1
        windows.append((max(release - w, 0), min(release + w, n - 1)))
        _add(transits, Transit("approach", k, free_from, g.close - w - m), cfg.min_steps)
        _add(transits, Transit("carry", k, g.close + w + m, release - w - m), cfg.min_steps)
        free_from = release + w + m
    return Segmentation(n, tuple(grasps), tuple(windows), tuple(transits))


def _add(transits: list[Transit], transit: Transit, min_steps: int) -> None:
    if transit.start >= 0 and transit.steps >= min_steps:
        transits.append(transit)
