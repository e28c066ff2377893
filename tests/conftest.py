"""Shared fixtures: building a LIBERO scene costs seconds, so env fixtures are module-scoped; tiny flow
checkpoints (synthetic demos, a few dozen steps) are trained once per session and shared."""

import os

import numpy as np
import pytest
from hypothesis import settings

# The same hypothesis examples every run (a fixed seed per test), so CI cannot turn red on a new random draw;
# an edge case found by exploring goes in as an @example.
settings.register_profile("derandomized", derandomize=True)
settings.load_profile("derandomized")

os.environ.setdefault("MUJOCO_GL", "egl")

TINY = dict(horizon=10, steps_per_token=2, d_model=32, layers=1, heads=2, obs_tokens=1, batch_size=32,
            warmup_steps=5, lr=2e-3, threads=1, progress=False, log_every=50, checkpoint_every=1000)


def train_tiny(root, method: str, steps: int, label_dim: int = 0):
    """Train a tiny ``method`` checkpoint on 8 synthetic demos; returns (checkpoint dir, first observation)."""
    from detaug_gym.models.dataset import read_demos
    from detaug_gym.models.synthetic import write_synthetic_demos
    from detaug_gym.train import TrainConfig, train

    data = write_synthetic_demos(root / "demos.hdf5", n_demos=8, length=24, label_dim=label_dim)
    cfg = TrainConfig(method=method, data=str(data), out=str(root / "policy"), steps=steps, **TINY)
    train(cfg)
    demo = read_demos(str(data))[0]
    return cfg.out, {key: np.asarray(value[0], np.float32) for key, value in demo.obs.items()}


@pytest.fixture(scope="session")
def tiny_base_checkpoint(tmp_path_factory):
    """A tiny ``base`` checkpoint (no label): the frozen prior of the AEGIS and CAPE tests."""
    return train_tiny(tmp_path_factory.mktemp("tiny_base"), "base", steps=40)


@pytest.fixture(scope="session")
def tiny_detaug_checkpoint(tmp_path_factory):
    """A tiny ``detaug`` checkpoint with 4-dim labels."""
    return train_tiny(tmp_path_factory.mktemp("tiny_detaug"), "detaug", steps=60, label_dim=4)


@pytest.fixture(scope="session")
def spatial_l2_obs():
    """The first observation of a real SafeLibero-Spatial-L2 episode (task 0, seed 5), obstacle in view."""
    import gymnasium as gym

    import detaug_gym  # noqa: F401  (registers the envs)

    env = gym.make("SafeLibero-Spatial-L2-v0")
    first, _ = env.reset(seed=5, options={"task": 0})
    env.close()
    return first
