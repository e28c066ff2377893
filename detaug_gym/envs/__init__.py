"""Registered gymnasium envs, one per (suite, level) of :data:`~detaug_gym.envs.suites.SUITES`. Importing this
module registers the ids; MuJoCo loads only at ``make``.

    SafeLibero-{Spatial,Object,Goal,Long}-{L1,L2}-v2   procedural scenarios calibrated to the official ones
    SafeLibero-{Spatial,Object,Goal,Long}-Free-v0      no obstacle (LIBERO's scenes)
    SafeLibero-{Spatial,Object,Goal,Long}-{L1,L2}-v1   calibrated spots on LIBERO's unedited layouts (kept)
    SafeLibero-{Spatial,Object,Goal,Long}-{L1,L2}-v0   the procedural scenarios before the calibration (kept)
    Newton-PickPlace-v0, Newton-PickPlace-Cylinder-v0

``gym.make(id, max_episode_steps=N)`` sets the step limit (the env's own and gymnasium's TimeLimit).
"""

from __future__ import annotations

import gymnasium as gym

from detaug_gym.envs.suites import SUITES, all_env_ids, get_suite, suite_of_env

SAFE_LIBERO_IDS: list[str] = [i for s in SUITES.values() if s.name != "newton" for i, _, _ in s.registered()]
NEWTON_IDS: list[str] = [i for i, _, _ in SUITES["newton"].registered()]


def _register() -> None:
    for suite in SUITES.values():
        for env_id, level, version in suite.registered():
            if env_id not in gym.registry:
                gym.register(
                    id=env_id,
                    entry_point=suite.entry_point,
                    kwargs=suite.env_kwargs(level, version),
                    max_episode_steps=suite.max_steps,
                    disable_env_checker=True,
                )


_register()

__all__ = ["NEWTON_IDS", "SAFE_LIBERO_IDS", "SUITES", "all_env_ids", "get_suite", "suite_of_env"]
