"""DetAug on a real Spatial scene: IK accuracy, exact unbent replay, accepted augmentations, the command."""

from __future__ import annotations

from dataclasses import replace

import gymnasium as gym
import h5py
import mujoco
import numpy as np
import pytest

import detaug_gym  # noqa: F401
from detaug_gym.augment.__main__ import main as augment_main
from detaug_gym.augment.arcs import arc_points, min_jerk
from detaug_gym.augment.context import SourceContext, reset_to_demo
from detaug_gym.augment.detaug import MODE as DETAUG
from detaug_gym.augment.detaug import DetAugConfig
from detaug_gym.augment.engine import augment_source
from detaug_gym.augment.plan import build_plan
from detaug_gym.augment.replay import length_limit, run_plan, tail_steps
from detaug_gym.collect import record_episode
from detaug_gym.data import DatasetWriter, load
from detaug_gym.envs.suites import suite_of_env
from detaug_gym.policies import make_policy
from detaug_gym.rollout import step_limit
from detaug_gym.rotations import quat_xyzw_to_mat, rotation_error, slerp

ENV_ID = "SafeLibero-Spatial-Free-v0"
SUITE = suite_of_env(ENV_ID)[0]


@pytest.fixture(scope="module")
def env():
    env = gym.make(ENV_ID)
    yield env
    env.close()


@pytest.fixture(scope="module")
def demo(env):
    demo, ok = record_episode(env, make_policy("scripted"), task=0, init_state=0, seed=0, env_id=ENV_ID)
    assert ok
    demo.name = "demo_0"
    return demo


@pytest.fixture(scope="module")
def augmented(env, demo):
    config = DetAugConfig(tries=12)
    result = augment_source(env, demo, 2, np.random.default_rng(3), DETAUG, SUITE, config)
    return result, config


def test_ik_reproduces_target_poses(env, demo):
    ctx = SourceContext.build(env, demo)
    tr = ctx.segmentation.transits[0]
    s = min_jerk(np.linspace(0, 1, 40))
    pos = arc_points(ctx.pos[tr.start], ctx.pos[tr.end], 0.5 * np.pi, 0.5 * np.pi, s)
    rot = quat_xyzw_to_mat(slerp(ctx.quat[tr.start], ctx.quat[tr.end], s))
    ctx.ik.load(ctx.qpos[tr.start])
    result = ctx.ik.solve_path(ctx.qpos[tr.start, ctx.scene.arm_qpos], pos, rot)
    assert result.solved(ctx.ik.config)
    for q, p, r in zip(result.q, pos, rot):  # forward kinematics of the solution, independently
        got_p, got_r = ctx.ik.site_pose(q)
        assert np.linalg.norm(got_p - p) < 1e-3
        assert np.linalg.norm(rotation_error(r, got_r)) < 1e-2


def test_unbent_plan_replays_the_source_exactly(env, demo):
    ctx = SourceContext.build(env, demo)
    plan = build_plan(ctx.pos, ctx.quat, demo.gripper_command, [])
    rec = run_plan(env, reset_to_demo(env, demo), plan, demo.actions, DetAugConfig().replay)
    assert rec.success
    np.testing.assert_array_equal(np.asarray(rec.actions, dtype=np.float32), demo.actions)
    np.testing.assert_array_equal(np.asarray(rec.states), demo.states)


def test_a_source_with_a_tail_is_replayed_past_its_first_success(env):
    demo, ok = record_episode(env, make_policy("scripted"), task=0, init_state=0, seed=0, env_id=ENV_ID,
                              tail_steps=15)
    assert ok and tail_steps(demo) == 15
    assert length_limit(env, demo, None) == step_limit(env) + 15
    ctx = SourceContext.build(env, demo)
    plan = build_plan(ctx.pos, ctx.quat, demo.gripper_command, [])
    replay = DetAugConfig().replay
    whole = run_plan(env, reset_to_demo(env, demo), plan, demo.actions, replay, tail=15)
    assert whole.success
    np.testing.assert_array_equal(np.asarray(whole.states), demo.states)
    cut = run_plan(env, reset_to_demo(env, demo), plan, demo.actions, replay)
    assert cut.success and len(cut.actions) == len(demo) - 15  # without the tail: stops at the first success


def test_accepted_copies_keep_windows_and_carry_the_object_rigidly(env, demo, augmented):
    result, config = augmented
    assert result.demos, f"no sample accepted: {dict(result.reasons)}"
    ctx = SourceContext.build(env, demo)
    seg = ctx.segmentation
    for aug in result.demos:
        assert aug.label.shape == (4,) and np.abs(aug.label).max() > 0.4  # phi >= 0.15 pi
        assert aug.rewards[-1] == 1.0 and aug.attrs["max_deviation"] <= config.replay.tolerance
        spans = aug.attrs["transits"]
        first = spans[0]["start"]
        np.testing.assert_array_equal(aug.actions[:first], demo.actions[:first])  # untouched prefix
        frame_map = _frame_map(spans, len(demo))
        for lo, hi in seg.windows:  # gripper commands of every interaction window, bit for bit
            frames = [f for f in range(lo, hi + 1) if frame_map.get(f, 10 ** 9) < len(aug)]
            np.testing.assert_array_equal(aug.gripper_command[[frame_map[f] for f in frames]],
                                          demo.gripper_command[frames])
        carry = next(s for s in spans if s["kind"] == "carry")
        drift = _held_drift(env, ctx, aug.states[carry["start"]:carry["end"] + 1])
        assert drift <= ctx.source_drift[1] + config.replay.offset_tolerance


def test_copies_whose_grasp_moved_on_the_object_are_rejected(env, demo, augmented):
    result, config = augmented
    ctx = SourceContext.build(env, demo)
    unbent = build_plan(ctx.pos, ctx.quat, demo.gripper_command, [])
    rec = run_plan(env, reset_to_demo(env, demo), unbent, demo.actions, config.replay)
    assert ctx.grasp_shift(unbent, rec) < 1e-9 and ctx.replay_reason(unbent, rec, config.replay) is None
    for aug in result.demos:  # accepted copies hold the bowl where the source did when the carry starts
        carry = next(s for s in aug.attrs["transits"] if s["kind"] == "carry")
        local = _held_offsets(ctx, aug.states[carry["start"]:carry["start"] + 1])[0]
        assert np.linalg.norm(local - ctx.held[1].offset_pos) <= config.replay.grasp_tolerance
    strict = replace(config, tries=3, replay=replace(config.replay, grasp_tolerance=1e-6))
    rejected = augment_source(env, demo, 1, np.random.default_rng(3), DETAUG, SUITE, strict)
    assert not rejected.demos and rejected.reasons["grasp_moved"] > 0, dict(rejected.reasons)


def _frame_map(spans, n_source):
    """source frame -> augmented frame for the frames outside the bent transits."""
    mapping, shift = {}, 0
    cursor = 0
    for s in spans:
        for f in range(cursor, s["source_start"] + 1):
            mapping[f] = f + shift
        shift += (s["end"] - s["start"]) - (s["source_end"] - s["source_start"])
        cursor = s["source_end"]
    for f in range(cursor, n_source):
        mapping[f] = f + shift
    return mapping


def _held_offsets(ctx, states):
    """(N, 3) the carried bowl's position in the grip-site frame, per simulator state."""
    model, data = ctx.scene.model, mujoco.MjData(ctx.scene.model)
    body = ctx.held[1].body
    local = []
    for st in states:
        data.qpos[:] = st[1:1 + model.nq]
        mujoco.mj_kinematics(model, data)
        rot = data.site_xmat[ctx.scene.eef_site].reshape(3, 3)
        local.append(rot.T @ (data.xpos[body] - data.site_xpos[ctx.scene.eef_site]))
    return np.array(local)


def _held_drift(env, ctx, states):
    local = _held_offsets(ctx, states)
    return float(np.linalg.norm(local - local[0], axis=1).max())


def test_command_writes_originals_and_labelled_copies_and_resumes(tmp_path, demo):
    raw, out, fig = tmp_path / "raw.hdf5", tmp_path / "aug.hdf5", tmp_path / "fig.png"
    env_args = {"env_name": ENV_ID, "env_version": "0", "type": "detaug_gym", "env_kwargs": {}}
    with DatasetWriter(raw, env_args) as writer:
        writer.append(demo)
    argv = ["--in", str(raw), "--out", str(out), "--copies", "1", "--tries", "8", "--seed", "1", "--no-progress"]
    augment_main(argv + ["--plot", str(fig)])
    data = load(out)
    assert [d.attrs["augmented"] for d in data.demos][0] is False and fig.stat().st_size > 0
    assert not data.demos[0].label.any() and data.demos[0].label.shape == (4,)
    for d in data.demos[1:]:
        assert d.attrs["source_demo"] == "demo_0" and np.abs(d.label).max() > 0
        assert len(d.attrs["phi"]) == 2 and "augment_params" in d.attrs
    augment_main(argv)  # resume: nothing left to do, nothing duplicated
    with h5py.File(out, "r") as f:
        assert len(f["data"]) == len(data.demos)
    q = quat_xyzw_to_mat(data.demos[0].obs["eef_quat"][0])
    assert np.allclose(q @ q.T, np.eye(3), atol=1e-5)
