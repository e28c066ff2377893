"""Shared conventions: the OSC_POSE action codec, rotations against MuJoCo's own conversions, the obstacle view."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

from detaug_gym.actions import (
    ACTION_DIM,
    CONTROL_DT,
    CONTROL_HZ,
    GRIPPER_CLOSE,
    GRIPPER_OPEN,
    POS_SCALE,
    ROT_SCALE,
    action_to_goal,
    controller_settings,
    goal_to_action,
)
from detaug_gym.geometry import obstacle_view
from detaug_gym.geometry.obstacle_view import (
    SHAPE_TOLERANCE,
    ShapeCache,
    has_obstacle,
    obstacle_frame,
    obstacle_local_points,
    obstacle_shape,
)
from detaug_gym.rotations import (
    mat_to_quat_wxyz,
    mat_to_quat_xyzw,
    mat_to_rotvec,
    quat_wxyz_to_mat,
    quat_xyzw_to_mat,
    rotation_error,
    rotvec_to_mat,
    skew,
)


def _random_quats_wxyz(n: int, seed: int = 0) -> np.ndarray:
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _mujoco_mat(quat_wxyz: np.ndarray) -> np.ndarray:
    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, quat_wxyz)
    return out.reshape(3, 3)


# ---------------------------------------------------------------------------------------------- rotations
def test_quaternion_to_matrix_matches_mujoco_single_and_batched():
    quats = _random_quats_wxyz(500)
    expected = np.stack([_mujoco_mat(q) for q in quats])
    batched = quat_xyzw_to_mat(quats[:, [1, 2, 3, 0]])
    assert batched.shape == (500, 3, 3)
    np.testing.assert_allclose(batched, expected, rtol=0, atol=2e-15)
    np.testing.assert_allclose(quat_wxyz_to_mat(quats), expected, rtol=0, atol=2e-15)
    for q, m in zip(quats[:20], expected):
        np.testing.assert_allclose(quat_xyzw_to_mat(q[[1, 2, 3, 0]]), m, rtol=0, atol=2e-15)
    grid = quat_xyzw_to_mat(quats[:12, [1, 2, 3, 0]].reshape(3, 4, 4))  # any leading shape
    np.testing.assert_array_equal(grid.reshape(12, 3, 3), batched[:12])


def test_quaternions_are_normalised_and_zero_gives_identity():
    q = np.array([0.3, -0.2, 0.5, 0.7])
    np.testing.assert_allclose(quat_xyzw_to_mat(7.5 * q), quat_xyzw_to_mat(q), atol=1e-15)
    np.testing.assert_array_equal(quat_xyzw_to_mat(np.zeros(4)), np.eye(3))  # an empty observation slot
    np.testing.assert_array_equal(quat_xyzw_to_mat(np.zeros((2, 4))), np.stack([np.eye(3)] * 2))
    rot = quat_xyzw_to_mat(np.float32(q))  # float32 observations are converted in float64
    assert rot.dtype == np.float64
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)


def test_matrix_to_quaternion_is_mujocos_and_round_trips():
    quats = _random_quats_wxyz(200, seed=1)
    mats = np.stack([_mujoco_mat(q) for q in quats])
    expected = np.zeros((200, 4))
    for row, m in zip(expected, mats):
        mujoco.mju_mat2Quat(row, m.reshape(9))
    np.testing.assert_array_equal(mat_to_quat_wxyz(mats), expected)
    np.testing.assert_array_equal(mat_to_quat_xyzw(mats), expected[:, [1, 2, 3, 0]])
    assert mat_to_quat_xyzw(mats[0]).shape == (4,)
    same_sign = np.sign(np.sum(mat_to_quat_wxyz(mats) * quats, axis=1))[:, None]  # q and -q: one rotation
    np.testing.assert_allclose(same_sign * mat_to_quat_wxyz(mats), quats, atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-4, 0.3, 2.0, np.pi - 1e-3, np.pi - 1e-7])
def test_rotation_vectors_round_trip_at_every_angle(angle):
    rng = np.random.default_rng(2)
    for _ in range(10):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        rotvec = angle * axis
        quat = np.zeros(4)
        mujoco.mju_axisAngle2Quat(quat, axis, angle)
        rot = rotvec_to_mat(rotvec)
        np.testing.assert_allclose(rot, _mujoco_mat(quat), atol=1e-15)
        np.testing.assert_allclose(mat_to_rotvec(rot), rotvec, atol=1e-7 if angle > 3 else 1e-12)


def test_rotation_error_takes_the_current_rotation_onto_the_target():
    quats = _random_quats_wxyz(40, seed=3)
    for a, b in zip(quats[::2], quats[1::2]):
        current, target = quat_wxyz_to_mat(a), quat_wxyz_to_mat(b)
        err = rotation_error(target, current)
        assert np.linalg.norm(err) <= np.pi + 1e-12
        np.testing.assert_allclose(rotvec_to_mat(err) @ current, target, atol=1e-9)
        angle = 2 * np.arccos(min(abs(float(a @ b)), 1.0))  # angle between the two quaternions
        assert np.linalg.norm(err) == pytest.approx(angle, abs=1e-6)


def test_skew_is_the_cross_product():
    u, v = np.random.default_rng(4).normal(size=(2, 3))
    np.testing.assert_allclose(skew(u) @ v, np.cross(u, v), atol=1e-15)


# ---------------------------------------------------------------------------------------------- actions
def test_constants_are_the_robosuite_osc_pose_convention():
    assert (POS_SCALE, ROT_SCALE, ACTION_DIM) == (0.05, 0.5, 7)
    assert CONTROL_HZ * CONTROL_DT == pytest.approx(1.0)
    assert (GRIPPER_OPEN, GRIPPER_CLOSE) == (-1.0, 1.0)


@pytest.mark.parametrize("stepper", ["fast", "stock"])
def test_controller_settings_are_what_collection_stores(stepper):
    # the keys and values detaug_gym.collect has written into every demo's "controller" attribute
    assert controller_settings(stepper) == {"type": "OSC_POSE", "stepper": stepper, "control_freq": 20,
                                            "pos_scale": 0.05, "rot_scale": 0.5, "gripper": "-1 open, +1 close"}


def test_goal_to_action_to_goal_round_trip():
    rng = np.random.default_rng(5)
    for quat in _random_quats_wxyz(50, seed=6):
        pos, rot = rng.normal(size=3), quat_wxyz_to_mat(quat)
        action = np.r_[rng.uniform(-1, 1, 6), rng.choice([GRIPPER_OPEN, GRIPPER_CLOSE])]
        goal_pos, goal_rot = action_to_goal(pos, rot, action)
        np.testing.assert_allclose(goal_pos, pos + POS_SCALE * action[:3], atol=1e-15)
        np.testing.assert_allclose(goal_rot @ rot.T, rotvec_to_mat(ROT_SCALE * action[3:6]), atol=1e-14)
        back = goal_to_action(pos, rot, goal_pos, goal_rot, action[6])
        assert back.shape == (ACTION_DIM,) and back.dtype == np.float64
        np.testing.assert_allclose(back, action, atol=1e-12)
        again = action_to_goal(pos, rot, back)
        np.testing.assert_allclose(again[0], goal_pos, atol=1e-12)
        np.testing.assert_allclose(again[1], goal_rot, atol=1e-12)


def test_goals_out_of_reach_clip_and_actions_out_of_the_box_are_clipped():
    rot = np.eye(3)
    far = goal_to_action(np.zeros(3), rot, np.array([1.0, -0.01, 0.0]), rotvec_to_mat([0.0, 0.0, 2.0]), 0.3)
    np.testing.assert_allclose(far, [1.0, -0.2, 0.0, 0.0, 0.0, 1.0, 0.3])
    goal_pos, goal_rot = action_to_goal(np.zeros(3), rot, np.array([3.0, 0.0, 0.0, 0.0, 0.0, -2.0, 1.0]))
    np.testing.assert_allclose(goal_pos, [POS_SCALE, 0.0, 0.0])
    np.testing.assert_allclose(goal_rot, rotvec_to_mat([0.0, 0.0, -ROT_SCALE]), atol=1e-15)


# ---------------------------------------------------------------------------------------------- obstacle view
def _obstacle_obs(local: np.ndarray, position, quat_xyzw, mask: float = 1.0) -> dict[str, np.ndarray]:
    world = local @ quat_xyzw_to_mat(np.asarray(quat_xyzw)).T + position
    return {"obstacle_points": world.astype(np.float32), "obstacle_pose": np.r_[position, quat_xyzw].astype(np.float32),
            "obstacle_mask": np.full(1, mask, np.float32)}


LOCAL = np.random.default_rng(7).uniform(-0.05, 0.05, (256, 3))
YAWED = (0.0, 0.0, np.sin(0.6), np.cos(0.6))


def test_has_obstacle_reads_the_mask_with_one_rule():
    assert has_obstacle(_obstacle_obs(LOCAL, [0.1, 0.0, 0.9], YAWED))
    assert not has_obstacle(_obstacle_obs(LOCAL, [0.1, 0.0, 0.9], YAWED, mask=0.0))
    assert not has_obstacle({"eef_pos": np.zeros(3)})  # no obstacle keys at all
    assert has_obstacle({"obstacle_mask": np.array([[1.0]])}) and not has_obstacle({"obstacle_mask": [0.0]})
    assert has_obstacle({"obstacle_mask": np.array([0.5])}) and not has_obstacle({"obstacle_mask": np.array([0.49])})


def test_obstacle_frame_and_local_points_undo_the_pose():
    obs = _obstacle_obs(LOCAL, [0.1, -0.2, 0.9], YAWED)
    position, rotation = obstacle_frame(obs)
    np.testing.assert_allclose(position, [0.1, -0.2, 0.9], atol=1e-6)
    np.testing.assert_allclose(rotation, quat_xyzw_to_mat(np.float32(YAWED)), atol=1e-15)
    local = obstacle_local_points(obs)
    assert local.shape == (256, 3) and local.dtype == np.float64
    np.testing.assert_allclose(local, LOCAL, atol=1e-6)  # float32 observations: ~1e-7 m jitter


def test_shape_cache_matches_a_posed_shape_and_keeps_the_newest(monkeypatch):
    shapes = ShapeCache(capacity=2)
    monkeypatch.setattr(obstacle_view, "SHAPES", shapes)
    here = obstacle_shape(_obstacle_obs(LOCAL, [0.1, -0.2, 0.9], YAWED))
    moved = obstacle_shape(_obstacle_obs(LOCAL, [-0.3, 0.2, 1.0], (0.0, 0.0, 0.0, 1.0)))
    assert moved is here and len(shapes) == 1
    built = []
    assert here.product("fit", lambda p: built.append(p) or "fit") == "fit"
    assert moved.product("fit", lambda p: built.append(p) or "again") == "fit" and len(built) == 1
    other = obstacle_shape(_obstacle_obs(LOCAL + [2 * SHAPE_TOLERANCE, 0.0, 0.0], [0.1, -0.2, 0.9], YAWED))
    assert other is not here and len(shapes) == 2
    third = shapes.lookup(0.5 * LOCAL)
    assert len(shapes) == 2 and shapes.lookup(0.5 * LOCAL) is third and shapes.lookup(LOCAL + [0.002, 0, 0]) is other
    assert shapes.lookup(LOCAL) is not here  # the least recently used shape was dropped


def test_sdf_and_ellipsoid_share_the_shape_entry(monkeypatch):
    from detaug_gym.geometry import obstacle_sdf
    from detaug_gym.policies.aegis import CBFFilter

    shapes = ShapeCache()
    monkeypatch.setattr(obstacle_view, "SHAPES", shapes)
    box = np.array(np.meshgrid(*[[-0.03, 0.03]] * 3)).reshape(3, -1).T
    local = np.concatenate([box, np.random.default_rng(8).uniform(-0.03, 0.03, (20, 3))])
    obs = _obstacle_obs(local, [0.1, -0.2, 0.9], YAWED)
    sdf = obstacle_sdf(obs, spacing=0.02)
    assert len(CBFFilter().obstacle_ellipsoids(obs)) == 1  # no support in this observation
    entry = shapes.lookup(obstacle_local_points(obs))
    assert len(shapes) == 1 and {"hull", ("sdf", 0.02, 0.1), "mvee"} <= set(entry.products)
    assert sdf.grid is entry.products[("sdf", 0.02, 0.1)] and sdf.mesh is entry.products["hull"]
    assert obstacle_sdf({**obs, "obstacle_mask": np.zeros(1)}).empty


def test_the_support_is_a_second_part_of_the_obstacle_view_and_of_its_sdf():
    from detaug_gym.geometry import UnionSDF, obstacle_parts, obstacle_sdf

    obs = _obstacle_obs(LOCAL, [0.1, 0.0, 0.9], YAWED)
    assert obstacle_parts(obs) == ("obstacle",) and not has_obstacle(obs, "obstacle_support")
    support = np.array(np.meshgrid(*[[-0.06, 0.06]] * 3)).reshape(3, -1).T
    obs.update(obstacle_support_local_points=support, obstacle_support_points=(support + [0.1, 0.0, 0.78]),
               obstacle_support_pose=np.r_[0.1, 0.0, 0.78, 0, 0, 0, 1.0], obstacle_support_mask=np.ones(1))
    assert obstacle_parts(obs) == ("obstacle", "obstacle_support")
    assert obstacle_parts({**obs, "obstacle_mask": np.zeros(1)}) == ()  # no obstacle: no support either
    union, alone = obstacle_sdf(obs, spacing=0.02), obstacle_sdf(obs, spacing=0.02, support=False)
    assert isinstance(union, UnionSDF) and not isinstance(alone, UnionSDF)
    assert not isinstance(obstacle_sdf({**obs, "obstacle_support_mask": np.zeros(1)}), UnionSDF)
    probe = torch.tensor([[0.1, 0.0, 0.78], [0.1, 0.0, 0.9], [0.1, 0.0, 1.2]], dtype=torch.float64)
    inside_base, at_obstacle, above = union(probe).tolist()
    assert inside_base < -0.03 and alone(probe)[0] > 0.0  # the base's centre: inside the union only
    assert at_obstacle == pytest.approx(float(alone(probe)[1]), abs=1e-9) and above > 0.0
    centre, radius = union.bounding_sphere()
    for part in union.parts:  # the union's ball holds each part's ball
        c, r = part.bounding_sphere()
        assert np.linalg.norm(c - centre) + r <= radius + 1e-9
