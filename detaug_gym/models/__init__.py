"""Flow-matching DiT policies: network blocks, flow matching, data windows, checkpoints and inference.

>>> from detaug_gym.models import FlowPolicy, load_checkpoint
>>> policy = FlowPolicy(load_checkpoint("policies/base/spatial"))   # made by python -m detaug_gym.train
>>> policy.reset(seed=0); action = policy.act(obs)

To run a trained method use ``detaug_gym.policies.load(path)`` (the class from the checkpoint's method) or
``detaug_gym.policies.make_policy(name, checkpoint=path)``.
"""

from detaug_gym.models.checkpoint import Checkpoint, CheckpointError, LabelSupport, load_checkpoint
from detaug_gym.models.dataset import OBS_KEYS, PLAN_STATE_KEYS, PlanLayout, WindowDataset, read_demos
from detaug_gym.models.dit import DiT, DiTConfig
from detaug_gym.models.flow import Guidance, Inpaint, flow_matching_loss, sample
from detaug_gym.models.network import FlowNetwork, NetworkConfig
from detaug_gym.models.normalize import Normalizer
from detaug_gym.models.pointcloud import PointCloudEncoder
from detaug_gym.models.policy import FlowPolicy, shift_plan, zoo_dir

__all__ = [
    "OBS_KEYS",
    "PLAN_STATE_KEYS",
    "Checkpoint",
    "CheckpointError",
    "DiT",
    "DiTConfig",
    "FlowNetwork",
    "FlowPolicy",
    "Guidance",
    "Inpaint",
    "LabelSupport",
    "NetworkConfig",
    "Normalizer",
    "PlanLayout",
    "PointCloudEncoder",
    "WindowDataset",
    "flow_matching_loss",
    "load_checkpoint",
    "read_demos",
    "sample",
    "shift_plan",
    "zoo_dir",
]
