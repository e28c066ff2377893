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
register_policy("base", "detaug_gym.policies.flow_base:BaseFlowPolicy", "flow policy on unaugmented demos, no label")
register_policy("detaug", "detaug_gym.policies.detaug:DetAugPolicy", "DetAug: K-label selection by collision cost")
register_policy("aegis", "detaug_gym.policies.aegis:AegisPolicy", "AEGIS: CBF-QP safety filter around another policy")
register_policy("cape", "detaug_gym.policies.cape:CapePolicy", "CAPE: re-noise the plan remainder, collision guidance")
register_policy("demogen", "detaug_gym.policies.demogen:DemoGenPolicy", "DemoGen: obstacle-cloud flow policy")


def load(path, **options):
    """A policy for a trained checkpoint folder (``policies/<method>/<suite>/``)."""
    from detaug_gym.policies.flow_base import load as load_flow

    return load_flow(path, **options)

__all__ = [
    "Policy",
    "PolicySpec",
    "available_policies",
    "load",
    "make_policy",
    "policy_class",
    "register_policy",
]
