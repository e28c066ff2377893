"""Policy zoo: every method behind one ``reset(seed)`` / ``act(obs)`` protocol.

>>> from detaug_gym.policies import make_policy, available_policies, load, parse_policy_options
>>> policy = make_policy("random")
>>> policy = make_policy("detaug", suite="spatial", k=32)      # policies/detaug/spatial/
>>> policy = load("policies/base/spatial", action_steps=5)      # the class from the checkpoint's method
>>> parse_policy_options("detaug", {"k": "8", "latch": "false"})  # checked without torch
{'k': 8, 'latch': False}

Each policy's options are a dataclass in :mod:`detaug_gym.policies.options`.
"""

from detaug_gym.policies.base import (
    Policy,
    PolicySpec,
    act_batch,
    available_policies,
    load,
    make_policy,
    option_names,
    parse_policy_options,
    policy_class,
    policy_options_class,
    register_policy,
    share_planner,
)

_OPTIONS = "detaug_gym.policies.options"
register_policy("random", "detaug_gym.policies.random_policy:RandomPolicy", "uniform random actions",
                options=f"{_OPTIONS}:RandomOptions")
register_policy("scripted", "detaug_gym.policies.scripted:ScriptedExpert", "privileged scripted pick-and-place expert",
                options=f"{_OPTIONS}:ScriptedOptions")
register_policy("base", "detaug_gym.policies.flow_base:BaseFlowPolicy", "flow policy on unaugmented demos, no label",
                options=f"{_OPTIONS}:FlowOptions")
register_policy("detaug", "detaug_gym.policies.detaug:DetAugPolicy", "DetAug: K-label selection by collision cost",
                options=f"{_OPTIONS}:DetAugOptions")
register_policy("aegis", "detaug_gym.policies.aegis:AegisPolicy", "AEGIS: CBF-QP safety filter around another policy",
                options=f"{_OPTIONS}:AegisOptions")
register_policy("cape", "detaug_gym.policies.cape:CapePolicy", "CAPE: re-noise the plan remainder, collision guidance",
                options=f"{_OPTIONS}:CapeOptions")
register_policy("demogen", "detaug_gym.policies.demogen:DemoGenPolicy", "DemoGen: obstacle-cloud flow policy",
                options=f"{_OPTIONS}:DemoGenOptions")

__all__ = [
    "Policy",
    "PolicySpec",
    "act_batch",
    "available_policies",
    "load",
    "make_policy",
    "option_names",
    "parse_policy_options",
    "policy_class",
    "policy_options_class",
    "register_policy",
    "share_planner",
]
