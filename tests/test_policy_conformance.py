"""Every registered policy, built the way the bench builds it, drives a real SafeLibero episode: actions are
float32 (7,), finite, inside [-1, 1], and a seeded reset replays the same actions."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import detaug_gym  # noqa: F401  (registers the env ids)
from detaug_gym.models.checkpoint import CheckpointError
from detaug_gym.policies import available_policies, load, make_policy, policy_class

ENV_ID = "SafeLibero-Spatial-L2-v0"
STEPS = 15  # covers a replan of every chunking policy (N = 10 for base/detaug/demogen, 2 for CAPE)
REPLAY = 5  # actions compared after the seeded reset
SEED = 7
SLOW = {"detaug": "K = 32 candidates scored per replan: ~30 s", "aegis": "loads torch, base and OSQP first: ~20 s"}
NAMES = [pytest.param(name, marks=pytest.mark.slow) if name in SLOW else name for name in available_policies()]


@pytest.fixture(scope="module")
def env():
    env = gym.make(ENV_ID, task=0)
    yield env
    env.close()


def _episode(env, policy, steps: int) -> list[np.ndarray]:
    obs, _ = env.reset(seed=SEED)
    policy.reset(seed=SEED)
    actions = []
    for _ in range(steps):
        action = policy.act(obs)
        actions.append(np.array(action, copy=True))
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
    return actions


@pytest.mark.parametrize("name", NAMES)
def test_policy_runs_a_real_episode_and_is_deterministic(env, name):
    policy = make_policy(name, suite="spatial")
    actions = _episode(env, policy, STEPS)
    assert len(actions) == STEPS
    for t, action in enumerate(actions):
        assert isinstance(action, np.ndarray) and action.dtype == np.float32 and action.shape == (7,), (t, action)
        assert np.all(np.isfinite(action)) and np.all(np.abs(action) <= 1.0), (t, action)
    again = _episode(env, policy, REPLAY)
    np.testing.assert_array_equal(np.stack(again), np.stack(actions[:REPLAY]))


def test_load_picks_the_class_of_the_checkpoint_method(tiny_base_checkpoint, tiny_detaug_checkpoint, tmp_path):
    base_path, _ = tiny_base_checkpoint
    detaug_path, _ = tiny_detaug_checkpoint
    assert type(load(base_path, action_steps=3)) is policy_class("base")
    assert load(base_path, action_steps=3).action_steps == 3
    detaug = load(detaug_path, k=4)
    assert type(detaug) is policy_class("detaug") and detaug.k == 4
    with pytest.raises(CheckpointError, match="python -m detaug_gym.train"):
        load(tmp_path / "nothing")
