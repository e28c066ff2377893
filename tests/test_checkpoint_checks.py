"""Checkpoints are checked at load (the file is named), record the suite they were trained on, and training
refuses non-finite demos with the file and demo named."""

import json
import shutil
import warnings

import h5py
import numpy as np
import pytest

from detaug_gym.models.checkpoint import CheckpointError, load_checkpoint
from detaug_gym.models.policy import FlowPolicy
from detaug_gym.rollout import EpisodeContext


def _copy(tiny_base_checkpoint, tmp_path):
    path = tmp_path / "ckpt"
    shutil.copytree(tiny_base_checkpoint[0], path)
    return path


def _edit(path, name, change):
    data = json.loads((path / name).read_text())
    (path / name).write_text(json.dumps(change(data)))


@pytest.mark.parametrize(("name", "change", "message"), [
    ("config.json", lambda c: [], "config.json .*JSON list"),
    ("config.json", lambda c: None, "config.json .*JSON NoneType"),
    ("config.json", lambda c: c | {"policy": {"action_steps": "5"}}, "action_steps must be an integer"),
    ("config.json", lambda c: c | {"policy": {"action_steps": 0}}, "action_steps must be an integer"),
    ("config.json", lambda c: c | {"obs_keys": ["robot_joint_pos", "teleport"]}, "unknown observation keys"),
    ("normalization.json", lambda n: n | {"obs": n["obs"] | {"center": n["obs"]["center"][:-1],
                                                            "scale": n["obs"]["scale"][:-1]}},
     "observation normaliser has"),
    ("normalization.json", lambda n: n | {"plan": n["plan"] | {"center": [float("nan")] * len(n["plan"]["center"])}},
     "corrupt checkpoint"),
])
def test_inconsistent_checkpoints_fail_at_load_naming_the_file(tiny_base_checkpoint, tmp_path, name, change, message):
    path = _copy(tiny_base_checkpoint, tmp_path)
    _edit(path, name, change)
    with pytest.raises(CheckpointError, match=message) as err:
        load_checkpoint(path)
    assert str(path) in str(err.value) and "python -m detaug_gym.train" in str(err.value)


def test_a_checkpoint_used_on_another_suite_warns_once(tiny_base_checkpoint, tmp_path):
    path = _copy(tiny_base_checkpoint, tmp_path)
    _edit(path, "config.json", lambda c: c | {"trained_on": {"suite": "spatial", "env_ids": ["x"]}})
    policy = FlowPolicy(path)
    goal = EpisodeContext("SafeLibero-Goal-L1-v0", "goal", "L1", 0, "bowl_on_plate", "put the bowl on the plate")
    with pytest.warns(UserWarning, match="trained on spatial demos"):
        policy.reset(seed=0, context=goal)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        policy.reset(seed=1, context=goal)  # once per policy
        policy.reset(seed=2, context=EpisodeContext("SafeLibero-Spatial-L1-v0", "spatial", "L1", 0, "k", "i"))


def test_training_on_nan_actions_names_the_file_and_demo(tmp_path):
    from detaug_gym.models.synthetic import write_synthetic_demos
    from detaug_gym.train import TrainConfig, train

    data = write_synthetic_demos(tmp_path / "demos.hdf5", n_demos=3, length=20)
    with h5py.File(data, "a") as f:
        actions = f["data/demo_1/actions"]
        values = actions[()]
        values[4, 2] = np.nan
        actions[...] = values
    with pytest.raises(SystemExit, match=r"demos.hdf5: data/demo_1 has non-finite values in actions"):
        train(TrainConfig(method="base", data=str(data), out=str(tmp_path / "out"), steps=2, progress=False))


def test_an_observation_of_another_size_is_a_clear_error(tiny_base_checkpoint):
    """An env whose observation is not the training env's (here one more task slot) is named key by key, not
    left to a numpy broadcast error deep in the normaliser."""
    path, obs = tiny_base_checkpoint
    policy = FlowPolicy(path)
    policy.reset(seed=0)
    policy.act(obs)
    wider = dict(obs, task_id=np.append(obs["task_id"], 0.0).astype(np.float32))
    n = len(obs["task_id"])
    policy.reset(seed=0)
    with pytest.raises(ValueError, match=rf"task_id {n + 1}.*trained on"):
        policy.act(wider)
