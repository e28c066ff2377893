"""``demogen``: the flow policy trained on DemoGen data, conditioned on the obstacle's point cloud.

The checkpoint (``python -m detaug_gym.train --method demogen``) holds a DP3-style point encoder whose
embedding is added to the AdaLN conditioning; :class:`~detaug_gym.models.policy.FlowPolicy` feeds it the
observation's ``obstacle_points`` (256, 3) and ``obstacle_mask`` (1,) at every replan. A Free env reports
mask 0, which the encoder maps to a zero embedding (the conditioning of the unaugmented originals).
"""

from __future__ import annotations

from pathlib import Path

from detaug_gym.models.policy import FlowPolicy, load_checkpoint, zoo_dir
from detaug_gym.policies.options import DemoGenOptions


class DemoGenPolicy(FlowPolicy):
    """Loads ``policies/demogen/<suite>/`` (or ``checkpoint``); fails at construction on another method's folder.

    Args:
        suite: zoo suite folder.
        checkpoint: a checkpoint folder instead of the zoo's.
        **options: :class:`~detaug_gym.models.policy.FlowPolicy` options (``action_steps``, ``flow_steps``, ...);
            all are :class:`~detaug_gym.policies.options.DemoGenOptions`.
    """

    zoo_method = "demogen"

    def __init__(self, suite: str = "spatial", checkpoint: str | Path | None = None, **options) -> None:
        opts = DemoGenOptions.from_kwargs(suite=suite, checkpoint=checkpoint, **options)
        path = opts.checkpoint or zoo_dir("demogen", opts.suite)
        loaded = load_checkpoint(path)
        if loaded.method != "demogen":
            raise ValueError(f"{path} holds a {loaded.method!r} checkpoint; "
                             "the demogen policy needs one trained with --method demogen")
        super().__init__(loaded, **opts.flow_policy_kwargs())
