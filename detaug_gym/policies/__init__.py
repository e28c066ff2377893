"""Policy zoo: every method behind one ``reset(seed)`` / ``act(obs)`` protocol.

>>> from detaug_gym.policies import make_policy, available_policies
>>> policy = make_policy("random")
"""

from detaug_gym.policies.base import (
    Policy,
    PolicySpec,
    available_policies,
    make_policy,
    policy_class,
    register_policy,
)

register_policy("random", "detaug_gym.policies.random_policy:RandomPolicy", "uniform random actions")
register_policy("scripted", "detaug_gym.policies.scripted:ScriptedExpert", "privileged scripted pick-and-place expert")

__all__ = [
    "Policy",
    "PolicySpec",
    "available_policies",
    "make_policy",
    "policy_class",
    "register_policy",
]
