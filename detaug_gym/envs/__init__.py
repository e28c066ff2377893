"""Registered gymnasium envs. Importing this module registers the ids; MuJoCo loads only at ``make``.

    SafeLibero-{Spatial,Object,Goal,Long}-{L1,L2,Free}-v0
    Newton-PickPlace-v0, Newton-PickPlace-Cylinder-v0
"""

from __future__ import annotations

import gymnasium as gym

from detaug_gym.envs.suites import LEVELS, SUITES

SAFE_LIBERO_IDS: list[str] = []
NEWTON_IDS = ["Newton-PickPlace-v0", "Newton-PickPlace-Cylinder-v0"]


def safe_libero_id(suite: str, level: str) -> str:
    """``SafeLibero-<Suite>-<Level>-v0`` for a suite name and level."""
    return f"SafeLibero-{suite.capitalize()}-{level}-v0"


def _register() -> None:
    for suite in SUITES.values():
        for level in LEVELS:
            env_id = safe_libero_id(suite.name, level)
            SAFE_LIBERO_IDS.append(env_id)
            if env_id not in gym.registry:
                gym.register(
                    id=env_id,
                    entry_point="detaug_gym.envs.safe_libero:SafeLiberoEnv",
                    kwargs={"suite": suite.name, "level": level},
                    max_episode_steps=suite.max_steps,
                    disable_env_checker=True,
                )
    for env_id, cylinder in zip(NEWTON_IDS, (False, True)):
        if env_id not in gym.registry:
            gym.register(
                id=env_id,
                entry_point="detaug_gym.envs.newton:NewtonPickPlaceEnv",
                kwargs={"cylinder": cylinder},
                max_episode_steps=200,
                disable_env_checker=True,
            )


_register()

__all__ = ["NEWTON_IDS", "SAFE_LIBERO_IDS", "safe_libero_id"]
