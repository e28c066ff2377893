"""The registered envs: ids, gymnasium's env checker, determinism, collision rule, bad input."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import detaug_gym  # noqa: F401
from detaug_gym.actions import ACTION_DIM, GRIPPER_OPEN, POS_SCALE
from detaug_gym.envs import NEWTON_IDS, SAFE_LIBERO_IDS
from detaug_gym.envs.safe_libero import SafeLiberoEnv

ALL_IDS = SAFE_LIBERO_IDS + NEWTON_IDS


def _flat(obs):
    return np.concatenate([np.asarray(v, np.float64).ravel() for _, v in sorted(obs.items())])


def _make(env_id, **kwargs):
    if env_id.startswith("SafeLibero"):
        kwargs.setdefault("task", 0)  # one scene per id keeps the test fast (each build takes seconds)
    return gym.make(env_id, **kwargs)


@pytest.fixture(scope="module")
def spatial_l2():
    env = gym.make("SafeLibero-Spatial-L2-v0", task=0)
    yield env
    env.close()


@pytest.fixture(scope="module")
def newton_cylinder():
    env = gym.make("Newton-PickPlace-Cylinder-v0")
    yield env
    env.close()


def test_all_thirty_ids_registered_and_namespaced():
    assert len(ALL_IDS) == 30  # 4 suites x (L1, L2 at v2, v1 and v0, Free) + Newton's 2
    for env_id in ALL_IDS:
        assert env_id in gym.registry
    env = gym.make("detaug_gym:SafeLibero-Goal-Free-v0")  # no scene is built before reset
    assert env.unwrapped.suite.name == "goal" and len(env.unwrapped.tasks) == 5
    assert env.spec.max_episode_steps == 300


def test_task_id_uses_the_suites_order_at_every_level():
    """Goal offers four tasks per obstacle level and five on Free: the one-hot keeps the suite's five slots, so
    L2's task 3 (the cream cheese) reads as the suite's task 4, as in the Free demos a policy was trained on."""
    from detaug_gym.envs.suites import SUITES

    goal = SUITES["goal"]
    assert [goal.suite_task("L2", t) for t in range(4)] == [0, 1, 2, 4]
    assert [goal.suite_task("L1", t) for t in range(4)] == [0, 1, 2, 3]
    assert goal.suite_task("Free", 4) == 4
    env = gym.make("SafeLibero-Goal-L2-v2", task=3)
    try:
        assert env.observation_space["task_id"].shape == (5,)
        obs, _ = env.reset(seed=0)
        assert obs["task_id"].shape == (5,) and int(np.argmax(obs["task_id"])) == 4
        assert goal.tasks[4].key == env.unwrapped.task_spec.key == "cream_cheese_in_bowl"
    finally:
        env.close()


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_env_checker_passes(env_id):
    """gymnasium's check_env on every id, each with one fixed task so that one scene is compiled."""
    env = _make(env_id)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=1)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    for key in ("is_success", "collision", "robot_obstacle_contact", "obstacle_displacement", "min_clearance"):
        assert key in info
    has_obstacle = not env_id.endswith("Free-v0") and env_id != "Newton-PickPlace-v0"
    assert obs["obstacle_mask"][0] == float(has_obstacle)
    assert np.any(obs["obstacle_points"] != 0) == has_obstacle
    env.close()


def test_seeded_reset_and_rollout_are_deterministic(spatial_l2):
    env = spatial_l2
    actions = np.random.default_rng(0).uniform(-0.5, 0.5, (15, 7)).astype(np.float32)
    runs = []
    for _ in range(2):
        obs, _ = env.reset(seed=11)
        trace = [_flat(obs)]
        for a in actions:
            obs, *_ = env.step(a)
            trace.append(_flat(obs))
        runs.append(np.stack(trace))
    assert np.array_equal(runs[0], runs[1])
    other, _ = env.reset(seed=12)
    assert not np.array_equal(_flat(other), runs[0][0])


def test_same_seed_same_obstacle_across_env_instances(spatial_l2):
    obs_a, info_a = spatial_l2.reset(seed=5)
    other = gym.make("SafeLibero-Spatial-L2-v0", task=0)
    obs_b, info_b = other.reset(seed=5)
    assert info_a["obstacle"] == info_b["obstacle"] and info_a["init_state"] == info_b["init_state"]
    assert np.array_equal(obs_a["obstacle_points"], obs_b["obstacle_points"])
    other.close()


def _push_obstacle(env, seed):
    """Drive the hand at the obstacle's mid-height into the obstacle; returns the infos."""
    obs, _ = env.reset(seed=seed)
    infos = []
    target = obs["obstacle_pose"][:3].copy()
    target[2] = obs["obstacle_points"][:, 2].min() + 0.6 * np.ptp(obs["obstacle_points"][:, 2])
    for step in range(80):
        goal = target.copy()
        if step < 40:  # first come down beside the obstacle, then sweep through it
            goal[:2] += np.array([0.0, -0.12])
        action = np.zeros(ACTION_DIM, np.float32)
        action[:3] = np.clip((goal - obs["eef_pos"]) / POS_SCALE, -1, 1)
        action[6] = GRIPPER_OPEN
        obs, _, terminated, truncated, info = env.step(action)
        infos.append(info)
    return infos


def test_collision_fires_when_robot_pushes_obstacle(newton_cylinder):
    infos = _push_obstacle(newton_cylinder, seed=0)
    assert not infos[0]["collision"]
    assert any(i["robot_obstacle_contact"] for i in infos)
    assert infos[-1]["collision"] and infos[-1]["obstacle_displacement"] > 1e-3
    assert min(i["min_clearance"] for i in infos) <= 1e-3


def test_no_collision_in_free_env():
    env = gym.make("Newton-PickPlace-v0")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(40):
        *_, info = env.step(rng.uniform(-1, 1, 7).astype(np.float32))
        assert not info["collision"] and not info["robot_obstacle_contact"]
        assert info["min_clearance"] == float("inf")
    env.close()


@pytest.mark.parametrize("bad", [np.zeros(3, np.float32), np.full(7, np.nan, np.float32),
                                 np.array([0, 0, np.inf, 0, 0, 0, 1], np.float32)])
def test_bad_actions_raise_value_error(newton_cylinder, bad):
    newton_cylinder.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        newton_cylinder.step(bad)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [({"suite": "kitchen", "level": "L1"}, "valid suites: spatial, object, goal, long"),
     ({"suite": "spatial", "level": "L3"}, "valid levels: L1, L2, Free"),
     ({"suite": "spatial", "level": "L1", "task": 7}, "valid tasks"),
     ({"suite": "goal", "level": "L2", "task": "open the top drawer and put the bowl inside"}, "valid tasks"),
     ({"suite": "spatial", "level": "L1", "obstacle": "piano"}, "valid types: moka_pot"),
     ({"suite": "spatial", "level": "L1", "init_state": 50}, "init_state")],
)
def test_bad_configuration_is_rejected_with_valid_values(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SafeLiberoEnv(**kwargs)


def test_unknown_env_id_is_rejected():
    with pytest.raises(gym.error.Error):
        gym.make("SafeLibero-Kitchen-L1-v0")


def test_task_by_language_and_obstacle_restriction(spatial_l2):
    env = gym.make("SafeLibero-Spatial-L1-v0", task="pick up the black bowl between the plate and the ramekin "
                   "and place it on the plate", obstacle=["milk"])
    _, info = env.reset(seed=3)
    assert info["task"] == 0 and info["obstacle"] == "milk"
    env.close()
