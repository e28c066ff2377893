"""The shared geometry on a real SafeLIBERO scene (one scene build, ~10-20 s)."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest
import torch

from detaug_gym.geometry import RobotGeometry, obstacle_sdf, plan_collision_cost

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def libero():
    env = gym.make("SafeLibero-Spatial-L2-v0", task=0).unwrapped
    obs, info = env.reset(seed=0)
    yield env, obs, info
    env.close()


def test_fk_of_the_scene_model_matches_mujoco(libero):
    env, _, _ = libero
    model, scene = env.scene.model, env.scene
    robot = RobotGeometry.from_model(model)
    data = mujoco.MjData(model)
    data.qpos[:] = scene.data.qpos
    rng = np.random.default_rng(0)
    ranges = model.jnt_range[[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"robot0_joint{i}")
                              for i in range(1, 8)]]
    for k in range(4):
        if k:  # the reset state first, then random arm configurations
            data.qpos[scene.arm_qpos] = rng.uniform(ranges[:, 0], ranges[:, 1])
        mujoco.mj_kinematics(model, data)
        out = robot.kinematics(torch.tensor(data.qpos[scene.arm_qpos]), torch.tensor(data.qpos[scene.gripper_qpos]))
        ids = robot.kinematics.link_body_ids
        np.testing.assert_allclose(out.positions.numpy(), data.xpos[ids], atol=1e-9)
        np.testing.assert_allclose(out.rotations.numpy(), data.xmat[ids].reshape(-1, 3, 3), atol=1e-9)
        np.testing.assert_allclose(out.eef_position.numpy(), data.site_xpos[scene.eef_site], atol=1e-9)


def test_default_panda_aligned_to_the_observation_matches_the_scene(libero):
    env, obs, _ = libero
    scene_robot = RobotGeometry.from_model(env.scene.model)
    aligned = RobotGeometry.panda().aligned_to(obs)
    q = torch.tensor(obs["robot_joint_pos"], dtype=torch.float64) + torch.linspace(-0.3, 0.3, 7, dtype=torch.float64)
    fingers = torch.tensor(obs["gripper_qpos"], dtype=torch.float64)
    torch.testing.assert_close(aligned.surface_points(q, fingers), scene_robot.surface_points(q, fingers),
                               atol=2e-4, rtol=0)  # float32 observations limit the base estimate


def test_obstacle_sdf_and_costs_on_the_observation(libero):
    env, obs, info = libero
    assert obs["obstacle_mask"][0] == 1.0
    sdf = obstacle_sdf({**obs, "obstacle_support_mask": np.zeros(1, np.float32)})  # the obstacle's own hull
    on_surface = sdf(torch.tensor(obs["obstacle_points"], dtype=torch.float64))
    assert on_surface.max() < sdf.grid.spacing  # on the hull (or inside it, from concave parts)
    # the hull is built from the exact local samples (obstacle_local_points); the world points are their float32
    # roundings, so they lie on or inside it to float32 precision
    assert np.all(sdf.exact(obs["obstacle_points"]) < 1e-6)
    centroid = torch.tensor(obs["obstacle_points"].mean(axis=0), dtype=torch.float64)
    assert sdf(centroid) < 0
    robot = RobotGeometry.from_model(env.scene.model)
    q = torch.tensor(obs["robot_joint_pos"], dtype=torch.float64)
    sdf = obstacle_sdf(obs)  # with what it stands on, as the env's clearance
    nearest = sdf(robot.surface_points(q, torch.tensor(obs["gripper_qpos"], dtype=torch.float64))).min().item()
    assert abs(nearest - info["min_clearance"]) < 0.05  # sampled robot surface vs the env's exact clearance
    plans = q + torch.zeros(32, 50, 7, dtype=torch.float64)
    cost = plan_collision_cost(plans, obs)
    assert cost.shape == (32,) and torch.all(cost == 0)  # the start pose is clear of the obstacle


def test_scorer_clearance_is_within_detaug_inflation_of_the_exact_one(libero):
    """Near the obstacle the scorer (SDF at the robot's surface points) may see more room than MuJoCo's exact
    distance, but never more than DetAug's ``inflate``: otherwise a plan that grazes the obstacle scores zero."""
    from detaug_gym.geometry import robot_clearance
    from detaug_gym.policies.options import DetAugOptions

    env, obs, info = libero
    scene = env.scene
    obstacle = scene.obstacles[info["obstacle"]].geom_ids
    start = env.get_state()
    rng = np.random.default_rng(0)
    errors = []
    centre = obs["obstacle_pose"][:3].astype(np.float64)
    try:
        for _ in range(400):
            q = obs["robot_joint_pos"] + rng.normal(0.0, 0.35, 7)
            scene.data.qpos[scene.arm_qpos] = q
            mujoco.mj_forward(scene.model, scene.data)
            if np.linalg.norm(scene.eef_pose()[0] - centre) > 0.25:
                continue
            exact = scene.min_distance(obstacle)
            if 0.0 < exact < 0.04:
                now = {**env.observe(), "obstacle_support_mask": np.zeros(1, np.float32)}  # the obstacle's part
                sdf = obstacle_sdf(now)
                errors.append(float(robot_clearance(torch.as_tensor(q), now, sdf)) - exact)
    finally:
        env.set_state(start)
    assert len(errors) >= 10, f"only {len(errors)} near-obstacle samples"
    errors = np.array(errors)
    assert errors.max() < DetAugOptions().inflate, f"scorer saw up to {errors.max():.4f} m more room"
    assert errors.min() > -0.02  # and it does not invent contact where there is 2 cm of room


def test_the_base_under_a_calibrated_obstacle_is_part_of_the_scorer_view():
    """-v2 obstacles stand on SafeLIBERO's bases, and knocking the base moves the obstacle. The observation
    shows the base (``obstacle_support_*``) and the SDF every scorer uses includes it: where the robot is nearer
    the base than the obstacle, the scorer's clearance is within DetAug's ``inflate`` of MuJoCo's exact one,
    while the obstacle alone would have seen several centimetres more room."""
    from detaug_gym.geometry import robot_clearance
    from detaug_gym.policies.options import DetAugOptions

    env = gym.make("SafeLibero-Spatial-L2-v2", task=0).unwrapped
    obs, info = env.reset(seed=0)
    scene = env.scene
    assert info["obstacle_raised"] and obs["obstacle_support_mask"][0] == 1.0
    base = next(b for b in scene.bases.values()
                if np.allclose(scene.data.xpos[b.body_id], obs["obstacle_support_pose"][:3], atol=1e-4))
    obstacle = scene.obstacles[info["obstacle"]].geom_ids
    rng, near_base, blind = np.random.default_rng(1), [], []
    centre = obs["obstacle_support_pose"][:3].astype(np.float64)
    for _ in range(3000):
        scene.data.qpos[scene.arm_qpos] = obs["robot_joint_pos"] + rng.normal(0.0, 0.6, 7)
        mujoco.mj_forward(scene.model, scene.data)
        if np.linalg.norm(scene.eef_pose()[0] - centre) > 0.25:
            continue
        to_base, to_obstacle = scene.min_distance(base.geom_ids), scene.min_distance(obstacle)
        if not 0.0 < to_base < min(to_obstacle, 0.04):
            continue
        now = env.observe()
        q = torch.as_tensor(now["robot_joint_pos"], dtype=torch.float64)
        near_base.append(float(robot_clearance(q, now, obstacle_sdf(now))) - to_base)
        alone = {**now, "obstacle_support_mask": np.zeros(1, np.float32)}
        blind.append(float(robot_clearance(q, alone, obstacle_sdf(alone))) - to_base)
    env.close()
    assert len(near_base) >= 5, f"only {len(near_base)} samples near the base"
    assert max(near_base) < DetAugOptions().inflate and min(near_base) > -0.02
    assert max(blind) > 0.03  # without the support the scorer misses the base
