"""Where the obstacle goes: SafeLIBERO's two levels as a pure function of the scene and a generator.

Level 1 puts the obstacle close to the object the robot must pick. Level 2 puts it on the straight motion
path: the carry segment from the pick object to the place target when there is room for it there, else
the approach segment from the end effector's start to the pick object (SafeLIBERO's Spatial Level 2 does
this: the bowl sits right next to the plate, and the obstacle stands mid-table on the way to the bowl).
Where the obstacle is shorter than the height at which the path is travelled, it stands on a pedestal
(SafeLIBERO raises obstacles on a storage-box base).

Everything here is plain numpy on axis-aligned footprints, so the invariants (distance bands, path
intersection, no overlap) are tested over thousands of seeds without physics.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

# Pedestal half-extents (m): SafeLIBERO's base is 0.14 m tall (a storage box) and comes in a half-height
# version too. Ours is a narrower column (9 x 9 cm instead of ~13 x 12 cm) so that a raised obstacle still
# fits between the objects of LIBERO's cluttered scenes; obstacles overhang it slightly but stand stably.
PEDESTALS: dict[str, np.ndarray] = {
    "half": np.array([0.045, 0.045, 0.035]),
    "full": np.array([0.045, 0.045, 0.07]),
}
# Upper end of the eef height above the support at which the scripted expert carries objects (grasp
# ~0.03 m + lift 0.12 +- 0.03 m, more over tall targets); a Level 2 obstacle must reach this high, minus
# the held object's height, to block the straight path, so short obstacles stand on a pedestal.
TRANSIT_HEIGHT = 0.22
L1_GAP = (0.03, 0.10)  # footprint gap between obstacle and pick object at Level 1 (m)
L2_PATH_FRACTION = (0.3, 0.7)  # where along its path segment the Level 2 obstacle stands
L2_LATERAL = 0.02  # lateral jitter off the segment at Level 2 (m), SafeLIBERO's 0-2 cm
HAND_CLEARANCE = 0.08  # vertical clearance under the start pose of the hand (m)
MIN_GAP_TO_SCENE = 0.01  # clearance to every other object (m)
MIN_GAP_TO_INTERACTION = 0.03  # clearance to pick object and place target so grasp/release stay feasible


@dataclass(frozen=True)
class Footprint:
    """Axis-aligned box of a scene object in world xy, with its top height."""

    name: str
    lo: np.ndarray  # (2,)
    hi: np.ndarray  # (2,)
    top: float = 0.0

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (self.lo + self.hi)


@dataclass(frozen=True)
class PlacementProblem:
    """The scene as the placement sees it.

    Attributes:
        pick: footprint of the object to pick.
        place: footprint of the place target.
        others: footprints of every other object and fixture on the support.
        workspace_lo, workspace_hi: xy box the obstacle centre must stay in, shape ``(2,)``.
        start: xy of the end effector at the start of the episode, shape ``(2,)``.
        start_height: height of the end effector above the support at the start; an obstacle whose top
            comes within ``HAND_CLEARANCE`` of it must also keep out of the box around ``start``.
    """

    pick: Footprint
    place: Footprint
    others: tuple[Footprint, ...]
    workspace_lo: np.ndarray
    workspace_hi: np.ndarray
    start: np.ndarray
    start_height: float = 0.0
    removable: frozenset[str] = frozenset()
    """Names of ``others`` that an anchored placement may take off the table (SafeLIBERO removes distractors)."""

    def path_segments(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """The Level 2 candidate segments in order of preference: carry, then approach."""
        return [("carry", self.pick.center, self.place.center), ("approach", self.start, self.pick.center)]


@dataclass(frozen=True)
class Placement:
    """Result: obstacle centre ``xy``, ``yaw`` about z, and what it stands on: ``None`` (the support), a
    pedestal (``"half"``, ``"full"``; scenario version 0) or a base (``"box_base"``, ``"box_small_base"``;
    version 1)."""

    xy: np.ndarray
    yaw: float
    pedestal: str | None
    level: str
    relaxed: int = 0  # how many times the constraints had to be relaxed to find a spot
    segment: str = ""  # Level 2: "carry" or "approach"; "anchor" for a calibrated placement
    footprint: Footprint = field(default=None)  # type: ignore[assignment]
    problem: PlacementProblem | None = field(default=None, repr=False)  # the scene it was placed in
    removed: tuple[str, ...] = ()  # distractors an anchored placement takes off the table


def footprint_gap(a: Footprint, b: Footprint) -> float:
    """Distance between two axis-aligned xy boxes (0 when they touch or overlap; negative depth inside)."""
    sep = np.maximum(a.lo - b.hi, b.lo - a.hi)
    if np.all(sep <= 0):
        return float(sep.max())
    return float(np.linalg.norm(np.maximum(sep, 0.0)))


def rotated_half_extents(half: np.ndarray, yaw: float) -> np.ndarray:
    """xy half-extents of the axis-aligned box around a box of ``half`` (x, y) rotated by ``yaw``."""
    c, s = abs(np.cos(yaw)), abs(np.sin(yaw))
    return np.array([c * half[0] + s * half[1], s * half[0] + c * half[1]])


def choose_pedestal(obstacle_height: float, held_height: float = 0.05) -> str | None:
    """Smallest pedestal that lifts the obstacle's top into the carry path, or ``None`` if tall enough."""
    need = TRANSIT_HEIGHT - held_height
    if obstacle_height >= need:
        return None
    for name in ("half", "full"):
        if 2 * PEDESTALS[name][2] + obstacle_height >= need:
            return name
    return "full"


def place_obstacle(
    problem: PlacementProblem,
    half_extents: np.ndarray,
    level: str,
    rng: np.random.Generator,
    attempts: int = 400,
) -> Placement:
    """Sample a collision-free obstacle position for ``level`` ("L1" or "L2").

    Args:
        problem: the scene footprints.
        half_extents: obstacle half-extents in its own frame, shape ``(3,)`` (x, y, z).
        level: ``"L1"`` (near the pick object) or ``"L2"`` (on the pick -> place path).
        rng: the env's generator; the same state gives the same placement.
        attempts: samples per relaxation round.

    Returns:
        The placement. If no sample satisfies the constraints, they are relaxed in up to six rounds
        (recorded in ``Placement.relaxed``): wider stretch of the path, larger lateral offset (covering
        the path up to round 4, beside it by at most 10 cm in rounds 5-6), smaller clearance gaps. The
        Level 1 distance band is never relaxed. Failing all rounds, the least-overlapping sample is used
        (``relaxed == 7``).
    """
    if level not in ("L1", "L2"):
        raise ValueError(f"obstacle placement needs level 'L1' or 'L2', got {level!r}")
    half_extents = np.asarray(half_extents, dtype=np.float64)
    pedestal = choose_pedestal(2 * half_extents[2]) if level == "L2" else None
    top = 2 * half_extents[2] + (0.0 if pedestal is None else 2 * PEDESTALS[pedestal][2])
    problem = _keep_from_hand(problem, top)
    segments = problem.path_segments() if level == "L2" else [("", problem.pick.center, problem.pick.center)]
    # Relaxation rounds: (path fraction range, lateral offset bound, scale on the clearance gaps). The
    # lateral bound never exceeds the obstacle's half-width, so a Level 2 footprint always covers the path.
    half_width = float(np.min(half_extents[:2]))
    rounds = [(L2_PATH_FRACTION, L2_LATERAL, 1.0), ((0.15, 0.85), L2_LATERAL, 1.0),
              ((0.15, 0.85), half_width, 0.6), ((0.1, 0.9), half_width, 0.3), ((0.1, 0.9), half_width, 0.0),
              # Cluttered scenes (LIBERO-Goal): beside the path rather than inside another object.
              ((0.1, 0.9), half_width + 0.05, 0.3), ((0.1, 0.9), half_width + 0.1, 0.0)]
    best, best_score = None, -np.inf
    for relaxed, (fraction, lateral, scale) in enumerate(rounds):
        for name, a, b in segments:
            for _ in range(attempts):
                yaw = float(rng.uniform(-np.pi, np.pi))
                xy = _sample_centre(problem, half_extents, level, yaw, a, b, fraction, lateral, rng)
                fp = _obstacle_footprint(xy, half_extents, yaw, pedestal)
                if _valid(problem, fp, level, scale):
                    return Placement(xy, yaw, pedestal, level, relaxed, name, fp, problem)
                score = _least_gap(problem, fp)
                if score > best_score:
                    best, best_score = Placement(xy, yaw, pedestal, level, len(rounds), name, fp, problem), score
    # Scenes too cluttered for any valid spot (rare): the least-overlapping sample, marked fully relaxed.
    return best


# place_at_anchor's rounds: (jitter multiplier, direction freed about the pick object, largest factor on the
# spot's distance from it). The freed rounds keep roughly the spot's gap, then move out to 1.6 times its distance.
ANCHOR_ROUNDS = ((1.0, False, 1.0), (2.0, False, 1.0), (3.0, False, 1.0), (1.0, True, 1.0), (1.0, True, 1.6))
MIN_GAP_AT_ANCHOR = 0.005  # m, clearance of an anchored obstacle (with its base) to every object
HAND_CLEARANCE_AT_ANCHOR = 0.03  # m under the grip site at the start (SafeLIBERO's spots come closer than v0's)


def place_at_anchor(problem: PlacementProblem, half_extents: np.ndarray, base_half: np.ndarray | None,
                    anchor, level: str, rng: np.random.Generator, attempts: int = 200,
                    accept=None, on_place: bool = False) -> Placement:
    """Sample an obstacle position around a calibrated anchor (scenario version 1,
    :mod:`~detaug_gym.envs.calibration`).

    The centre is drawn at the anchor's spot on the pick -> place path of ``problem`` (``anchor.along`` of its
    length along it, ``anchor.lateral`` beside it), within the calibration's jitter along and across, with a
    uniform yaw; the base (``base_half``, half-extents ``(3,)``, or None) stands under it with the same centre and
    yaw. A sample is valid inside the workspace box, at least :data:`MIN_GAP_AT_ANCHOR` from every object, pick
    and place target included (and from the hand's start when the obstacle's top comes within
    :data:`HAND_CLEARANCE_AT_ANCHOR` of it), and where ``accept(footprint)`` (when given; the env checks that the
    support under it is flat) says so. Distractors named in ``problem.removable`` do not block a spot: those it
    would touch are listed in ``Placement.removed`` and the env takes them off the table, as SafeLIBERO's scenes
    leave distractors out. Without a valid sample the jitter widens (:data:`ANCHOR_ROUNDS`, recorded in
    ``Placement.relaxed``), then the spot turns about the pick object at its distance, then farther; failing
    all rounds, the
    least-overlapping sample is used (``relaxed == len(ANCHOR_ROUNDS)``), one that ``accept`` passes if any does.

    Args:
        problem: the scene footprints (``pick`` and ``place`` of the task's first pick-place step).
        half_extents: obstacle half-extents in its own upright frame, ``(3,)``.
        base_half: the base's half-extents ``(3,)``, or None.
        anchor: a :class:`~detaug_gym.envs.calibration.Anchor` (its ``along``, ``lateral`` and ``base``).
        level: ``"L1"`` or ``"L2"`` (recorded).
        rng: the env's generator; the same state gives the same placement.
        attempts: samples per round.
        accept: ``footprint -> bool``, an extra check of the scene (or None).
        on_place: the place target is a region on a fixture the obstacle may stand on (SafeLIBERO puts a mug on
            the cabinet's top beside the region the bowl goes to): no clearance to ``problem.place`` is asked, and
            ``accept`` must check that the obstacle stands wholly on its top where it overlaps it.
    """
    from detaug_gym.envs.calibration import JITTER

    half_extents = np.asarray(half_extents, dtype=np.float64)
    top = 2 * half_extents[2] + (0.0 if base_half is None else 2 * float(base_half[2]))
    problem = _keep_from_hand(problem, top, HAND_CLEARANCE_AT_ANCHOR)
    axis = problem.place.center - problem.pick.center
    unit = axis / max(float(np.linalg.norm(axis)), 1e-9)
    normal = np.array([-unit[1], unit[0]])
    spot = anchor.along * axis + anchor.lateral * normal  # relative to the pick object's centre
    fixed = (*(o for o in problem.others if o.name not in problem.removable), problem.pick,
             *(() if on_place else (problem.place,)))
    removable = [o for o in problem.others if o.name in problem.removable]
    best, best_score = None, (False, -np.inf)  # (accepted, least gap) of the fallback
    for relaxed, (widen, free, farther) in enumerate(ANCHOR_ROUNDS):
        for _ in range(attempts):
            if free:  # about the pick object, at (up to ``farther`` times) the spot's distance
                turn = rng.uniform(-np.pi, np.pi)
                rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
                rel = rng.uniform(1.0, farther) * (rot @ spot)
            else:
                rel = spot + widen * JITTER * (rng.uniform(-1, 1) * unit + rng.uniform(-1, 1) * normal)
            yaw = float(rng.uniform(-np.pi, np.pi))
            xy = problem.pick.center + rel
            fp = _obstacle_footprint(xy, half_extents, yaw, None, base_half)
            inside = np.all(xy >= problem.workspace_lo) and np.all(xy <= problem.workspace_hi)
            score = min(footprint_gap(fp, other) for other in fixed) if inside else -1.0
            removed = tuple(o.name for o in removable if footprint_gap(fp, o) < MIN_GAP_AT_ANCHOR)
            if score >= MIN_GAP_AT_ANCHOR and (accept is None or accept(fp)):
                return Placement(xy, yaw, anchor.base, level, relaxed, "anchor", fp, problem, removed)
            # The fallback: the least-overlapping sample, among those ``accept`` passes when there are any.
            if score > best_score[1] or not best_score[0]:
                candidate = (accept is None or accept(fp), score)
                if candidate > best_score:
                    best = Placement(xy, yaw, anchor.base, level, len(ANCHOR_ROUNDS), "anchor", fp, problem,
                                     removed)
                    best_score = candidate
    return best


def _keep_from_hand(problem: PlacementProblem, top: float, clearance: float = HAND_CLEARANCE) -> PlacementProblem:
    """``problem`` with the box around the hand's start among the objects to avoid when an obstacle of this
    ``top`` (above the support) would come within ``clearance`` of the hand's grip site."""
    if top + clearance <= problem.start_height:
        return problem
    hand = Footprint("robot_hand", problem.start - 0.05, problem.start + 0.05)
    return replace(problem, others=(*problem.others, hand))


def _obstacle_footprint(xy: np.ndarray, half: np.ndarray, yaw: float, pedestal: str | None,
                        base_half: np.ndarray | None = None) -> Footprint:
    ext = rotated_half_extents(half[:2], yaw)
    if pedestal is not None:
        ext = np.maximum(ext, rotated_half_extents(PEDESTALS[pedestal][:2], yaw))
    if base_half is not None:
        ext = np.maximum(ext, rotated_half_extents(np.asarray(base_half)[:2], yaw))
    return Footprint("obstacle", xy - ext, xy + ext)


def _sample_centre(problem: PlacementProblem, half: np.ndarray, level: str, yaw: float, a: np.ndarray,
                   b: np.ndarray, fraction: tuple[float, float], lateral: float,
                   rng: np.random.Generator) -> np.ndarray:
    pick_c = problem.pick.center
    if level == "L1":
        # Aim at a footprint gap in the L1 band along a random direction from the pick object.
        direction = rng.uniform(-np.pi, np.pi)
        unit = np.array([np.cos(direction), np.sin(direction)])
        reach = np.abs(unit) @ (0.5 * (problem.pick.hi - problem.pick.lo))
        reach += np.abs(unit) @ rotated_half_extents(half[:2], yaw)
        return pick_c + unit * (reach + rng.uniform(*L1_GAP))
    seg = b - a
    u = rng.uniform(*fraction)
    normal = np.array([-seg[1], seg[0]]) / max(np.linalg.norm(seg), 1e-9)
    return a + u * seg + normal * rng.uniform(-lateral, lateral)


def _valid(problem: PlacementProblem, fp: Footprint, level: str, scale: float) -> bool:
    centre = fp.center
    if np.any(centre < problem.workspace_lo) or np.any(centre > problem.workspace_hi):
        return False
    gap_pick = footprint_gap(fp, problem.pick)
    gap_place = footprint_gap(fp, problem.place)
    if level == "L1" and not (L1_GAP[0] - 1e-9 <= gap_pick <= L1_GAP[1] + 1e-9):
        return False
    if min(gap_pick, gap_place) < MIN_GAP_TO_INTERACTION * max(scale, 0.3):
        return False
    return all(footprint_gap(fp, other) >= MIN_GAP_TO_SCENE * scale for other in problem.others)


def _least_gap(problem: PlacementProblem, fp: Footprint) -> float:
    """The smallest clearance of ``fp`` to anything it must avoid (negative when overlapping)."""
    gaps = [footprint_gap(fp, other) for other in problem.others]
    gaps += [footprint_gap(fp, problem.pick), footprint_gap(fp, problem.place)]
    if np.any(fp.center < problem.workspace_lo) or np.any(fp.center > problem.workspace_hi):
        gaps.append(-1.0)
    return min(gaps)


def distance_to_segment(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Euclidean distance from ``point`` to the segment ``a``-``b`` in the plane."""
    ab = b - a
    t = float(np.clip((point - a) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(point - (a + t * ab)))
