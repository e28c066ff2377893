"""The policy protocol every method implements, and the registry that builds policies by name.

A policy drives one environment. The bench (the only rollout loop in the project) calls::

    policy.reset(seed=seed, context=context)   # at the start of every episode
    action = policy.act(obs)                   # once per env step, obs is the env's Dict observation
    policy.episode_summary()                   # optional: a JSON-able dict for the episode's record

``context`` is the :class:`~detaug_gym.rollout.EpisodeContext` (env id, suite, level, task index, key and
instruction); a policy may ignore it, and one whose ``reset`` takes only ``seed`` still works.
``act`` returns one action in env units: ``np.ndarray`` of shape ``(7,)``, float32, OSC_POSE delta in
``[-1, 1]`` plus the gripper command (-1 open, +1 close).

Constructors take keyword options; the bench always passes ``suite=<suite name>`` (policies that do not
need it accept and ignore it) and a policy fails in its constructor, not mid-rollout, when misconfigured.

Chunking policies (the flow-matching ones) plan ``horizon`` steps, execute the first ``action_steps`` of
the plan from an internal queue and replan when the queue runs dry; ``reset`` clears the queue.

Methods register themselves with :func:`register_policy` using a *string* import path, so that
``import detaug_gym.policies`` stays light and torch/MuJoCo-heavy modules load only when a policy of
that kind is made.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Policy(Protocol):
    """What the bench needs from a policy."""

    def reset(self, seed: int | None = None, context=None) -> None:
        """Start a new episode; ``seed`` makes any sampling inside the policy reproducible, ``context``
        (an :class:`~detaug_gym.rollout.EpisodeContext` or None) says which task it is."""

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Return the next action, shape ``(7,)`` float32, for the observation of one env."""


@dataclass(frozen=True)
class PolicySpec:
    """A registry entry: ``entry_point`` is ``"module.path:ClassName"``, imported on first use."""

    name: str
    entry_point: str
    summary: str


_REGISTRY: dict[str, PolicySpec] = {}


def register_policy(name: str, entry_point: str, summary: str = "") -> None:
    """Register a policy class under ``name`` (lower case). Re-registering a name replaces it."""
    if ":" not in entry_point:
        raise ValueError(f"entry_point must look like 'package.module:ClassName', got {entry_point!r}")
    _REGISTRY[name.lower()] = PolicySpec(name.lower(), entry_point, summary)


def available_policies() -> list[str]:
    """Names accepted by :func:`make_policy`, sorted."""
    return sorted(_REGISTRY)


def policy_class(name: str) -> type:
    """Import and return the class registered under ``name``."""
    key = name.lower()
    if key not in _REGISTRY:
        raise KeyError(
            f"unknown policy {name!r}; registered policies: {', '.join(available_policies())}"
        )
    module_name, class_name = _REGISTRY[key].entry_point.split(":")
    return getattr(importlib.import_module(module_name), class_name)


def make_policy(name: str, **kwargs: Any) -> Policy:
    """Build the policy registered under ``name`` with ``kwargs`` (for example ``suite="spatial"``).

    Raises:
        KeyError: ``name`` is not registered; the message lists the registered names.
    """
    return policy_class(name)(**kwargs)
