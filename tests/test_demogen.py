"""DemoGen: the detour planner (pure, fast), the zoo policy, and the augmentation mode on a real Spatial demo.

The point encoder's permutation invariance and the zero-initialised encoder leaving the backbone unchanged
are tested in ``tests/test_models.py`` (``test_point_encoder_permutation_invariant_and_empty_mask``,
``test_zero_initialised_point_encoder_leaves_backbone_unchanged``); training a demogen checkpoint and
feeding it ``obstacle_points`` in ``tests/test_train.py`` (``test_demogen_policy_reads_obstacle_points``).
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from detaug_gym.augment.planner import (
    PlannerConfig,
    ProxyWorld,
    box_part,
    edge_free,
    polyline_length,
    resample,
    rrt_connect,
    sampling_box,
    shortcut,
    smooth,
    sphere_part,
)


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("seed", range(6))
def test_planned_detours_are_collision_free_and_keep_the_endpoints(seed):
    rng = np.random.default_rng(seed)
    obstacle = trimesh.creation.box(extents=2 * rng.uniform([0.015, 0.015, 0.02], [0.06, 0.06, 0.11]))
    obstacle.apply_translation([0.0, 0.0, obstacle.extents[2] / 2])
    def hand(margin):
        return [box_part(np.array([-0.02, -0.06, 0.0]) - margin, np.array([0.02, 0.06, 0.1]) + margin),
                sphere_part(np.array([0.0, 0.0, 0.15]), 0.05 + margin)]

    # plan with the proxy inflated by 5 mm (the mode's clearance); edges are checked every 5 mm, so the
    # true proxy must be free everywhere in between
    world, true_world = ProxyWorld(obstacle, 0.0, hand(0.005)), ProxyWorld(obstacle, 0.0, hand(0.0))
    r0, r1 = _yaw(rng.uniform(0, np.pi)), _yaw(rng.uniform(0, np.pi))
    start, goal = np.array([-0.25, rng.uniform(-0.05, 0.05), 0.03]), np.array([0.25, rng.uniform(-0.05, 0.05), 0.05])
    assert not edge_free(start, goal, world.free_in_all([r0, r1]), 0.005)  # the straight path is blocked
    config = PlannerConfig()
    is_free = world.free_in_all([r0, r1])
    lo, hi = sampling_box(start, goal, 0.0, config)
    raw = rrt_connect(start, goal, is_free, lo, hi, rng, config)
    assert raw is not None
    path = smooth(shortcut(raw, is_free, rng, config), is_free, config)
    assert polyline_length(path) <= polyline_length(raw) + 1e-9
    dense = resample(path, np.linspace(0.0, 1.0, 400))
    assert np.allclose(dense[0], start) and np.allclose(dense[-1], goal)
    assert all(not true_world.collides(p, r) for p in dense for r in (r0, r1))


def test_proxy_world_respects_orientation_and_table():
    obstacle = trimesh.creation.box(extents=[0.02, 0.02, 0.2])
    obstacle.apply_translation([0.0, 0.08, 0.1])
    world = ProxyWorld(obstacle, 0.0, [box_part([-0.01, -0.1, 0.0], [0.01, 0.1, 0.05])])
    p = np.array([0.0, 0.0, 0.05])
    assert world.collides(p, np.eye(3))  # long axis along y reaches the obstacle
    assert not world.collides(p, _yaw(np.pi / 2))  # turned, it does not
    assert world.collides(np.array([0.3, 0.0, -0.01]), np.eye(3))  # below the table top
    assert not world.collides(np.array([0.3, 0.0, -0.01]), np.eye(3), with_table=False)


def test_demogen_policy_is_registered_and_fails_at_construction(tmp_path):
    from detaug_gym.models import CheckpointError
    from detaug_gym.policies import available_policies, make_policy

    assert "demogen" in available_policies()
    with pytest.raises(CheckpointError, match="--method demogen"):
        make_policy("demogen", checkpoint=tmp_path / "demogen" / "spatial")


# ---------------------------------------------------------------------------------------------- simulator
@pytest.fixture(scope="module")
def demogen_run(tmp_path_factory):
    """``python -m detaug_gym.augment --mode demogen --limit 1 --copies 1`` on a 1-demo Spatial dataset."""
    import gymnasium as gym

    import detaug_gym  # noqa: F401
    from detaug_gym.augment.__main__ import main as augment_main
    from detaug_gym.collect import record_episode
    from detaug_gym.data import DatasetWriter, load
    from detaug_gym.policies import make_policy

    env_id = "SafeLibero-Spatial-Free-v0"
    root = tmp_path_factory.mktemp("demogen")
    env = gym.make(env_id)
    try:
        demo, ok = record_episode(env, make_policy("scripted"), task=0, init_state=0, seed=0, env_id=env_id)
        assert ok
        demo.name = "demo_0"
        env_args = {"env_name": env_id, "env_version": "0", "type": "detaug_gym", "env_kwargs": {}}
        with DatasetWriter(root / "src.hdf5", env_args) as writer:
            writer.append(demo)
    finally:
        env.close()
    augment_main(["--mode", "demogen", "--in", str(root / "src.hdf5"), "--out", str(root / "out.hdf5"),
                  "--limit", "1", "--copies", "1", "--tries", "6", "--seed", "0", "--no-progress"])
    return load(root / "out.hdf5")


def test_demogen_mode_writes_demos_with_obstacle_clouds(demogen_run):
    originals = [d for d in demogen_run.demos if not d.attrs.get("augmented")]
    augmented = [d for d in demogen_run.demos if d.attrs.get("augmented")]
    assert len(originals) == 1 and originals[0].obstacle_points is None  # empty cloud: mask 0 in training
    assert len(augmented) == 1
    demo = augmented[0]
    assert demo.attrs["augment_mode"] == "demogen" and demo.obstacle_points.shape == (256, 3)
    cloud = demo.obstacle_points
    hull = trimesh.convex.convex_hull(cloud)
    # the replayed end effector stays outside the obstacle, which stands on the table under the old path
    assert not hull.contains(demo.obs["eef_pos"]).any()
    assert cloud[:, 2].min() == pytest.approx(demo.attrs["obstacle_pose"][2], abs=1e-3)
    assert len(demo.attrs["transits"]) >= 1


def test_a_suite_without_safelibero_meshes_borrows_spatials():
    from detaug_gym.augment.obstacle_shapes import N_POINTS, SAFELIBERO_TYPES, safelibero_shapes
    from detaug_gym.envs.suites import get_suite

    newton = get_suite("newton")
    assert newton.shape_source_level is None
    shapes = safelibero_shapes(newton)
    assert shapes is safelibero_shapes(get_suite("spatial")) and tuple(shapes) == SAFELIBERO_TYPES
    assert all(s.points.shape == (N_POINTS, 3) and s.points[:, 2].min() >= -1e-9 for s in shapes.values())
