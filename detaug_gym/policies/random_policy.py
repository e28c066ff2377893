"""Uniformly random actions: the floor every method must beat, and a cheap policy for harness tests."""

from __future__ import annotations

import numpy as np

from detaug_gym.actions import ACTION_DIM, GRIPPER_CLOSE, GRIPPER_OPEN
from detaug_gym.policies.options import RandomOptions


class RandomPolicy:
    """Samples each action uniformly from ``[-scale, scale]^6`` for the arm and ``{-1, +1}`` for the gripper.

    Args:
        scale: bound on the arm part of the action (``(0, 1]``).
        seed: default seed used when ``reset`` is called without one.
        suite: accepted (the bench passes it to every policy) and ignored.
    """

    def __init__(self, scale: float = 1.0, seed: int | None = None, suite: str | None = None) -> None:
        options = RandomOptions(scale=scale, seed=seed)
        self.scale = options.scale
        self._default_seed = options.seed
        self._rng = np.random.default_rng(options.seed)

    def reset(self, seed: int | None = None, context=None) -> None:
        self._rng = np.random.default_rng(self._default_seed if seed is None else seed)

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        action = np.empty(ACTION_DIM, dtype=np.float32)
        action[:6] = self._rng.uniform(-self.scale, self.scale, 6)
        action[6] = GRIPPER_CLOSE if self._rng.random() < 0.5 else GRIPPER_OPEN
        return action
