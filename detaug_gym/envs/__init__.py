"""Registered gymnasium envs, one per (suite, level) of :data:`~detaug_gym.envs.suites.SUITES`. Importing this
module registers the ids; MuJoCo loads only at ``make``.

    SafeLibero-{Spatial,Object,Goal,Long}-{L1,L2,Free}-v0
    Newton-PickPlace-v0, Newton-PickPlace-Cylinder-v0

``gym.make(id, max_episode_steps=N)`` sets the step limit (the env's own and gymnasium's TimeLimit).
"""

from __future__ import annotations

import gymnasium as gym

from detaug_gym.envs.suites import SUITES, all_env_ids, get_suite, suite_of_env

SAFE_LIBERO_IDS: list[str] = [s.ids[lv] for s in SUITES.values() if s.name != "newton" for lv in s.levels]
NEWTON_IDS: list[str] = [SUITES["newton"].ids[lv] for lv in SUITES["newton"].levels]


def _register() -> None:
    for suite in SUITES.values():
        for level in suite.levels:
            env_id = suite.env_id(level)
            if env_id not in gym.registry:
                gym.register(
                    id=env_id,
                    entry_point=suite.entry_point,
                    kwargs=suite.env_kwargs(level),
                    max_episode_steps=suite.max_steps,
                    disable_env_checker=True,
                )


_register()

__all__ = ["NEWTON_IDS", "SAFE_LIBERO_IDS", "SUITES", "all_env_ids", "get_suite", "suite_of_env"]
