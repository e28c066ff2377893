"""CAPE on a tiny synthetic-data checkpoint: the sphere cost, guidance lowering it, the re-noise schedule."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from detaug_gym.geometry import RobotGeometry, obstacle_sdf, plan_collision_cost
from detaug_gym.models.checkpoint import CheckpointError
from detaug_gym.models.flow import Guidance
from detaug_gym.policies import available_policies, make_policy
from detaug_gym.policies.cape import CapePolicy


@pytest.fixture(scope="module")
def checkpoint(tiny_base_checkpoint):
    return tiny_base_checkpoint


def with_obstacle_near_hand(obs, shift=(0.0, 0.0, -0.03), half=0.05):
    """A box of half-width ``half`` around (slightly below) the hand: plans start in collision."""
    robot = RobotGeometry.panda().aligned_to(obs)
    hand = robot.kinematics(torch.as_tensor(obs["robot_joint_pos"], dtype=torch.float64)[None]).eef_position[0]
    centre = hand.numpy() + np.asarray(shift)
    corners = np.array(np.meshgrid(*[[-half, half]] * 3)).reshape(3, -1).T
    points = centre + np.concatenate([corners, np.random.default_rng(0).uniform(-half, half, (248, 3))])
    return dict(obs, obstacle_points=points.astype(np.float32), obstacle_mask=np.ones(1, np.float32),
                obstacle_pose=np.r_[centre, 0, 0, 0, 1].astype(np.float32), obstacle_size=np.full(3, half, np.float32))


def test_registered_and_acts(checkpoint):
    path, obs = checkpoint
    assert "cape" in available_policies()
    policy = make_policy("cape", suite="spatial", checkpoint=path, track_cost=True, seed=0)
    assert isinstance(policy, CapePolicy) and policy.prefix_steps == 2
    policy.reset(seed=0)
    for observation in (obs, with_obstacle_near_hand(obs), with_obstacle_near_hand(obs)):
        for _ in range(2):
            action = policy.act(observation)
            assert action.shape == (7,) and action.dtype == np.float32 and np.all(np.isfinite(action))
    assert [step.fresh for step in policy.diagnostics] == [True, False, False]  # then re-noise every 2 steps
    assert [step.guided for step in policy.diagnostics] == [False, True, True]
    assert policy.diagnostics[0].cost == 0.0 and policy.diagnostics[1].cost > 0.0
    policy.reset(seed=0)
    policy.act(obs)
    assert [step.fresh for step in policy.diagnostics] == [True]


def test_state_term_is_the_shared_sphere_cost(checkpoint):
    path, obs = checkpoint
    obs = with_obstacle_near_hand(obs)
    policy = CapePolicy(checkpoint=path, guide="states", seed=0)
    plans = policy.plan(obs, None, num_samples=3).double()
    ours = policy.cost_function(obs)(plans, 1.0)
    shared = plan_collision_cost(plans[..., policy.layout.key_slice("robot_joint_pos")], obs, kind="spheres",
                                 margin=policy.margin)
    torch.testing.assert_close(ours, shared)
    assert torch.all(ours > 0)


def test_action_term_pushes_the_executed_actions(checkpoint):
    path, obs = checkpoint
    obs = with_obstacle_near_hand(obs)
    policy = CapePolicy(checkpoint=path, guide="actions", seed=0)
    plans = policy.plan(obs, None, num_samples=2).requires_grad_(True)
    policy.cost_function(obs)(plans, 1.0).sum().backward()
    grad = plans.grad[..., policy.layout.action_slice]
    assert grad[..., :-1, :3].abs().sum() > 0  # position commands are moved
    assert grad[..., 3:].abs().sum() == 0  # rotation and gripper are not
    assert plans.grad[..., policy.layout.key_slice("robot_joint_pos")].abs().sum() == 0


@pytest.mark.parametrize("guide", ["both", "actions"])
def test_guidance_lowers_the_cost_of_a_colliding_plan(checkpoint, guide):
    path, obs = checkpoint
    obs = with_obstacle_near_hand(obs)
    policy = CapePolicy(checkpoint=path, guide=guide, seed=0)
    cost = policy.cost_function(obs)
    seeds = range(4)

    def plans(guidance, **kwargs):
        return torch.cat([policy.plan(obs, None, num_samples=4, guidance=guidance,
                                      generator=torch.Generator().manual_seed(s), **kwargs) for s in seeds])

    guidance = Guidance(cost, scale=policy.guidance_scale, t_min=policy.guidance_t_min)
    plain, guided = plans(None), plans(guidance)
    assert cost(guided, 1.0).mean() < cost(plain, 1.0).mean()
    # CAPE's refine: re-noise the same remainders to t = 0.92 and denoise with vs without guidance
    remainder = plain[:4]

    def refine(guidance):
        return policy.plan(obs, None, num_samples=4, init_plan=remainder, t_start=0.92, guidance=guidance,
                           generator=torch.Generator().manual_seed(9))

    plain_refined, refined = refine(None), refine(guidance)
    assert cost(refined, 1.0).mean() < cost(plain_refined, 1.0).mean()


def test_gradient_step_on_a_fixed_plan_lowers_the_cost(checkpoint):
    path, obs = checkpoint
    obs = with_obstacle_near_hand(obs)
    policy = CapePolicy(checkpoint=path, seed=0)
    cost = policy.cost_function(obs)
    plan = policy.plan(obs, None, num_samples=1).double().requires_grad_(True)
    before = cost(plan, 1.0).sum()
    (grad,) = torch.autograd.grad(before, plan)
    after = cost(plan.detach() - 1e-2 * grad, 1.0).sum()
    assert before > 0 and after < before


def test_no_obstacle_no_guidance(checkpoint):
    path, obs = checkpoint
    policy = CapePolicy(checkpoint=path, seed=0)
    assert policy.cost_function(obs) is None  # synthetic obs carry no obstacle keys
    assert policy.cost_function(dict(with_obstacle_near_hand(obs), obstacle_mask=np.zeros(1, np.float32))) is None
    assert obstacle_sdf(with_obstacle_near_hand(obs)).empty is False


@pytest.mark.parametrize("options", [dict(t_start=1.0), dict(t_start=0.0), dict(guide="joints"),
                                     dict(prefix_steps=0), dict(prefix_steps=10), dict(sphere_radius=0.0),
                                     dict(action_steps=4), dict(refine_steps=0), dict(guidance_t_min=1.5)])
def test_bad_options_fail_at_construction(checkpoint, options):
    path, _ = checkpoint
    with pytest.raises(ValueError):
        CapePolicy(checkpoint=path, **options)


def test_missing_checkpoint_fails_at_construction(tmp_path):
    with pytest.raises(CheckpointError, match="python -m detaug_gym.train"):
        make_policy("cape", suite="spatial", checkpoint=str(tmp_path / "nothing"))
