"""The policy protocol every method implements, and the registry that builds policies by name.

A policy drives one environment. The bench (the only rollout loop in the project) calls::

    policy.reset(seed=seed, context=context)   # at the start of every episode
    action = policy.act(obs)                   # once per env step, obs is the env's Dict observation
    policy.episode_summary()                   # optional: a JSON-able dict for the episode's record
    policy.belief(obs)                         # optional: what it expected of its last action (a plan's
                                               # joints, a predicted cost) and how it judges obs, the state
                                               # that action led to; read at the first collision
    policy.share_planner(batcher)              # optional: plan through a shared PlanBatcher (flow policies;
                                               # a wrapper such as AEGIS hands it to the policy it wraps)

``context`` is the :class:`~detaug_gym.rollout.EpisodeContext` (env id, suite, level, task index, key and
instruction); a policy may ignore it, and one whose ``reset`` takes only ``seed`` still works.
``act`` returns one action in env units: ``np.ndarray`` of shape ``(7,)``, float32, OSC_POSE delta in
``[-1, 1]`` plus the gripper command (-1 open, +1 close).

Constructors take keyword options; the bench always passes ``suite=<suite name>`` (policies that do not
need it accept and ignore it) and a policy fails in its constructor, not mid-rollout, when misconfigured.

Chunking policies (the flow-matching ones) plan ``horizon`` steps, execute the first ``action_steps`` of
the plan from an internal queue and replan when the queue runs dry; ``reset`` clears the queue.

A policy object is one episode's state. Several envs stepped together (the bench's ``--envs-per-worker``) use
one policy object each and :func:`act_batch`: with a shared :class:`~detaug_gym.models.batching.PlanBatcher`,
the policies that replan at the same step integrate their plans in one batched network call; a policy
without ``share_planner`` simply acts on its own.

Methods register themselves with :func:`register_policy` using a *string* import path, so that
``import detaug_gym.policies`` stays light and torch/MuJoCo-heavy modules load only when a policy of
that kind is made. The entry also names the policy's options dataclass (:mod:`detaug_gym.policies.options`),
so :func:`parse_policy_options` can turn ``name:key=value`` strings into checked, typed options without
importing the policy.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from detaug_gym.config import check_value, config_fields, convert


@runtime_checkable
class Policy(Protocol):
    """What the bench needs from a policy."""

    def reset(self, seed: int | None = None, context=None) -> None:
        """Start a new episode; ``seed`` makes any sampling inside the policy reproducible, ``context``
        (an :class:`~detaug_gym.rollout.EpisodeContext` or None) says which task it is."""

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Return the next action, shape ``(7,)`` float32, for the observation of one env."""


def act_batch(policies: Sequence[Policy], observations: Sequence[dict[str, np.ndarray]],
              batcher=None) -> list[np.ndarray | BaseException]:
    """One action per (policy, observation) pair: ``policies[i].act(observations[i])``.

    With ``batcher`` (a :class:`~detaug_gym.models.batching.PlanBatcher` the policies were given with
    ``share_planner``) the calls run together and their replans share network calls. An ``act`` that raises
    gives its exception in its place, so one broken episode does not stop the others.
    """
    if batcher is None or len(policies) == 1:
        out: list[np.ndarray | BaseException] = []
        for policy, obs in zip(policies, observations):
            try:
                out.append(policy.act(obs))
            except Exception as exc:  # noqa: BLE001  (recorded by the caller)
                out.append(exc)
        return out
    return batcher.run_all([partial(policy.act, obs) for policy, obs in zip(policies, observations)])


def share_planner(policy: Policy, batcher) -> bool:
    """Give ``policy`` the shared ``batcher`` when it plans with a network; returns whether it took it."""
    hook = getattr(policy, "share_planner", None)
    if callable(hook):
        hook(batcher)
    return callable(hook)


@dataclass(frozen=True)
class PolicySpec:
    """A registry entry: ``entry_point`` is ``"module.path:ClassName"``, imported on first use; ``options``
    (``"module.path:ClassName"`` of a dataclass, or ``None``) declares the constructor's options."""

    name: str
    entry_point: str
    summary: str
    options: str | None = None


_REGISTRY: dict[str, PolicySpec] = {}


def register_policy(name: str, entry_point: str, summary: str = "", options: str | None = None) -> None:
    """Register a policy class under ``name`` (lower case). Re-registering a name replaces it.

    Args:
        entry_point: ``"package.module:ClassName"`` of the policy.
        summary: one line for listings.
        options: ``"package.module:ClassName"`` of the dataclass of its options (a light module: no torch),
            used by :func:`parse_policy_options`; ``None`` for a policy that takes none.
    """
    for what, path in (("entry_point", entry_point), ("options", options)):
        if path is not None and ":" not in path:
            raise ValueError(f"{what} must look like 'package.module:ClassName', got {path!r}")
    _REGISTRY[name.lower()] = PolicySpec(name.lower(), entry_point, summary, options)


def available_policies() -> list[str]:
    """Names accepted by :func:`make_policy`, sorted."""
    return sorted(_REGISTRY)


def _spec(name: str) -> PolicySpec:
    key = name.lower()
    if key not in _REGISTRY:
        raise KeyError(
            f"unknown policy {name!r}; registered policies: {', '.join(available_policies())}"
        )
    return _REGISTRY[key]


def _import(path: str) -> Any:
    module_name, attr = path.split(":")
    return getattr(importlib.import_module(module_name), attr)


def policy_class(name: str) -> type:
    """Import and return the class registered under ``name``."""
    return _import(_spec(name).entry_point)


def policy_options_class(name: str) -> type | None:
    """The options dataclass registered with ``name`` (imports only its light module), or ``None``."""
    spec = _spec(name)
    return None if spec.options is None else _import(spec.options)


def option_names(name: str, options: Mapping[str, Any] | None = None) -> set[str]:
    """The option keys policy ``name`` takes given ``options``: its dataclass's fields and, for a wrapping
    policy (AEGIS), those of the policy it wraps (``options`` may name which)."""
    cls = policy_options_class(name)
    if cls is None:
        return set()
    fields = config_fields(cls)
    names = set(fields)
    if cls.WRAPS:
        wrapped = (options or {}).get(cls.WRAPS, fields[cls.WRAPS][0].default)
        names |= option_names(str(wrapped))
    return names


def parse_policy_options(name: str, raw: Mapping[str, Any]) -> dict[str, Any]:
    """Check and convert a policy's options without building it: ``("detaug", {"k": "8", "latch": "no"})``
    -> ``{"k": 8, "latch": False}``.

    String values are converted by the declared field types (:func:`detaug_gym.config.convert`: ints
    reject ``"2.5"``, bools take true/false, 1/0, yes/no in any case, ``none`` for optional fields, tuple
    items separated by spaces); other values must already have the declared type. The options dataclass
    is then built, so its ``__post_init__`` range checks run too. ``suite`` (which the bench passes to every
    policy) is accepted even where the dataclass has no such field. A wrapping policy (AEGIS, ``WRAPS``)
    hands the options that are not its own to the policy it wraps, and those are checked the same way.

    Returns:
        the given options only, converted (pass them on with ``make_policy(name, suite=..., **options)``).
    Raises:
        KeyError: ``name`` (or a wrapped policy's name) is not registered.
        ValueError: an unknown key (the message lists the valid ones), a value of the wrong type, or one
            that fails a range check.
    """
    cls = policy_options_class(name)
    if cls is None:
        if set(raw) - {"suite"}:
            raise ValueError(f"{name} declares no options (register_policy(..., options=...)); got "
                             f"{', '.join(sorted(raw))}")
        return dict(raw)
    fields = config_fields(cls)
    own = {key: value for key, value in raw.items() if key in fields or key == "suite"}
    rest = {key: value for key, value in raw.items() if key not in own}
    parsed = {key: _convert_option(name, key, value, fields[key][1]) for key, value in own.items() if key in fields}
    wrapped = parsed.get(cls.WRAPS, fields[cls.WRAPS][0].default) if cls.WRAPS else None
    if wrapped is not None:
        _spec(wrapped)  # a KeyError listing the registered names
    if rest:
        inner = None if wrapped is None else policy_options_class(wrapped)
        inner_names = [] if inner is None else list(config_fields(inner))
        unknown = [key for key in rest if key not in inner_names]
        if unknown:
            valid = ", ".join(sorted(fields))
            if wrapped is not None:
                valid += f"; or an option of the wrapped {wrapped}: {', '.join(sorted(inner_names)) or 'none'}"
            raise ValueError(f"unknown option {unknown[0]!r} for {name}; valid: {valid}")
    cls(**parsed)  # the range checks of __post_init__
    if rest:
        inner_raw = dict(rest, **({"suite": own["suite"]} if "suite" in own else {}))
        parsed.update({k: v for k, v in parse_policy_options(wrapped, inner_raw).items() if k != "suite"})
    if "suite" in own and "suite" not in fields:
        parsed["suite"] = str(own["suite"])
    return parsed


def _convert_option(policy: str, key: str, value: Any, kind) -> Any:
    try:
        return convert(value, kind, key) if isinstance(value, str) else check_value(value, kind, key)
    except ValueError as err:
        raise ValueError(f"{policy}: {err}") from None


def make_policy(name: str, **kwargs: Any) -> Policy:
    """Build the policy registered under ``name`` with ``kwargs`` (for example ``suite="spatial"``).

    Raises:
        KeyError: ``name`` is not registered; the message lists the registered names.
    """
    return policy_class(name)(**kwargs)


def load(path: str | Path, **options: Any) -> Policy:
    """The policy for a trained checkpoint folder (``policies/<method>/<suite>/``): the registered policy of the
    method it was trained with (``base``, ``detaug`` or ``demogen``), built with ``options``. The one loader;
    ``make_policy(name, checkpoint=path)`` builds a chosen method (``cape``, ``aegis``) on a folder instead.

    Raises:
        CheckpointError: no readable checkpoint at ``path`` (the message names the train command).
    """
    from detaug_gym.models.checkpoint import CheckpointError, read_config

    method = read_config(path).get("method")
    if not isinstance(method, str) or method.lower() not in _REGISTRY:
        raise CheckpointError(f"{path} was trained with method {method!r}, which no registered policy loads; "
                              f"registered policies: {', '.join(available_policies())}")
    return make_policy(method, checkpoint=str(path), **options)
