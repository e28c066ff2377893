"""Batched inference across envs (``--envs-per-worker``): the records of one episode at a time for the same
seeds (to float32 rounding: a row's matmul result can depend on its place in the batch), plans of several
policies in one network call, a failing episode that stops no other."""

import json

import numpy as np
import pytest
import torch

from detaug_gym import bench
from detaug_gym.models.batching import PlanBatcher, run_requests
from detaug_gym.policies import act_batch, make_policy, share_planner

TIMING = ("wall_time",)


def _records(out):
    lines = [json.loads(line) for line in (out / "episodes.jsonl").read_text().splitlines()]
    return {bench.record_key(r): {k: v for k, v in r.items() if k not in TIMING} for r in lines}


@pytest.mark.slow
def test_batched_bench_gives_the_unbatched_records(tmp_path):
    """Every flow method (AEGIS around base, CAPE's guided re-noising, DetAug's K = 32 selection, DemoGen's
    cloud) on 3 L2 episodes, 3 envs per worker against 1: the same outcomes, clearances equal to 1e-5 m."""
    methods = ["aegis", "cape", "detaug", "demogen"]
    runs = {}
    for n in (1, 3):
        out = tmp_path / f"n{n}"
        bench.run(bench.BenchConfig(methods=methods, suites=["spatial"], levels=["2"], episodes=3, seeds=[7],
                                    out=str(out), envs_per_worker=n, env_kwargs=["max_episode_steps=30"]))
        runs[n] = _records(out)
    assert len(runs[1]) == 12 and set(runs[1]) == set(runs[3])
    for key, record in runs[1].items():
        other = runs[3][key]
        assert record["termination"] != "error", record["error"]
        for field in ("termination", "success", "collision", "steps", "init_state", "obstacle"):
            assert other[field] == record[field], (key, field)
        assert other["min_clearance"] == pytest.approx(record["min_clearance"], abs=1e-5), key


@pytest.fixture(scope="module")
def obs(spatial_l2_obs):
    return spatial_l2_obs


class _Capture:
    """A stand-in batcher that keeps the requests a policy makes (and runs each alone)."""

    def __init__(self):
        self.requests = []

    def submit(self, request):
        self.requests.append(request)
        return run_requests([request])[0]


def test_merged_requests_integrate_like_each_alone(obs):
    """Plans of four requests integrated in one call equal each integrated alone (to float32 rounding; on this
    machine bit for bit at K = 8), and they were one call."""
    policy, capture = make_policy("detaug", k=8), _Capture()
    policy.share_planner(capture)
    for seed in range(4):
        policy.reset(seed=seed)
        policy.plan(obs, policy.sample_labels(obs, 8))
    alone = [run_requests([r])[0] for r in capture.requests]
    together = run_requests(capture.requests)
    for a, b in zip(alone, together):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5)
    assert len({r.group() for r in capture.requests}) == 1


def test_act_batch_shares_network_calls_and_isolates_failures(obs):
    policies = [make_policy("base") for _ in range(3)]
    batcher = PlanBatcher()
    for seed, policy in enumerate(policies):
        assert share_planner(policy, batcher)
        policy.reset(seed=seed)
    actions = act_batch(policies, [obs, obs, obs], batcher)
    assert all(isinstance(a, np.ndarray) and a.shape == (7,) for a in actions)
    assert batcher.requests == 3 and batcher.integrations == 1  # three replans, one network call
    broken = dict(obs, robot_joint_pos=np.zeros(3, np.float32))  # a wrong shape: that policy's act raises
    for policy in policies:
        policy.reset(seed=0)
    actions = act_batch(policies, [obs, broken, obs], batcher)
    assert isinstance(actions[1], Exception) and all(isinstance(actions[i], np.ndarray) for i in (0, 2))
    np.testing.assert_allclose(actions[0], actions[2], atol=1e-5)  # same seed and observation: same plan
    assert not share_planner(make_policy("scripted"), batcher)


def test_a_folder_refuses_a_rerun_in_another_batching(tmp_path):
    """Batching changes a flow policy's float32 arithmetic, so --envs-per-worker is part of what an episode is."""
    cfg = dict(methods=["random"], suites=["newton"], levels=["2"], episodes=2, out=str(tmp_path),
               env_kwargs=["max_episode_steps=5"])
    bench.run(bench.BenchConfig(**cfg))
    with pytest.raises(SystemExit, match="--envs-per-worker differs: the folder's episodes ran with 1, this run asks "
                                         "for 2"):
        bench.run(bench.BenchConfig(**cfg, envs_per_worker=2))
