"""``base``: the flow policy trained on the unaugmented demos, with no label (the frozen prior of CAPE/AEGIS)."""

from __future__ import annotations

from pathlib import Path

from detaug_gym.models.policy import FlowPolicy, load_checkpoint, zoo_dir
from detaug_gym.policies.options import FlowOptions


class BaseFlowPolicy(FlowPolicy):
    """Loads ``policies/base/<suite>/`` (or ``checkpoint``) and plans without a label.

    Args:
        suite: zoo suite folder.
        checkpoint: a checkpoint folder instead of the zoo's.
        **options: :class:`~detaug_gym.models.policy.FlowPolicy` options (``action_steps``, ``flow_steps``, ...);
            all are :class:`~detaug_gym.policies.options.FlowOptions`.
    """

    zoo_method = "base"

    def __init__(self, suite: str = "spatial", checkpoint: str | Path | None = None, **options) -> None:
        opts = FlowOptions.from_kwargs(suite=suite, checkpoint=checkpoint, **options)
        super().__init__(load_checkpoint(opts.checkpoint or zoo_dir("base", opts.suite)), **opts.flow_policy_kwargs())
