"""Stable-Baselines3 adapter: evaluate any registered policy with ``evaluate_policy``.

>>> from stable_baselines3.common.evaluation import evaluate_policy
>>> mean, std = evaluate_policy(SB3Adapter(make_policy("random")), env, n_eval_episodes=5)
"""

from __future__ import annotations

import numpy as np

from detaug_gym.policies.base import Policy


class SB3Adapter:
    """Gives a detaug_gym policy SB3's ``predict(obs, state, episode_start, deterministic)`` signature.

    SB3 evaluates vectorised envs, so ``obs`` is a dict of batched arrays ``(N, ...)``; one wrapped policy
    per env index is kept (created with ``factory`` where several envs run in parallel), and each is reset
    when its ``episode_start`` flag is set.

    Args:
        policy: the policy for env 0.
        factory: ``() -> Policy`` for the other envs of a ``VecEnv`` with ``num_envs > 1``.
        seed: base seed; env ``i``'s policy is reset with ``seed + episodes_started``.
    """

    def __init__(self, policy: Policy, factory=None, seed: int = 0) -> None:
        self._policies = [policy]
        self._factory = factory
        self._seed = seed
        self._episodes = 0

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = False):
        first = next(iter(observation.values()))
        n = first.shape[0]
        while len(self._policies) < n:
            if self._factory is None:
                raise ValueError(f"{n} envs need a policy factory; pass factory=lambda: make_policy(...)")
            self._policies.append(self._factory())
        starts = np.ones(n, dtype=bool) if episode_start is None else np.asarray(episode_start, dtype=bool)
        actions = np.empty((n, 7), dtype=np.float32)
        for i in range(n):
            if starts[i]:
                self._policies[i].reset(seed=self._seed + self._episodes)
                self._episodes += 1
            actions[i] = self._policies[i].act({k: v[i] for k, v in observation.items()})
        return actions, state
