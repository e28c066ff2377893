"""Scenario versions 1 and 2: procedural obstacles drawn around SafeLIBERO's own spots (calibration.py,
place_at_anchor), on the pure placement function and on real LIBERO scenes; version 2's scene edits."""

import gymnasium as gym
import numpy as np
import pytest

import detaug_gym  # noqa: F401
from detaug_gym.envs.calibration import ANCHORS, JITTER, Anchor, anchor_for, anchors_for, cell_types, scene_edit
from detaug_gym.envs.obstacles import BASES, OBSTACLE_SETS
from detaug_gym.envs.placement import (
    ANCHOR_ROUNDS,
    MIN_GAP_AT_ANCHOR,
    Footprint,
    PlacementProblem,
    footprint_gap,
    place_at_anchor,
)
from detaug_gym.envs.safe_libero import SafeLiberoEnv
from detaug_gym.envs.suites import SUITES


def _box(name, cx, cy, hx, hy, top=0.0):
    c, h = np.array([cx, cy]), np.array([hx, hy])
    return Footprint(name, c - h, c + h, top)


def _problem(removable=frozenset()):
    pick, place = _box("bowl", 0.0, 0.0, 0.04, 0.04), _box("plate", 0.4, 0.0, 0.06, 0.06)
    others = (_box("ramekin", 0.2, 0.02, 0.03, 0.03), _box("cabinet", 0.1, -0.35, 0.15, 0.1))
    return PlacementProblem(pick, place, others, np.array([-0.5, -0.5]), np.array([0.8, 0.5]),
                            np.array([-0.3, 0.3]), 0.3, removable)


HALF = np.array([0.03, 0.03, 0.08])
ON_PATH = Anchor(("milk",), None, 0.5, 0.0)  # half-way from the bowl (0, 0) to the plate (0.4, 0)


def test_every_anchor_names_types_and_bases_of_version_1_one_per_task():
    for (suite, level), anchors in ANCHORS.items():
        assert len(anchors) == len(SUITES[suite].tasks_for(level)), (suite, level)
        for a in anchors:
            assert set(a.types) <= set(OBSTACLE_SETS[1]) and a.base in (None, *BASES)
    assert cell_types("object", "L1") == ("wine_bottle",)  # SafeLIBERO's Object L1: always the enlarged bottle
    with pytest.raises(KeyError, match="cells with anchors: spatial L1"):
        anchor_for("newton", "L2", 0)


def test_anchored_spots_keep_their_place_on_the_path_and_their_clearance():
    problem = _problem()
    beside = Anchor(("milk",), None, 0.25, -0.12)  # a quarter of the way, 12 cm to the right of the path
    for anchor, spot in ((ON_PATH, (0.2, 0.0)), (beside, (0.1, -0.12))):
        for seed in range(100):
            p = place_at_anchor(problem, HALF, None, anchor, "L2", np.random.default_rng(seed))
            if p.relaxed == 0:
                assert np.all(np.abs(p.xy - spot) <= JITTER + 1e-9)
            if p.relaxed < len(ANCHOR_ROUNDS):
                for other in (*problem.others, problem.pick, problem.place):
                    assert footprint_gap(p.footprint, other) >= MIN_GAP_AT_ANCHOR - 1e-12


def test_a_base_widens_the_footprint_and_the_same_state_gives_the_same_spot():
    base = np.array([0.07, 0.06, 0.07])
    a = place_at_anchor(_problem(), HALF, base, ON_PATH, "L2", np.random.default_rng(3))
    b = place_at_anchor(_problem(), HALF, base, ON_PATH, "L2", np.random.default_rng(3))
    assert np.array_equal(a.xy, b.xy) and a.yaw == b.yaw
    assert np.all(a.footprint.hi - a.footprint.lo >= 2 * base[:2].min() - 1e-9)


def test_a_blocking_distractor_is_taken_off_the_table_only_when_removable():
    """The ramekin sits on the anchor's spot: fixed, the spot moves off it; removable, it is listed to go."""
    fixed = place_at_anchor(_problem(), HALF, None, ON_PATH, "L2", np.random.default_rng(0))
    assert fixed.removed == () and footprint_gap(fixed.footprint, _problem().others[0]) >= MIN_GAP_AT_ANCHOR
    removable = [place_at_anchor(_problem(frozenset({"ramekin"})), HALF, None, ON_PATH, "L2",
                                 np.random.default_rng(s)) for s in range(20)]
    assert any(p.removed == ("ramekin",) for p in removable)
    assert all(p.relaxed == 0 for p in removable)


def test_an_accept_check_that_refuses_everything_ends_in_the_marked_fallback():
    p = place_at_anchor(_problem(), HALF, None, ON_PATH, "L2", np.random.default_rng(0), attempts=5,
                        accept=lambda fp: False)
    assert p.relaxed == len(ANCHOR_ROUNDS)


@pytest.fixture(scope="module")
def spatial_l2_v1():
    env = gym.make("SafeLibero-Spatial-L2-v1", task=2)
    yield env
    env.close()


def test_v1_obstacles_stand_on_safelibero_bases_with_its_sizes_and_stay_still(spatial_l2_v1):
    env = spatial_l2_v1
    anchor = anchor_for("spatial", "L2", 2)
    seen = set()
    for seed in range(6):
        obs, info = env.reset(seed=seed)
        scene = env.unwrapped.scene
        assert info["obstacle"] in anchor.types and info["obstacle_raised"] and not info["collision"]
        seen.add(info["obstacle"])
        base = scene.bases["box_base"]
        obstacle = scene.data.xpos[scene.obstacles[info["obstacle"]].body_id]
        assert np.linalg.norm(scene.data.xpos[base.body_id][:2] - obstacle[:2]) < 0.05  # on its base
        for _ in range(3):
            obs, _, _, _, info = env.step(np.zeros(7))
        assert not info["collision"], f"seed {seed}: the obstacle moved with the robot at rest"
    heights = {k: 2 * h.half_extents[2] for k, h in env.unwrapped.scene.obstacles.items()}
    assert heights["wine_bottle"] == pytest.approx(1.6 * heights["wine_bottle_small"], rel=1e-3)
    assert heights["milk"] == pytest.approx(2.0 * heights["milk_small"], rel=1e-3)
    assert heights["white_storage_box"] < 0.125  # lying on its side (0.117 m), as SafeLIBERO's
    assert len(seen) > 1


def test_v0_ids_keep_the_old_generator_and_versions_are_checked():
    assert SUITES["spatial"].env_id("L2") == "SafeLibero-Spatial-L2-v2"
    assert SUITES["spatial"].env_id("L2", version=1) == "SafeLibero-Spatial-L2-v1"
    assert SUITES["spatial"].env_id("L2", version=0) == "SafeLibero-Spatial-L2-v0"
    assert SUITES["spatial"].env_id("Free", version=0) == SUITES["spatial"].env_id("Free")
    with pytest.raises(ValueError, match="its versions: 0, 1, 2"):
        SUITES["spatial"].env_id("L1", version=7)
    with pytest.raises(ValueError, match="unknown scenario version 7; valid: 0, 1, 2"):
        SafeLiberoEnv("spatial", "L1", version=7)
    env = gym.make("SafeLibero-Spatial-L2-v0", task=2)
    _, info = env.reset(seed=0)
    assert env.unwrapped.version == 0 and info["obstacle"] in OBSTACLE_SETS[0]
    assert env.unwrapped.episode.placement.pedestal in ("half", "full", None)
    assert not env.unwrapped.scene.bases
    env.close()


def test_the_bench_runs_v2_by_default_older_versions_on_request_and_official_under_one_id():
    from detaug_gym import bench

    def ids(**kw):
        cfg = bench.BenchConfig(methods=["scripted"], suites=["spatial"], levels=["1", "free"], episodes=1, **kw)
        return sorted({j.key.env_id for j in bench.plan_jobs(cfg.methods, cfg.suites, ["L1", "Free"], 1, 0, cfg=cfg)})

    assert ids() == ["SafeLibero-Spatial-Free-v0", "SafeLibero-Spatial-L1-v2"]
    assert ids(scenario_version=1) == ["SafeLibero-Spatial-Free-v0", "SafeLibero-Spatial-L1-v1"]
    assert ids(scenario_version=0) == ["SafeLibero-Spatial-Free-v0", "SafeLibero-Spatial-L1-v0"]
    assert "procedural -v0" in " ".join(bench.BenchConfig(scenario_version=0).notes())
    assert "before SafeLIBERO's scene edits" in " ".join(bench.BenchConfig(scenario_version=1).notes())
    # Official episodes do not depend on the procedural version: one id keeps their result folders resumable.
    official = bench.BenchConfig(methods=["scripted"], suites=["spatial"], levels=["1"], episodes=1,
                                 scenarios="official")
    assert {j.key.env_id for j in bench.plan_jobs(["scripted"], ["spatial"], ["L1"], 1, 0, cfg=official)} == {
        "SafeLibero-Spatial-L1-v1"}
    with pytest.raises(ValueError, match="unknown --scenario-version 3; valid: 0, 1, 2"):
        bench.BenchConfig(scenario_version=3)
    with pytest.raises(ValueError, match="--scenarios official has one"):
        bench.BenchConfig(scenario_version=0, scenarios="official")


def test_every_v2_task_has_weighted_per_type_anchors_and_a_scene_edit():
    for (suite, level) in ANCHORS:
        for task in range(len(SUITES[suite].tasks_for(level))):
            anchors = anchors_for(suite, level, task)
            assert anchors and all(len(a.types) == 1 and a.weight > 0 for a in anchors), (suite, level, task)
            assert {a.types[0] for a in anchors} <= set(OBSTACLE_SETS[2])
            assert all(a.base in (None, *BASES) for a in anchors)
            edit = scene_edit(suite, level, task)
            assert not set(edit.moved) & set(edit.removed)
    # SafeLIBERO hand-sets spots per type: Spatial L1 task 0's storage box stands on the other side of its moka pot.
    spots = {a.types[0]: a.along for a in anchors_for("spatial", "L1", 0)}
    assert spots["white_storage_box"] < 0 < spots["moka_pot"]
    assert cell_types("object", "L1", version=2) == ("wine_bottle",)
    assert scene_edit("goal", "L2", 2).fixtures["flat_stove_1"] == pytest.approx((-0.099, 0.206))  # stove moved
    with pytest.raises(KeyError, match="version 2"):
        anchors_for("newton", "L2", 0)


def _xy(env, name):
    scene = env.unwrapped.scene
    return scene.data.xpos[scene.body_id(name)][:2].copy()


def test_v2_moves_objects_and_fixtures_and_takes_distractors_off_as_safelibero_does():
    """Object L1 task 0: SafeLIBERO moves the orange juice 7 cm and leaves the bbq sauce and butter out; the same
    LIBERO init state under -v1 keeps LIBERO's layout."""
    edit = scene_edit("object", "L1", 0)
    assert edit.moved and set(edit.removed) == {"bbq_sauce_1", "butter_1"}
    v1, v2 = gym.make("SafeLibero-Object-L1-v1", task=0), gym.make("SafeLibero-Object-L1-v2", task=0)
    for state in (0, 7):
        v1.reset(seed=state, options={"init_state": state})
        _, info = v2.reset(seed=state, options={"init_state": state})
        for name, shift in edit.moved.items():
            assert np.allclose(_xy(v2, name) - _xy(v1, name), shift, atol=0.01), name
        for name in edit.removed:
            assert np.all(np.abs(_xy(v2, name)) > 1.0) and np.all(np.abs(_xy(v1, name)) < 0.5), name
        assert not info["collision"]
    v1.close()
    v2.close()
    stove = scene_edit("goal", "L2", 2).fixtures["flat_stove_1"]
    v1, v2 = gym.make("SafeLibero-Goal-L2-v1", task=2), gym.make("SafeLibero-Goal-L2-v2", task=2)
    for seed in range(2):  # the shift holds across resets (every reset restores the nominal body poses)
        v1.reset(seed=seed, options={"init_state": 3})
        v2.reset(seed=seed, options={"init_state": 3})
        assert np.allclose(_xy(v2, "flat_stove_1") - _xy(v1, "flat_stove_1"), stove, atol=1e-6)
    v1.close()
    v2.close()


def test_free_layouts_give_safelibero_edits_without_an_obstacle_and_replay_from_the_seed():
    """Goal task 2 (bowl on the stove) is offered at both levels with the stove moved 23 cm: a "mixed" Free env
    gives LIBERO's layout and both levels' edits, moves the stove only in edited episodes, and a restore from the
    seed gives the same layout; the obstacle levels refuse the option."""
    stove = scene_edit("goal", "L1", 2).fixtures["flat_stove_1"]
    plain = gym.make("SafeLibero-Goal-Free-v0", task=2).unwrapped
    mixed = gym.make("SafeLibero-Goal-Free-v0", task=2, layout="mixed").unwrapped
    plain.reset(seed=0, options={"init_state": 3})
    seen = set()
    for seed in range(16):
        mixed.reset(seed=seed, options={"init_state": 3})
        layout = mixed.episode_layout
        seen.add(layout)
        shift = (0.0, 0.0) if layout == "libero" else stove
        assert np.allclose(_xy(mixed, "flat_stove_1") - _xy(plain, "flat_stove_1"), shift, atol=1e-6), layout
        if layout != "libero":
            edit = scene_edit("goal", layout, 2)
            for name, moved in edit.moved.items():
                assert np.allclose(_xy(mixed, name) - _xy(plain, name), moved, atol=0.01), (layout, name)
            assert all(np.all(np.abs(_xy(mixed, name)) > 1.0) for name in edit.removed)
        state = mixed.scene.get_state()[1:].copy()
        mixed.restore({"task": 2, "init_state": 3, "seed": seed})
        assert mixed.episode_layout == layout and np.allclose(mixed.scene.get_state()[1:], state)
    assert seen == {"libero", "L1", "L2"}
    assert not mixed.scene.obstacles
    plain.close()
    mixed.close()
    with pytest.raises(ValueError, match="Free-level option"):
        SafeLiberoEnv("goal", "L1", layout="mixed")
    with pytest.raises(ValueError, match="valid: libero, safelibero, mixed"):
        SafeLiberoEnv("goal", "Free", layout="edited")


def test_v2_draws_the_anchor_of_the_asked_type():
    env = gym.make("SafeLibero-Spatial-L1-v2", task=0)
    problem_axis = []
    for kind in ("moka_pot", "white_storage_box"):
        _, info = env.reset(seed=0, options={"obstacle": kind})
        assert info["obstacle"] == kind
        placement = env.unwrapped.episode.placement
        pick, place = placement.problem.pick.center, placement.problem.place.center
        along = (placement.xy - pick) @ (place - pick) / np.sum((place - pick) ** 2)
        problem_axis.append(along)
    assert problem_axis[1] < problem_axis[0]  # the box's spot lies behind the pot's along the path
    env.close()
