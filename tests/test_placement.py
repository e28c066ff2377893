"""Obstacle placement invariants over many seeds, on the pure placement function (no physics)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from detaug_gym.envs.placement import (
    L1_GAP,
    L2_LATERAL,
    TRANSIT_HEIGHT,
    Footprint,
    PlacementProblem,
    choose_pedestal,
    distance_to_segment,
    footprint_gap,
    place_obstacle,
)


def _box(name, cx, cy, hx, hy):
    c = np.array([cx, cy])
    h = np.array([hx, hy])
    return Footprint(name, c - h, c + h)


def _problem(pick_xy=(-0.05, 0.2), place_xy=(0.1, -0.15)):
    pick = _box("bowl", *pick_xy, 0.05, 0.05)
    place = _box("plate", *place_xy, 0.07, 0.07)
    others = (_box("ramekin", -0.2, 0.25, 0.04, 0.04), _box("cabinet", 0.05, -0.38, 0.15, 0.1),
              _box("stove", -0.32, -0.15, 0.12, 0.09))
    return PlacementProblem(pick, place, others, np.array([-0.35, -0.3]), np.array([0.3, 0.4]),
                            np.array([-0.2, 0.0]))


HALF = np.array([0.04, 0.04, 0.08])


@pytest.mark.parametrize("level", ["L1", "L2"])
def test_placements_never_overlap_scene_objects(level):
    problem = _problem()
    for seed in range(300):
        p = place_obstacle(problem, HALF, level, np.random.default_rng(seed))
        assert p.relaxed == 0
        for other in problem.others:
            assert footprint_gap(p.footprint, other) >= 0.01 - 1e-9, (seed, other.name)
        assert footprint_gap(p.footprint, problem.place) > 0.0
        assert np.all(p.xy >= problem.workspace_lo) and np.all(p.xy <= problem.workspace_hi)


def test_level1_within_distance_band_of_pick_object():
    problem = _problem()
    for seed in range(300):
        p = place_obstacle(problem, HALF, "L1", np.random.default_rng(seed))
        gap = footprint_gap(p.footprint, problem.pick)
        assert L1_GAP[0] - 1e-9 <= gap <= L1_GAP[1] + 1e-9
        assert p.pedestal is None


def test_level2_intersects_the_motion_path():
    problem = _problem()
    segments = {name: (a, b) for name, a, b in problem.path_segments()}
    for seed in range(300):
        p = place_obstacle(problem, HALF, "L2", np.random.default_rng(seed))
        a, b = segments[p.segment]
        # The centre lies within the lateral jitter of the segment, and the footprint covers the segment.
        assert p.relaxed < 5  # this scene has room on the path itself
        lateral = L2_LATERAL if p.relaxed < 2 else HALF[:2].min()
        assert distance_to_segment(p.xy, a, b) <= lateral + 1e-9
        t = np.linspace(0, 1, 200)[:, None]
        on_path = a + t * (b - a)
        inside = np.all((on_path >= p.footprint.lo) & (on_path <= p.footprint.hi), axis=1)
        assert inside.any()


def test_level2_prefers_carry_and_falls_back_to_approach_when_pick_and_place_touch():
    far = _problem()
    assert place_obstacle(far, HALF, "L2", np.random.default_rng(0)).segment == "carry"
    touching = _problem(pick_xy=(-0.05, 0.2), place_xy=(0.06, 0.2))
    assert place_obstacle(touching, HALF, "L2", np.random.default_rng(0)).segment == "approach"


def test_same_generator_state_gives_same_placement():
    problem = _problem()
    a = place_obstacle(problem, HALF, "L2", np.random.default_rng(42))
    b = place_obstacle(problem, HALF, "L2", np.random.default_rng(42))
    assert np.array_equal(a.xy, b.xy) and a.yaw == b.yaw and a.pedestal == b.pedestal


@settings(max_examples=60, deadline=None)
@given(height=st.floats(0.02, 0.4))
def test_pedestal_lifts_short_obstacles_into_the_path(height):
    need = TRANSIT_HEIGHT - 0.05  # the default held-object height
    pedestal = choose_pedestal(height)
    top = height + {None: 0.0, "half": 0.07, "full": 0.14}[pedestal]
    if pedestal is None:
        assert height >= need - 1e-9
    else:
        assert top >= need - 1e-9 or pedestal == "full"
        if pedestal == "full":
            assert height + 0.07 < need  # the half pedestal would not have been enough


def test_bad_level_is_rejected():
    with pytest.raises(ValueError, match="L1"):
        place_obstacle(_problem(), HALF, "L3", np.random.default_rng(0))
