"""Dataset format: round trip, resume, LIBERO-layout files, clear errors, replay and resumable collection."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from detaug_gym.data import DatasetError, DatasetWriter, Demo, load, replay

ENV_ARGS = {"env_name": "SafeLibero-Spatial-Free-v0", "env_version": "0", "type": "detaug_gym", "env_kwargs": {}}


def _demo(t: int = 5, task: int = 0, init_state: int = 0, seed: int = 0, **extra) -> Demo:
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, (t, 7)).astype(np.float32)
    return Demo(
        actions=actions,
        states=rng.normal(size=(t, 11)),
        obs={"eef_pos": rng.normal(size=(t, 3)).astype(np.float32),
             "object_poses": rng.normal(size=(t, 2, 7)).astype(np.float32),
             "obstacle_points": np.zeros((t, 4, 3), dtype=np.float32)},
        gripper_command=actions[:, -1].copy(),
        attrs={"env_id": ENV_ARGS["env_name"], "task": task, "task_key": "k", "init_state": init_state,
               "seed": seed, "controller": json.dumps({"type": "OSC_POSE"})},
        **extra,
    )


def test_round_trip_keeps_arrays_attrs_and_optional_fields(tmp_path):
    path = tmp_path / "d.hdf5"
    first = _demo(seed=1)
    second = _demo(t=7, seed=2, label=np.array([0.3, 0.7], dtype=np.float32),
                   obstacle_points=np.ones((6, 3), dtype=np.float32))
    with DatasetWriter(path, ENV_ARGS) as writer:
        assert writer.append(first) == "demo_0"
        assert writer.append(second) == "demo_1"
    data = load(path)
    assert len(data) == 2
    assert data.attrs["env_args"] == ENV_ARGS and data.attrs["total"] == 12
    got = data[1]
    np.testing.assert_array_equal(got.actions, second.actions)
    np.testing.assert_array_equal(got.states, second.states)
    np.testing.assert_array_equal(got.obs["object_poses"], second.obs["object_poses"])
    assert "obstacle_points" not in got.obs  # obstacle observation keys are not stored per step
    np.testing.assert_array_equal(got.label, second.label)
    np.testing.assert_array_equal(got.obstacle_points, second.obstacle_points)
    assert data[0].label is None and data[0].obstacle_points is None
    assert got.attrs["num_samples"] == 7 and got.attrs["controller"] == {"type": "OSC_POSE"}
    assert got.key == (0, 0, 2)


def test_writer_resumes_and_drops_a_half_written_demo(tmp_path):
    path = tmp_path / "d.hdf5"
    with DatasetWriter(path, ENV_ARGS) as writer:
        writer.append(_demo(seed=1))
    with h5py.File(path, "a") as f:  # a crash mid-write leaves a group without actions
        f["data"].create_group("demo_1").create_dataset("states", data=np.zeros((3, 11)))
    with DatasetWriter(path, ENV_ARGS) as writer:
        assert len(writer) == 1
        assert writer.has(0, 0, 1) and not writer.has(0, 0, 2)
        assert writer.append(_demo(seed=2)) == "demo_1"
    assert [d.key for d in load(path)] == [(0, 0, 1), (0, 0, 2)]
    with pytest.raises(DatasetError, match="Newton"):
        DatasetWriter(path, {**ENV_ARGS, "env_name": "Newton-PickPlace-v0"})


def test_loads_libero_layout(tmp_path):
    path = tmp_path / "libero_demo.hdf5"
    t = 4
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps({"env_name": "Libero", "type": 1, "env_kwargs": {}})
        data.attrs["total"] = t
        demo = data.create_group("demo_0")
        demo.attrs["num_samples"] = t
        demo.create_dataset("actions", data=np.full((t, 7), 0.5))
        demo.create_dataset("states", data=np.zeros((t, 9)))
        demo.create_dataset("rewards", data=np.zeros(t))
        demo.create_dataset("dones", data=np.r_[np.zeros(t - 1), 1.0])
        obs = demo.create_group("obs")
        obs.create_dataset("joint_states", data=np.ones((t, 7)))
        obs.create_dataset("gripper_states", data=np.ones((t, 2)))
        obs.create_dataset("ee_pos", data=np.ones((t, 3)))
        obs.create_dataset("ee_ori", data=np.ones((t, 3)))
        obs.create_dataset("agentview_rgb", data=np.zeros((t, 8, 8, 3), dtype=np.uint8))
    data = load(path)
    demo = data[0]
    assert data.attrs["env_args"]["env_name"] == "Libero"
    assert set(demo.obs) == {"robot_joint_pos", "gripper_qpos", "eef_pos", "eef_ori"}
    np.testing.assert_array_equal(demo.gripper_command, np.full(t, 0.5, dtype=np.float32))
    assert demo.dones[-1] == 1.0 and demo.label is None


def test_missing_and_corrupt_files_name_the_file(tmp_path):
    missing = tmp_path / "nope.hdf5"
    with pytest.raises(DatasetError, match="nope.hdf5.*no such"):
        load(missing)
    corrupt = tmp_path / "corrupt.hdf5"
    corrupt.write_bytes(b"this is not hdf5" * 10)
    with pytest.raises(DatasetError, match="corrupt.hdf5.*not a readable HDF5"):
        load(corrupt)
    empty = tmp_path / "empty.hdf5"
    with h5py.File(empty, "w") as f:
        f.create_group("other")
    with pytest.raises(DatasetError, match="empty.hdf5.*no 'data' group"):
        load(empty)
    broken = tmp_path / "broken.hdf5"
    with h5py.File(broken, "w") as f:
        f.create_group("data/demo_0/obs")
    with pytest.raises(DatasetError, match="demo_0 is incomplete"):
        load(broken)


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    """Two Spatial task-0 demos from the collect CLI (the second run resumes the first)."""
    from detaug_gym.collect import CollectArgs, collect

    path = tmp_path_factory.mktemp("collect") / "raw.hdf5"
    first = collect(CollectArgs(env="SafeLibero-Spatial-Free-v0", out=str(path), task="0", demos=1))
    second = collect(CollectArgs(env="SafeLibero-Spatial-Free-v0", out=str(path), task="0", demos=2))
    return path, first, second


def test_collect_resumes_without_redoing_demos(collected):
    path, first, second = collected
    assert first[0].kept == 1 and first[0].attempts == 1
    assert second[0].resumed == 1 and second[0].kept == 2 and second[0].attempts == 1
    data = load(path)
    assert [d.attrs["init_state"] for d in data] == [0, 1]
    demo = data[0]
    assert demo.states.shape == (len(demo), demo.states.shape[1]) and demo.actions.dtype == np.float32
    assert {"robot_joint_pos", "robot_joint_vel", "gripper_qpos", "eef_pos", "eef_quat", "object_poses",
            "task_id"} <= set(demo.obs)
    assert demo.dones[-1] == 1.0  # kept demos end in success


def test_tail_steps_record_the_expert_letting_go_after_the_first_success(collected, tmp_path):
    from detaug_gym.collect import CollectArgs, collect, main

    path, _, _ = collected
    plain = load(path)[0]
    tailed_path = tmp_path / "tail.hdf5"
    collect(CollectArgs(env="SafeLibero-Spatial-Free-v0", out=str(tailed_path), task="0", demos=1, tail_steps=20))
    tailed = load(tailed_path)[0]
    assert len(tailed) == len(plain) + 20 and tailed.attrs["tail_steps"] == 20
    np.testing.assert_array_equal(tailed.states[: len(plain)], plain.states)  # same episode up to the success
    width = tailed.obs["gripper_qpos"][:, 0] - tailed.obs["gripper_qpos"][:, 1]
    assert width[-1] > width[len(plain) - 1] + 0.02  # the fingers opened during the tail
    assert tailed.actions[-1, -1] < 0 and tailed.dones[-1] == 1.0  # and the task is still solved
    with pytest.raises(SystemExit):
        main(["--env", "SafeLibero-Spatial-Free-v0", "--out", str(tmp_path / "x.hdf5"), "--tail-steps", "-1"])


def test_collect_takes_policy_options_and_a_step_limit(tmp_path):
    from detaug_gym.collect import CollectArgs, collect

    args = dict(env="SafeLibero-Spatial-Free-v0", out=str(tmp_path / "short.hdf5"), task="0", demos=1)
    stats = collect(CollectArgs(**args, policy="scripted:variation=0.5", max_steps=30, max_attempts=1))
    assert stats[0].attempts == 1 and stats[0].kept == 0  # no pick-and-place finishes in 30 steps
    with pytest.raises(ValueError, match="fumble must be in"):
        CollectArgs(**args, policy="scripted:fumble=2")
    with pytest.raises(ValueError, match="unknown policy"):
        CollectArgs(**args, policy="expert")
    with pytest.raises(ValueError, match="--max-steps must be >= 1"):
        CollectArgs(**args, max_steps=0)


def test_fumbled_demos_record_the_correct_command_and_send_the_miss(tmp_path):
    from detaug_gym.collect import CollectArgs, collect

    path = tmp_path / "fumble.hdf5"
    stats = collect(CollectArgs(env="SafeLibero-Goal-Free-v0", out=str(path), task="3", demos=1, seed=500,
                                policy="scripted:fumble=1", max_steps=400, max_attempts=2))
    assert stats[0].kept == 1
    demo = load(path)[0]
    acted = np.flatnonzero(np.abs(demo.executed_actions - demo.actions).max(axis=1) > 1e-6)
    stretches = np.split(acted, np.flatnonzero(np.diff(acted) > 1) + 1)
    assert len(stretches) == 1  # the handle's fumble (the bowl, rim-held, never fumbles)
    for stretch in stretches:  # each acted out in one stretch: labels open, the env sent the close
        assert 15 <= len(stretch) <= 60
        assert np.all(demo.actions[stretch, -1] < 0) and np.sum(demo.executed_actions[stretch, -1] > 0) >= 8
    assert len(demo) > 300  # the retry runs past the task's 300 steps: kept thanks to max_steps
    assert demo.attrs["fumble"] == 1.0
    clean = tmp_path / "clean.hdf5"  # fumble=0 (the default) acts nothing out: no executed_actions
    collect(CollectArgs(env="SafeLibero-Goal-Free-v0", out=str(clean), task="0", demos=1, policy="scripted:fumble=0"))
    assert load(clean)[0].executed_actions is None


def test_replay_reproduces_recorded_states(collected):
    import gymnasium as gym

    path, _, _ = collected
    demo = load(path)[0]
    env = gym.make(demo.attrs["env_id"])
    try:
        states = replay(env, demo)
    finally:
        env.close()
    assert states.shape == demo.states.shape
    np.testing.assert_allclose(states, demo.states, atol=1e-9)


def test_action_noise_is_correlated_with_the_requested_std():
    from detaug_gym.collect import ActionNoise

    noise = ActionNoise(sigma=0.3, tau=10.0)
    noise.reset(seed=3)
    clean = np.zeros(7, np.float32)
    clean[6] = 1.0
    pushes = np.array([noise(clean) for _ in range(20_000)])
    assert np.all(pushes[:, 3:] == clean[3:])  # rotation and gripper untouched
    std = pushes[:, :3].std(axis=0)
    np.testing.assert_allclose(std, 0.3, rtol=0.1)
    lag1 = np.corrcoef(pushes[1:, 0], pushes[:-1, 0])[0, 1]
    assert abs(lag1 - np.exp(-1 / 10)) < 0.03
    with pytest.raises(ValueError, match="tau > 0"):
        ActionNoise(sigma=0.3, tau=0.0)


def test_action_noise_in_bursts_acts_the_requested_share_of_steps():
    from detaug_gym.collect import ActionNoise

    noise = ActionNoise(sigma=0.3, tau=10.0, duty=0.25, burst=15.0)
    noise.reset(seed=3)
    clean = np.zeros(7, np.float32)
    pushed = np.array([np.any(noise(clean)[:3] != 0.0) for _ in range(40_000)])
    assert abs(pushed.mean() - 0.25) < 0.03
    starts = np.flatnonzero(np.diff(pushed.astype(int)) == 1)
    ends = np.flatnonzero(np.diff(pushed.astype(int)) == -1)
    lengths = ends[ends > starts[0]][: len(starts) - 1] - starts[: len(starts) - 1]
    assert abs(lengths.mean() - 15.0) < 2.0  # bursts, not isolated steps
    always = ActionNoise(sigma=0.3, tau=10.0)
    always.reset(seed=3)
    assert all(np.any(always(clean)[:3] != 0.0) for _ in range(100))
    for bad in (dict(duty=0.0), dict(duty=1.5), dict(burst=0.5)):
        with pytest.raises(ValueError, match="duty"):
            ActionNoise(sigma=0.3, **bad)


def test_noisy_collection_records_clean_actions_and_replays_what_was_sent(tmp_path):
    import gymnasium as gym

    from detaug_gym.augment.runner import select_sources
    from detaug_gym.collect import CollectArgs, collect

    path = tmp_path / "dart.hdf5"
    stats = collect(CollectArgs(env="SafeLibero-Spatial-Free-v0", out=str(path), task="0", demos=1, seed=500,
                                action_noise=0.3, max_attempts=4, tail_steps=10))
    assert stats[0].kept == 1
    demo = load(path)[0]
    assert demo.executed_actions.shape == demo.actions.shape
    np.testing.assert_array_equal(demo.executed_actions[-10:], demo.actions[-10:])  # the tail is not disturbed
    pushed = demo.executed_actions[:, :3] - demo.actions[:, :3]
    assert np.abs(pushed).max() > 0.2 and np.all(demo.executed_actions[:, 3:] == demo.actions[:, 3:])
    # the expert steers against the push it felt on the previous step
    assert np.corrcoef(demo.actions[1:, 0], pushed[:-1, 0])[0, 1] < -0.2
    assert demo.attrs["action_noise"]["sigma"] == 0.3
    env = gym.make(demo.attrs["env_id"])
    try:
        states = replay(env, demo)
    finally:
        env.close()
    np.testing.assert_allclose(states, demo.states, atol=1e-9)
    assert select_sources([demo]) == []  # augmentation cannot copy commands that did not move the arm
