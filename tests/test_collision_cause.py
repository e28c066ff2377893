"""Collision attribution: who moved the obstacle (env contact labels), in which phase (the demo segmentation
applied to the executed gripper commands), and what a planning policy believed (its ``belief()``)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from detaug_gym.augment.segment import PHASES, segment_gripper
from detaug_gym.policies import make_policy
from detaug_gym.report import collision_rows
from detaug_gym.rollout import BODY_KINDS, CollisionAttribution, EpisodeKey, rollout, run_episode


def test_phases_follow_the_gripper_command():
    command = np.r_[-np.ones(30), np.ones(40), -np.ones(30)]  # close at 30, release at 70
    seg = segment_gripper(command)
    w = seg.windows[0][1] - 30
    assert [seg.phase(f) for f in (0, 30 - w - 1, 30, 50, 70, 70 + w + 1, 99)] == [
        "approach", "approach", "grasp", "carry", "release", "retreat", "retreat"]
    assert segment_gripper(-np.ones(20)).phase(10) == "approach"  # never grasped
    assert set(seg.phase(f) for f in range(100)) == set(PHASES)


@pytest.fixture(scope="module")
def l2_env():
    env = gym.make("SafeLibero-Spatial-L2-v0")
    yield env
    env.close()


def test_the_scripted_expert_on_l2_gets_an_attributed_collision(l2_env):
    """The scripted expert ignores the obstacle; on L2 (obstacle on the path) the held bowl or the hand moves it.
    Every contact label must name a real body, and the env's robot-contact flag must agree with the labels."""
    expert = make_policy("scripted", suite="spatial")
    record = run_episode(l2_env, expert, EpisodeKey("scripted", "SafeLibero-Spatial-L2-v0", 0, 0, 0), "spatial",
                         "L2")
    assert record.collision and record.collision_cause is not None
    cause = record.collision_cause
    assert cause["step"] == record.first_collision_step
    assert cause["bodies"] and cause["contact_step"] <= cause["step"]
    assert cause["first_touch_step"] <= cause["contact_step"]
    kinds = {BODY_KINDS[label.split(":", 1)[0]] for label in cause["bodies"]}
    assert cause["body"] == "+".join(sorted(kinds))
    assert cause["phase"] in PHASES and isinstance(cause["bent"], bool)
    assert "plan_deviation" not in cause  # the expert plans nothing
    model = l2_env.unwrapped.scene.model
    body_names = {model.body(i).name.removesuffix("_main") for i in range(model.nbody)}
    assert all(label.split(":", 1)[1] in body_names for label in cause["bodies"])


def test_contacts_in_info_match_the_robot_contact_flag(l2_env):
    expert = make_policy("scripted", suite="spatial")
    seen = []

    class Watch(CollisionAttribution):
        def on_step(self, step):
            super().on_step(step)
            labels = step.info["obstacle_contacts"]
            robot = any(label.split(":")[0] in ("link", "gripper") for label in labels)
            assert robot == step.info["robot_obstacle_contact"]
            assert bool(step.info["collision_bodies"]) <= (step.index + 1 == self.step)
            seen.extend(labels)

    watch = Watch(expert)
    rollout(l2_env, expert, seed=3, options={"task": 1}, hooks=[watch], max_steps=260)
    assert seen, "nothing touched the obstacle in an L2 episode of the obstacle-blind expert"
    assert not any(label.split(":")[1].startswith(("main_table", "table", "floor")) for label in seen)


def test_a_planning_policy_reports_its_belief_at_the_collision(l2_env):
    policy = make_policy("base", suite="spatial")
    for seed in range(4):  # base ignores the obstacle; on L2 it collides in most episodes
        record = run_episode(l2_env, policy, EpisodeKey("base", "SafeLibero-Spatial-L2-v0", seed % 4, seed, seed),
                             "spatial", "L2")
        if record.collision:
            break
    else:
        pytest.fail("base avoided the L2 obstacle in 4 episodes: pick seeds where it collides")
    cause = record.collision_cause
    assert 0.0 <= cause["plan_deviation"] < 1.0 and 1 <= cause["plan_age"] <= policy.action_steps


def test_report_tabulates_collisions_by_body_and_phase():
    rows = [dict(method="m", suite="spatial", level="L2", collision=True, termination="timeout",
                 collision_cause={"body": "held_object", "phase": "carry"}),
            dict(method="m", suite="spatial", level="L2", collision=True, termination="success",
                 collision_cause={"body": "gripper", "phase": "approach"}),
            dict(method="m", suite="spatial", level="L2", collision=True, termination="success"),
            dict(method="m", suite="spatial", level="L2", collision=True, termination="error"),
            dict(method="m", suite="spatial", level="L2", collision=False, termination="success")]
    header, table = collision_rows(rows, "body")
    assert header == ["Method", "Suite", "Level", "Collisions", "gripper", "held_object", "unattributed"]
    assert table == [["m", "spatial", "L2", "3", "1", "1", "1"]]
    assert collision_rows(rows, "phase")[1] == [["m", "spatial", "L2", "3", "1", "1", "1"]]
