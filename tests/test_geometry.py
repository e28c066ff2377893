"""Shared geometry: FK against MuJoCo, robot points, obstacle SDF, collision costs, MVEE."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch
import trimesh

from detaug_gym.geometry import (
    NO_OBSTACLE_DISTANCE,
    PandaKinematics,
    RobotGeometry,
    clearance_cost,
    exact_signed_distance,
    min_volume_ellipsoid,
    obstacle_sdf,
    panda_model,
    penetration_cost,
    plan_collision_cost,
)
from detaug_gym.geometry.meshes import body_collision_mesh
from detaug_gym.rotations import quat_xyzw_to_mat

ARM = [f"robot0_joint{i}" for i in range(1, 8)]
FINGERS = ["gripper0_finger_joint1", "gripper0_finger_joint2"]
HOME = np.array([0.0, -0.17, 0.0, -2.42, 0.0, 2.2, 0.8])


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    """robosuite's Panda with its base moved and turned, so the base pose is not the identity."""
    m = panda_model()
    base = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "robot0_base")
    m.body_pos[base] = (-0.66, 0.05, 0.912)
    m.body_quat[base] = (np.cos(0.2), 0.0, 0.0, np.sin(0.2))
    return m


@pytest.fixture(scope="module")
def robot(model) -> RobotGeometry:
    return RobotGeometry.from_model(model, num_points=300)


def _joint_qpos(model: mujoco.MjModel, names: list[str]) -> np.ndarray:
    return np.array([model.jnt_qposadr[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n)] for n in names])


def _random_configs(model: mujoco.MjModel, shape: tuple[int, ...], seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ranges = model.jnt_range[[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in ARM + FINGERS]]
    q = rng.uniform(ranges[:, 0], ranges[:, 1], (*shape, 9))
    return q[..., :7], q[..., 7:]


def _mujoco_poses(model, kin: PandaKinematics, arm: np.ndarray, fingers: np.ndarray):
    data = mujoco.MjData(model)
    data.qpos[_joint_qpos(model, ARM)] = arm
    data.qpos[_joint_qpos(model, FINGERS)] = fingers
    mujoco.mj_kinematics(model, data)
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, "gripper0_grip_site")
    ids = kin.link_body_ids
    return (data.xmat[ids].reshape(-1, 3, 3), data.xpos[ids], data.site_xmat[site].reshape(3, 3),
            data.site_xpos[site].copy(), data)


def _box_obs(centre, half, yaw: float = 0.0, seed: int = 0) -> dict[str, np.ndarray]:
    """An observation whose obstacle is a box (256 surface samples), as the envs report it."""
    mesh = trimesh.creation.box(extents=2.0 * np.asarray(half))
    points, _ = trimesh.sample.sample_surface(mesh, 256, seed=seed)
    quat = np.array([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)])
    world = points @ quat_xyzw_to_mat(quat).T + centre
    return {"obstacle_points": world.astype(np.float32), "obstacle_pose": np.concatenate([centre, quat]),
            "obstacle_size": np.asarray(half, np.float32), "obstacle_mask": np.ones(1, np.float32),
            "gripper_qpos": np.array([0.04, -0.04], np.float32)}


# ---------------------------------------------------------------------------------------------- kinematics
@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-9), (torch.float32, 1e-5)])
def test_fk_matches_mujoco_on_random_configurations(model, dtype, tol):
    kin = PandaKinematics.from_model(model)
    arm, fingers = _random_configs(model, (4, 5))
    out = kin(torch.tensor(arm, dtype=dtype), torch.tensor(fingers, dtype=dtype))
    assert out.rotations.shape == (4, 5, len(kin.link_names), 3, 3) and out.rotations.dtype == dtype
    for i in range(4):
        for j in range(5):
            rot, pos, eef_rot, eef_pos, _ = _mujoco_poses(model, kin, arm[i, j], fingers[i, j])
            np.testing.assert_allclose(out.rotations[i, j].numpy(), rot, atol=tol)
            np.testing.assert_allclose(out.positions[i, j].numpy(), pos, atol=tol)
            np.testing.assert_allclose(out.eef_rotation[i, j].numpy(), eef_rot, atol=tol)
            np.testing.assert_allclose(out.eef_position[i, j].numpy(), eef_pos, atol=tol)


def test_fk_links_default_fingers_and_broadcasting(model):
    kin = PandaKinematics.from_model(model)
    assert kin.link_names[:7] == [f"robot0_link{i}" for i in range(7)]
    assert {"gripper0_right_gripper", "gripper0_leftfinger", "gripper0_rightfinger"} <= set(kin.link_names)
    np.testing.assert_allclose(kin.default_fingers, [0.04, -0.04])
    q = torch.tensor(np.tile(HOME, (3, 2, 1)))
    opened = kin(q)
    explicit = kin(q, torch.tensor([0.04, -0.04], dtype=torch.float64))  # (2,) broadcast over (3, 2)
    torch.testing.assert_close(opened.positions, explicit.positions)
    assert kin(torch.tensor(HOME)).positions.shape == (len(kin.link_names), 3)
    with pytest.raises(ValueError):
        kin(torch.zeros(3, 6))


def test_fk_is_differentiable(model):
    kin = PandaKinematics.from_model(model)
    q = torch.tensor(HOME[None], requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: kin(x).eef_position, (q,))


def test_base_from_eef_recovers_the_base(model):
    """A kinematics built at the origin, re-based from an observation, matches the moved model."""
    kin = PandaKinematics.from_model(model)
    origin = PandaKinematics.from_model(panda_model())
    arm, fingers = _random_configs(model, (1,), seed=3)
    _, _, eef_rot, eef_pos, _ = _mujoco_poses(model, kin, arm[0], fingers[0])
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, eef_rot.ravel())
    rebased = origin.base_from_eef(arm[0], eef_pos, quat[[1, 2, 3, 0]], fingers[0])
    other_arm, other_fingers = _random_configs(model, (6,), seed=4)
    expected = kin(torch.tensor(other_arm), torch.tensor(other_fingers))
    got = rebased(torch.tensor(other_arm), torch.tensor(other_fingers))
    torch.testing.assert_close(got.positions, expected.positions, atol=1e-9, rtol=0)
    torch.testing.assert_close(got.rotations, expected.rotations, atol=1e-9, rtol=0)


# ---------------------------------------------------------------------------------------------- robot points
def test_surface_points_lie_on_the_collision_meshes(model, robot):
    assert len(robot.points) == 300
    arm, fingers = _random_configs(model, (1,), seed=1)
    world = robot.surface_points(torch.tensor(arm[0]), torch.tensor(fingers[0])).numpy()
    assert world.shape == (300, 3)
    kin = robot.kinematics
    _, _, _, _, data = _mujoco_poses(model, kin, arm[0], fingers[0])
    for link, body in enumerate(kin.link_body_ids):
        mesh = body_collision_mesh(model, body)
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = data.xmat[body].reshape(3, 3), data.xpos[body]
        mesh.apply_transform(pose)
        mine = world[robot.points.link_index == link]
        assert len(mine) >= 1
        _, dist, _ = trimesh.proximity.closest_point(mesh, mine)
        assert dist.max() < 1e-6


def test_surface_points_are_deterministic_and_area_weighted(model, robot):
    again = RobotGeometry.from_model(model, num_points=300)
    np.testing.assert_array_equal(again.points.local_points, robot.points.local_points)
    counts = np.bincount(robot.points.link_index, minlength=len(robot.kinematics.link_names))
    assert counts.min() >= 1
    assert counts[robot.kinematics.link_names.index("robot0_link5")] > 5 * counts[
        robot.kinematics.link_names.index("gripper0_leftfinger")]


def test_eef_spheres_cover_the_hand_and_fingers(model, robot):
    arm, _ = _random_configs(model, (1,), seed=2)
    fk = robot.kinematics(torch.tensor(arm[0]))  # fingers open
    centres = robot.spheres.world(fk).numpy()
    assert centres.shape == (3, 3)
    for name in ("gripper0_right_gripper", "gripper0_leftfinger", "gripper0_finger_joint1_tip",
                 "gripper0_rightfinger", "gripper0_finger_joint2_tip"):
        link = robot.kinematics.link_names.index(name)
        vertices = body_collision_mesh(model, robot.kinematics.link_body_ids[link]).vertices
        world = vertices @ fk.rotations[link].numpy().T + fk.positions[link].numpy()
        outside = np.linalg.norm(world[:, None] - centres[None], axis=-1) - robot.spheres.radii
        assert outside.min(axis=1).max() < 1e-3, name


# ---------------------------------------------------------------------------------------------- SDF
@pytest.fixture(scope="module")
def box_sdf():
    obs = _box_obs(np.array([0.1, -0.2, 1.0]), [0.03, 0.05, 0.08], yaw=0.7)
    return obs, obstacle_sdf(obs)


def test_exact_sdf_sign_convention_matches_trimesh(box_sdf):
    _, sdf = box_sdf
    rng = np.random.default_rng(0)
    local = rng.uniform(-0.15, 0.15, (300, 3))
    mine = exact_signed_distance(sdf.mesh, local)
    theirs = -trimesh.proximity.signed_distance(sdf.mesh, local)  # trimesh: positive inside
    np.testing.assert_allclose(mine, theirs, atol=1e-9)
    assert exact_signed_distance(sdf.mesh, np.zeros((1, 3)))[0] < -0.02  # the box centre


def test_grid_sdf_agrees_with_exact_within_resolution(box_sdf):
    obs, sdf = box_sdf
    rng = np.random.default_rng(1)
    centre = obs["obstacle_pose"][:3]
    points = centre + rng.uniform(-0.15, 0.15, (2000, 3))
    exact = sdf.exact(points)
    grid = sdf(torch.tensor(points)).numpy()
    assert np.abs(grid - exact).max() < sdf.grid.spacing
    clear = np.abs(exact) > sdf.grid.spacing
    assert (exact < 0).sum() > 50 and (exact > 0).sum() > 50
    np.testing.assert_array_equal(grid[clear] < 0, exact[clear] < 0)
    assert sdf(torch.tensor(centre)).item() < -0.02  # inside: negative
    assert sdf(torch.tensor(centre + [0.0, 0.0, 0.2])).item() > 0.1  # above the box: positive


def test_grid_sdf_outside_the_grid_dtype_and_gradients(box_sdf):
    obs, sdf = box_sdf
    far = obs["obstacle_pose"][:3] + np.array([[0.6, 0.0, 0.0], [0.0, -0.5, 0.4], [1.0, 1.0, 1.0]])
    grid = sdf(torch.tensor(far)).numpy()
    exact = sdf.exact(far)
    assert np.all(grid >= exact - 1e-6) and np.all(grid < exact + 0.03)
    points = torch.tensor(np.vstack([far, obs["obstacle_pose"][:3] + [0.0, 0.0, 0.12]]), dtype=torch.float32,
                          requires_grad=True)
    values = sdf(points)
    assert values.dtype == torch.float32
    values.sum().backward()
    norms = torch.linalg.vector_norm(points.grad, dim=-1)
    assert torch.isfinite(points.grad).all() and torch.all((norms > 0.8) & (norms < 1.2))  # |grad sdf| ~ 1


def test_obstacle_sdf_cache_rotation_and_empty(box_sdf):
    obs, sdf = box_sdf
    assert obstacle_sdf(obs).grid is sdf.grid  # baked once per shape
    moved = _box_obs(np.array([0.3, 0.2, 0.9]), [0.03, 0.05, 0.08], yaw=-1.1)
    moved_sdf = obstacle_sdf(moved)
    assert moved_sdf.grid is sdf.grid  # same shape in its own frame: the same grid
    probe = np.array([[0.3, 0.2, 0.9], [0.3, 0.25, 0.9], [0.36, 0.2, 0.95]])
    np.testing.assert_allclose(moved_sdf(torch.tensor(probe)).numpy(), moved_sdf.exact(probe), atol=0.01)
    empty = obstacle_sdf({**obs, "obstacle_mask": np.zeros(1)})
    assert empty.empty and torch.all(empty(torch.zeros(5, 3)) == NO_OBSTACLE_DISTANCE)


# ---------------------------------------------------------------------------------------------- costs
@pytest.fixture(scope="module")
def eef_obs(robot):
    """A box obstacle around the hand at HOME."""
    eef = robot.kinematics(torch.tensor(HOME)).eef_position.numpy()
    return _box_obs(eef + np.array([0.0, 0.0, 0.05]), [0.05, 0.05, 0.05])


def _plans(dtype=torch.float64) -> torch.Tensor:
    """(3, 10, 7): through the obstacle, swung away from it, and moving from inside to far out."""
    plans = np.tile(HOME, (3, 10, 1))
    plans[1, :, 0] += 1.5
    plans[2, :, 0] += np.linspace(0.0, 1.5, 10)
    return torch.tensor(plans, dtype=dtype)


def test_penetration_cost_separates_colliding_plans(robot, eef_obs):
    cost = plan_collision_cost(_plans(), eef_obs, robot)
    assert cost.shape == (3,)
    assert cost[0] > 0.1 and cost[1] == 0.0 and 0.0 < cost[2] < cost[0]
    clearance = plan_collision_cost(_plans(), eef_obs, robot, kind="clearance", margin=0.05)
    assert torch.all(clearance >= cost)
    spheres = plan_collision_cost(_plans(), eef_obs, robot, kind="spheres")
    assert spheres[0] > 0 and spheres[1] == 0.0


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_culled_cost_equals_the_all_points_cost(robot, eef_obs, dtype):
    plans = _plans(dtype)
    fingers = torch.tensor(eef_obs["gripper_qpos"], dtype=dtype)
    points = robot.surface_points(plans, fingers)
    assert points.shape == (3, 10, 300, 3)
    sdf = obstacle_sdf(eef_obs)
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(plan_collision_cost(plans, eef_obs, robot), penetration_cost(points, sdf),
                               atol=tol, rtol=tol)
    torch.testing.assert_close(plan_collision_cost(plans, eef_obs, robot, kind="clearance", margin=0.05),
                               clearance_cost(points, sdf, 0.05), atol=tol, rtol=tol)


def test_cost_gradient_pushes_the_plan_out(robot):
    """Descending the penetration gradient (with step halving) clears an obstacle the hand grazes.

    (Penetration depth has local minima, e.g. a hand centred in a box is pushed out on both sides.)
    """
    eef = robot.kinematics(torch.tensor(HOME)).eef_position.numpy()
    graze = _box_obs(eef + np.array([0.0, 0.08, 0.05]), [0.05, 0.05, 0.05])
    plan = _plans()[:1].clone().requires_grad_(True)
    start = cost = plan_collision_cost(plan, graze, robot).sum()
    assert start > 0.5
    step = 0.3
    (grad,) = torch.autograd.grad(cost, plan)
    for _ in range(25):
        trial = (plan - step * grad / grad.norm()).detach().requires_grad_(True)
        trial_cost = plan_collision_cost(trial, graze, robot).sum()
        if trial_cost < cost:
            plan, cost = trial, trial_cost
            (grad,) = torch.autograd.grad(cost, plan)
        else:
            step /= 2
    assert cost < 0.1 * start


def test_no_obstacle_costs_zero_with_zero_gradient(robot, eef_obs):
    plan = _plans().requires_grad_(True)
    for kind in ("penetration", "clearance", "spheres"):
        cost = plan_collision_cost(plan, {**eef_obs, "obstacle_mask": np.zeros(1)}, robot, kind=kind)
        (grad,) = torch.autograd.grad(cost.sum(), plan)
        assert torch.all(cost == 0) and torch.all(grad == 0)
    with pytest.raises(ValueError):
        plan_collision_cost(plan, eef_obs, robot, kind="distance")


# ---------------------------------------------------------------------------------------------- ellipsoid
def test_mvee_encloses_points_and_is_tight():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(400, 3)) * [0.1, 0.03, 0.2] + [0.5, 0.0, 1.0]
    ellipsoid = min_volume_ellipsoid(points)
    assert ellipsoid.contains(points).all()
    assert np.isclose(ellipsoid.level(points).max(), 1.0, atol=1e-6)  # touches the hull
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    sphere = min_volume_ellipsoid(cube)
    np.testing.assert_allclose(sphere.semi_axes, np.sqrt(3.0), rtol=1e-4)
    np.testing.assert_allclose(sphere.centre, 0.0, atol=1e-9)


def test_mvee_recovers_an_ellipsoid_from_its_surface():
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(300, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    rot = quat_xyzw_to_mat(np.array([0.2, -0.1, 0.3, 0.9]))
    points = (directions * [0.02, 0.05, 0.11]) @ rot.T + [0.1, 0.2, 0.9]
    ellipsoid = min_volume_ellipsoid(points)
    np.testing.assert_allclose(ellipsoid.semi_axes, [0.02, 0.05, 0.11], rtol=1e-3)
    np.testing.assert_allclose(ellipsoid.centre, [0.1, 0.2, 0.9], atol=1e-4)
    with pytest.raises(ValueError):
        min_volume_ellipsoid(np.c_[rng.normal(size=(20, 2)), np.zeros(20)])  # flat


# ---------------------------------------------------------------------------------------------- held object
def _bowl_points(centre, radius: float = 0.06, seed: int = 0) -> np.ndarray:
    """(64, 3) surface samples of a bowl-sized cylinder (radius, 5 cm tall) standing at ``centre``."""
    mesh = trimesh.creation.cylinder(radius=radius, height=0.05)
    points, _ = trimesh.sample.sample_surface(mesh, 64, seed=seed)
    return (points + centre).astype(np.float32)


def test_held_object_is_found_only_with_closed_fingers_and_an_object_at_hand():
    from detaug_gym.geometry import held_object

    obs = _box_obs(np.array([0.0, 0.0, 1.0]), [0.03, 0.03, 0.08])
    origins = np.array([[0.3, 0.065, 0.96], [0.6, 0.3, 0.9]])
    obs |= {"eef_pos": np.array([0.3, 0.0, 1.0]), "object_mask": np.ones(2, np.float32),
            "object_poses": np.c_[origins, np.tile([0, 0, 0, 1], (2, 1))].astype(np.float32),
            "object_points": np.stack([_bowl_points(o) for o in origins])}
    assert held_object(obs) is None  # fingers open (the helper's 0.08 m)
    obs["gripper_qpos"] = np.array([0.004, -0.004], np.float32)
    points = held_object(obs)
    np.testing.assert_allclose(points, obs["object_points"][0] - obs["eef_pos"], atol=1e-6)  # the nearer one
    obs["object_poses"][0, :3] = [0.6, 0.6, 0.9]  # nothing within reach
    assert held_object(obs) is None
    del obs["object_points"]
    with pytest.raises(KeyError, match="object_points"):
        held_object(obs)


def test_held_object_cost_catches_a_carry_that_the_robot_points_miss():
    """The hand passes 8 cm beside the obstacle; the bowl it holds 6.5 cm to that side sweeps through it."""
    from detaug_gym.geometry import held_object_cost

    obs = _box_obs(np.array([0.0, 0.0, 1.0]), [0.03, 0.03, 0.08])
    obs |= {"eef_pos": np.array([0.3, -0.11, 1.0]), "object_mask": np.ones(1, np.float32),
            "gripper_qpos": np.array([0.004, -0.004], np.float32),
            "object_poses": np.array([[0.3, -0.045, 0.96, 0, 0, 0, 1]], np.float32),
            "object_points": _bowl_points(np.array([0.3, -0.045, 0.985]))[None]}
    x = torch.linspace(0.3, -0.3, 30, dtype=torch.float64)
    beside = torch.stack([x, torch.full_like(x, -0.11), torch.full_like(x, 1.0)], -1)  # (T, 3)
    away = beside - torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64)
    eef = torch.stack([beside, away])  # (B=2, T, 3)
    closed = torch.tensor([0.004, -0.004], dtype=torch.float64).expand(2, 30, 2)
    cost = held_object_cost(eef, closed, obs)
    assert cost.shape == (2,) and cost[0] > 0.1 and cost[1] == 0.0
    opened = closed.clone()
    opened[0, 10:] = torch.tensor([0.04, -0.04], dtype=torch.float64)  # let go before reaching the obstacle
    assert held_object_cost(eef, opened, obs)[0] == 0.0
    eef_grad = beside.clone().requires_grad_(True)
    held_object_cost(eef_grad, closed[0], obs).backward()
    assert eef_grad.grad[..., 1].sum() > 0  # descending it moves the hand (and bowl) to -y, away from the box
    obs["gripper_qpos"] = np.array([0.04, -0.04], np.float32)  # nothing held at the replan
    assert torch.equal(held_object_cost(eef, closed, obs), torch.zeros(2, dtype=torch.float64))
