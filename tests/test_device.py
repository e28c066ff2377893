"""``--device`` for train, bench and make_policy, on the CPU: the default and auto give the CPU path (the
same plans, the same checkpoint format), an absent CUDA device is a clear error before any work."""

import numpy as np
import pytest
import torch

from detaug_gym import bench
from detaug_gym.models.checkpoint import resolve_device
from detaug_gym.policies import make_policy, option_names
from detaug_gym.train import TrainConfig, train

NO_CUDA = not torch.cuda.is_available()


@pytest.fixture(scope="module")
def obs(spatial_l2_obs):
    return spatial_l2_obs


def test_auto_and_cpu_give_the_same_plans(obs):
    """``auto`` on a machine without CUDA is the CPU, and the plans are bit-identical to the default's."""
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    default, auto = make_policy("detaug", k=4), make_policy("detaug", k=4, device="auto")
    if NO_CUDA:
        assert auto.device == torch.device("cpu")
    plans = []
    for policy in (default, auto):
        policy.reset(seed=3)
        plans.append(policy.plan(obs, policy.sample_labels(obs, 4)).numpy())
    if NO_CUDA:
        np.testing.assert_array_equal(plans[0], plans[1])
    else:  # the same noise on both devices; kernels differ in rounding only
        np.testing.assert_allclose(plans[0], plans[1], atol=1e-3)


@pytest.mark.skipif(not NO_CUDA, reason="the machine has a CUDA device")
def test_a_missing_cuda_device_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match=r"device 'cuda' asked, but torch .* sees 0 CUDA device\(s\); use device=cpu"):
        make_policy("base", device="cuda")
    with pytest.raises(SystemExit, match="--device: device 'cuda:1' asked"):
        bench.run(bench.BenchConfig(methods=["base"], episodes=1, device="cuda:1", out=str(tmp_path / "b")))
    with pytest.raises(SystemExit, match="--device: device 'cuda' asked"):
        train(TrainConfig(data=__file__, out=str(tmp_path / "t"), device="cuda"))


def test_bad_device_names_are_refused_with_the_valid_ones(capsys):
    with pytest.raises(ValueError, match="device must be cpu, cuda, cuda:N or auto, got 'gpu'"):
        make_policy("base", device="gpu")
    with pytest.raises(SystemExit):
        bench.parse_config(["--device", "tpu"])
    assert "device must be cpu, cuda, cuda:N or auto, got 'tpu'" in capsys.readouterr().err


def test_the_bench_hands_the_device_to_flow_policies_only():
    """The bench passes --device to every method whose options take one (AEGIS: through the policy it wraps)."""
    assert {"device"} <= option_names("detaug") & option_names("cape") & option_names("aegis")
    assert "device" not in option_names("scripted") | option_names("aegis", {"base": "scripted"})
    key = bench.EpisodeKey("aegis", "SafeLibero-Spatial-L2-v0", 0, 0, 1)
    [record] = bench._run_group((bench.Job(key, "spatial", "2", env_kwargs=(("max_episode_steps", 3),),
                                           device="auto"),))
    assert record["termination"] != "error", record["error"]
    policy = bench._CACHE[("policy", "aegis", "spatial", "auto", 0)]
    assert policy.policy.device == resolve_device("auto")
    bench.close_cached()
