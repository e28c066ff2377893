"""AEGIS: the CBF-QP filter on synthetic poses (pass-through, no new violation, minimal change) and the policy
wrapper on a tiny synthetic-data checkpoint."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st

from detaug_gym.actions import action_to_goal
from detaug_gym.geometry import obstacle_view
from detaug_gym.geometry.obstacle_view import ShapeCache, obstacle_local_points
from detaug_gym.models.checkpoint import CheckpointError
from detaug_gym.policies import available_policies, make_policy
from detaug_gym.policies.aegis import AegisPolicy, CBFFilter, EndEffectorEllipsoid, barrier
from detaug_gym.rotations import quat_xyzw_to_mat

OBSTACLE_POS = np.array([0.0, 0.0, 1.0])
DOWN = np.array([1.0, 0.0, 0.0, 0.0])  # xyzw: tool axis pointing down, like the env's default hand
FILTER = CBFFilter()


def box_observation(centre=OBSTACLE_POS, half=(0.04, 0.05, 0.10), quat=(0.0, 0.0, 0.0, 1.0), eef=(0.0, -0.3, 1.05),
                    eef_quat=DOWN) -> dict[str, np.ndarray]:
    """An observation with a posed box obstacle (256 surface points) and a free-floating hand."""
    points, _ = trimesh.sample.sample_surface(trimesh.creation.box(extents=2 * np.asarray(half)), 248, seed=0)
    corners = np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T * half
    local = np.concatenate([corners, points])
    world = local @ quat_xyzw_to_mat(np.asarray(quat)).T + centre
    return {"obstacle_points": world.astype(np.float32), "obstacle_pose": np.r_[centre, quat].astype(np.float32),
            "obstacle_size": np.asarray(half, np.float32), "obstacle_mask": np.ones(1, np.float32),
            "eef_pos": np.asarray(eef, np.float64), "eef_quat": np.asarray(eef_quat, np.float64)}


def commanded_barrier(action: np.ndarray, obs: dict, flt: CBFFilter = FILTER) -> float:
    """Exact barrier at the pose the action commands (OSC_POSE goal), not its linearisation."""
    goal, rotation = action_to_goal(obs["eef_pos"], quat_xyzw_to_mat(obs["eef_quat"]), action)
    return barrier(*flt.end_effector.placed(goal, rotation), *flt.obstacle_ellipsoids(obs)[0])[0]


unit = st.floats(-1.0, 1.0, allow_nan=False)
actions = st.tuples(*[unit] * 6, st.sampled_from([-1.0, 1.0])).map(lambda a: np.array(a, np.float32))
offsets = st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-0.1, 0.3)).map(np.array)
quats = st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1).map(np.array)


@settings(max_examples=150, deadline=None)
@given(action=actions, offset=offsets, quat=quats)
@example(action=np.array([1, 1, -1, 0, 0, 1, -1], np.float32), offset=np.zeros(3), quat=np.array([1, 0, -0.75, 0]))
@example(action=np.array([0, 0, -1, 0, 0, 0, -1], np.float32), offset=np.zeros(3), quat=np.array([0, 0, 0, 1.0]))
def test_filter_never_makes_the_commanded_pose_less_safe(action, offset, quat):
    """The examples were found by hypothesis: the grip site at the obstacle's centre, deep inside it (h < 0), where
    the nominal can already be the fastest escape the action box allows (nothing to correct) and the linear
    constraint no longer bounds how the true barrier compares with the nominal's."""
    obs = box_observation(eef=OBSTACLE_POS + offset, eef_quat=quat)
    filtered, step = FILTER(action, obs)
    h_nominal, h_filtered = commanded_barrier(action, obs), commanded_barrier(filtered, obs)
    assert np.all(np.isfinite(filtered)) and np.all(np.abs(filtered[:3]) <= 1.0 + 1e-6)
    assert filtered[3:] .tobytes() == action[3:].tobytes()  # only the position part is ever changed
    if not step.active:
        assert filtered is action
        return
    if step.feasible:  # h is convex in the centre, so the linear constraint bounds the true barrier
        assert step.correction > 0.0
        assert h_filtered >= (1.0 - FILTER.alpha * FILTER.dt) * step.h - 1e-6
        if step.h >= 0.0:
            assert h_filtered >= h_nominal - 1e-6  # never a larger violation than the proposal's
            assert h_filtered >= -1e-6  # a safe pose stays safe


def test_at_a_vanishing_gradient_the_filter_escapes_upwards():
    from detaug_gym.policies.aegis import _escape

    np.testing.assert_array_equal(_escape(np.array([0.3, 0.0, -1.0]), np.zeros(3)), [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(_escape(np.array([0.3, 0.0, -1.0]), np.array([0.0, 2.0, 0.0])), [0.3, 1.0, -1.0])


@settings(max_examples=60, deadline=None)
@given(action=actions, quat=quats)
def test_safe_actions_pass_bit_identical(action, quat):
    far = box_observation(eef=OBSTACLE_POS + np.array([0.0, -0.8, 0.3]), eef_quat=quat)
    filtered, step = FILTER(action, far)
    assert filtered is action and not step.active and step.h > 0.5
    free = dict(far, obstacle_mask=np.zeros(1, np.float32))
    filtered, step = FILTER(action, free)
    assert filtered is action and step.h == float("inf")


def test_correction_is_the_projection_when_the_box_is_slack():
    obs = box_observation(eef=OBSTACLE_POS + np.array([0.0, -0.17, 0.05]))
    action = np.array([0.0, 0.6, 0.0, 0.0, 0.0, 0.0, -1.0], np.float32)  # straight at the obstacle
    filtered, step = FILTER(action, obs)
    assert step.active and step.feasible
    h, g, b = FILTER.constraint(action, obs, FILTER.obstacle_ellipsoids(obs)[0])
    a = action[:3].astype(np.float64)
    projection = a + (b - g @ a) / (g @ g) * g  # closed form of the one-constraint QP
    assert np.abs(projection).max() < 1.0
    np.testing.assert_allclose(filtered[:3], projection, atol=1e-5)
    assert g @ filtered[:3] >= b - 1e-6


def test_infeasible_step_takes_the_fastest_way_out_and_says_so():
    obs = box_observation(eef=OBSTACLE_POS + np.array([0.0, -0.02, -0.056]))  # hand centre near the obstacle centre
    action = np.array([0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0], np.float32)
    filtered, step = FILTER(action, obs)
    assert step.active and step.h < 0 and not step.feasible
    assert filtered[1] == -1.0 and commanded_barrier(filtered, obs) > step.h


@settings(max_examples=60, deadline=None)
@given(offset=offsets, quat=quats)
def test_nonnegative_barrier_means_the_ellipsoids_are_apart(offset, quat):
    obs = box_observation(eef=OBSTACLE_POS + offset, eef_quat=quat)
    rotation = quat_xyzw_to_mat(quat)
    centre, q_ee = FILTER.end_effector.placed(obs["eef_pos"], rotation)
    obs_centre, q_obs = FILTER.obstacle_ellipsoids(obs)[0]
    h, _ = barrier(centre, q_ee, obs_centre, q_obs)
    if h < 0:
        return
    sphere = np.random.default_rng(0).normal(size=(2000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    surface = centre + sphere @ np.linalg.cholesky(q_ee).T  # points on the end-effector ellipsoid
    diff = surface - obs_centre
    assert np.all(np.einsum("ni,ij,nj->n", diff, np.linalg.inv(q_obs), diff) > 1.0)


@pytest.mark.parametrize("distance", [0.05, 0.1, 0.2, 0.4])
def test_barrier_is_exact_for_equal_spheres(distance):
    q = 0.05**2 * np.eye(3)
    h, grad = barrier(np.array([distance, 0.0, 0.0]), q, np.zeros(3), q)
    assert h == pytest.approx(distance / 0.1 - 1.0)
    np.testing.assert_allclose(grad, [1.0 / 0.1, 0.0, 0.0])


def test_obstacle_ellipsoid_encloses_the_points_when_posed_and_moved(monkeypatch):
    shapes = ShapeCache()
    monkeypatch.setattr(obstacle_view, "SHAPES", shapes)
    flt = CBFFilter()
    yaw = np.array([0.0, 0.0, np.sin(0.4), np.cos(0.4)])
    for centre, quat in ((OBSTACLE_POS, (0, 0, 0, 1)), (OBSTACLE_POS + [0.1, -0.05, 0.0], yaw)):
        obs = box_observation(centre=centre, quat=quat)
        c, q = flt.obstacle_ellipsoids(obs)[0]
        diff = obs["obstacle_points"].astype(np.float64) - c
        assert np.all(np.einsum("ni,ij,nj->n", diff, np.linalg.inv(q), diff) <= 1.0 + 1e-6)
    assert len(shapes) == 1 and "mvee" in shapes.lookup(obstacle_local_points(obs)).products  # fitted once


def test_end_effector_ellipsoid_sits_above_the_grip_site():
    centre, q = EndEffectorEllipsoid().placed(np.zeros(3), quat_xyzw_to_mat(DOWN))
    np.testing.assert_allclose(centre, [0.0, 0.0, 0.056])  # tool axis points down: the wrist is above
    np.testing.assert_allclose(np.sort(np.sqrt(np.linalg.eigvalsh(q))), [0.06, 0.11, 0.12])


@pytest.mark.parametrize("options", [dict(alpha=0.0), dict(alpha=30.0), dict(ee_semi_axes=(0.1, 0.0, 0.1)),
                                     dict(base="aegis")])
def test_bad_options_fail_at_construction(options):
    with pytest.raises(ValueError):
        AegisPolicy(base="random", **options) if "base" not in options else AegisPolicy(**options)


@pytest.fixture(scope="module")
def checkpoint(tiny_base_checkpoint):
    return tiny_base_checkpoint


def test_policy_from_the_registry_filters_the_base_policy(checkpoint):
    path, obs = checkpoint
    assert "aegis" in available_policies()
    policy = make_policy("aegis", suite="spatial", checkpoint=path, action_steps=2, seed=0)
    assert isinstance(policy, AegisPolicy)
    near = dict(obs, **{k: v for k, v in box_observation(eef=obs["eef_pos"]).items() if k.startswith("obstacle")})
    near["obstacle_pose"][:3] = obs["eef_pos"] + [0.0, 0.2, 0.0]
    near["obstacle_points"] += near["obstacle_pose"][:3] - OBSTACLE_POS
    policy.reset(seed=0)
    for observation in (obs | {"obstacle_mask": np.zeros(1, np.float32)}, near, near):
        action = policy.act(observation)
        assert action.shape == (7,) and action.dtype == np.float32 and np.all(np.isfinite(action))
    assert len(policy.diagnostics) == 3 and policy.diagnostics[0].h == float("inf")
    policy.reset(seed=1)
    assert policy.diagnostics == []


def test_missing_checkpoint_or_base_fails_at_construction(tmp_path):
    with pytest.raises(CheckpointError):
        make_policy("aegis", suite="spatial", checkpoint=str(tmp_path / "nothing"))
    with pytest.raises(KeyError, match="unknown policy"):
        make_policy("aegis", base="no_such_policy")


def with_support(obs: dict, centre, half=(0.07, 0.06, 0.07)) -> dict:
    """``obs`` with a box support (pedestal or base) at ``centre``: the env's ``obstacle_support_*`` entries."""
    corners = np.array(np.meshgrid(*[[-1, 1]] * 3)).reshape(3, -1).T * half
    points, _ = trimesh.sample.sample_surface(trimesh.creation.box(extents=2 * np.asarray(half)), 120, seed=1)
    local = np.concatenate([corners, points])
    return {**obs, "obstacle_support_points": (local + centre).astype(np.float32),
            "obstacle_support_local_points": local, "obstacle_support_mask": np.ones(1, np.float32),
            "obstacle_support_pose": np.r_[centre, 0, 0, 0, 1].astype(np.float32)}


def test_the_support_gets_its_own_barrier_and_the_qp_keeps_both():
    """Hand moving down onto the base beside the obstacle: only the support's barrier objects, and the filtered
    action satisfies both linearised barriers; without ``support`` the base is ignored."""
    base_centre = OBSTACLE_POS + np.array([0.0, -0.25, -0.17])
    obs = with_support(box_observation(eef=base_centre + np.array([0.0, 0.0, 0.24])), base_centre)
    flt = CBFFilter()
    ellipsoids = flt.obstacle_ellipsoids(obs)
    assert len(ellipsoids) == 2 and len(CBFFilter(support=False).obstacle_ellipsoids(obs)) == 1
    np.testing.assert_allclose(ellipsoids[1][0], base_centre, atol=1e-6)  # the box's MVEE sits on its centre
    down = np.array([0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0], np.float32)
    filtered, step = flt(down, obs)
    assert step.active and step.feasible
    for ellipsoid in ellipsoids:
        _, g, b = flt.constraint(filtered, obs, ellipsoid)
        assert g @ filtered[:3] >= b - 1e-9
    assert CBFFilter(support=False)(down, obs)[1].active is False  # blind to the base: nothing to correct


def test_multi_row_qp_is_the_projection_onto_both_half_spaces():
    """Two barrier rows: OSQP's answer equals the closed form (the nominal projected onto the intersection of
    two half-spaces whose boundaries cross inside the box)."""
    flt = CBFFilter()
    g = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    b = np.array([0.2, 0.3])
    x, feasible = flt.solve(np.array([-0.5, -0.5, 0.4]), g, b)
    assert feasible
    np.testing.assert_allclose(x, [0.2, 0.3, 0.4], atol=1e-7)
    x, feasible = flt.solve(np.zeros(3), g, np.array([0.2, 3.5]))  # row 2 cannot be met inside the box
    assert not feasible and x[1] == 1.0
