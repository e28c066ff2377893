"""DetAug label selection on a tiny synthetic-data checkpoint: batching, scoring, ties, latch, zero labels."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from detaug_gym.geometry import RobotGeometry
from detaug_gym.policies import available_policies, load, make_policy
from detaug_gym.policies.detaug import DetAugPolicy


@pytest.fixture(scope="module")
def checkpoint(tiny_detaug_checkpoint):
    return tiny_detaug_checkpoint


def _with_obstacle_at_hand(obs):
    """Surround the hand with a 10 cm box so that every plan starts in penetration."""
    robot = RobotGeometry.panda().aligned_to(obs)
    q = torch.as_tensor(obs["robot_joint_pos"], dtype=torch.float64)[None]
    hand = robot.kinematics(q).eef_position[0].numpy()
    corners = np.array(np.meshgrid(*[[-0.05, 0.05]] * 3)).reshape(3, -1).T
    points = hand + np.concatenate([corners, np.random.default_rng(0).uniform(-0.05, 0.05, (248, 3))])
    out = dict(obs)
    out.update(obstacle_points=points.astype(np.float32), obstacle_mask=np.ones(1, np.float32),
               obstacle_pose=np.r_[hand, 0, 0, 0, 1].astype(np.float32),
               obstacle_size=np.full(3, 0.05, np.float32))
    return out


def test_registered_and_loadable(checkpoint):
    path, _ = checkpoint
    assert {"base", "detaug"} <= set(available_policies())
    assert isinstance(load(path), DetAugPolicy)
    assert isinstance(make_policy("detaug", checkpoint=path, k=4), DetAugPolicy)


def test_selects_the_lowest_cost_candidate_from_one_batch(checkpoint):
    path, obs = checkpoint
    policy = DetAugPolicy(checkpoint=path, k=8, labels="random", seed=0, wider_batches=0)  # the paper's one batch
    obs = _with_obstacle_at_hand(obs)
    policy.reset(seed=1)
    plan = policy.next_plan(obs)
    diag = policy.diagnostics[-1]
    assert diag.k == 8 and diag.best_cost <= diag.median_cost
    assert diag.best_cost > 0  # the first state sits inside the box
    rescored = policy.score(torch.as_tensor(plan)[None], obs)[0]
    assert rescored == pytest.approx(diag.best_cost, rel=1e-5)
    assert np.any(np.all(np.isclose(policy.labels.bank, diag.label), axis=1))  # a training label


def test_fresh_labels_every_replan_unless_latched(checkpoint):
    path, obs = checkpoint
    policy = DetAugPolicy(checkpoint=path, k=4, action_steps=2, seed=0)
    policy.reset(seed=3)
    for _ in range(6):
        policy.act(obs)
    assert len(policy.diagnostics) == 3
    latched = DetAugPolicy(checkpoint=path, k=4, action_steps=2, latch=True, seed=0)
    latched.reset(seed=3)
    for _ in range(6):
        latched.act(obs)
    assert len(latched.diagnostics) == 1  # later replans reuse the first label


def test_ties_prefer_the_least_bent_label_and_zero_mode(checkpoint):
    path, obs = checkpoint  # no obstacle keys: every cost is zero
    policy = DetAugPolicy(checkpoint=path, k=16, seed=0)
    policy.reset(seed=0)
    policy.next_plan(obs)
    assert np.all(policy.diagnostics[-1].label == 0)  # the default draw always holds the unbent label
    bank_draw = DetAugPolicy(checkpoint=path, k=16, labels="random", seed=0)
    bank_draw.reset(seed=0)
    bank_draw.next_plan(obs)
    chosen = bank_draw.diagnostics[-1].label
    bank = policy.labels.bank[policy.labels.task == int(np.argmax(obs["task_id"]))]
    assert np.linalg.norm(chosen) == pytest.approx(np.linalg.norm(bank, axis=1).min())
    zero = DetAugPolicy(checkpoint=path, k=4, labels="zero", seed=0)
    zero.reset(seed=0)
    zero.next_plan(obs)
    assert np.all(zero.diagnostics[-1].label == 0)


@pytest.mark.parametrize("mode", ["null_guidance", "guided_select", "null_select"])
def test_guidance_ablation_modes_run(checkpoint, mode):
    path, obs = checkpoint
    policy = DetAugPolicy(checkpoint=path, k=4, mode=mode, seed=0)
    policy.reset(seed=0)
    action = policy.act(_with_obstacle_at_hand(obs))
    assert action.shape == (7,) and np.all(np.isfinite(action))


def test_bad_options_fail_at_construction(checkpoint):
    path, _ = checkpoint
    with pytest.raises(ValueError, match="valid: penetration, clearance"):
        DetAugPolicy(checkpoint=path, cost="distance")
    with pytest.raises(ValueError, match="valid: select"):
        DetAugPolicy(checkpoint=path, mode="vote")


def test_belief_reports_the_selected_plan_and_its_candidates(checkpoint):
    path, obs = checkpoint
    policy = DetAugPolicy(checkpoint=path, k=8, action_steps=2, seed=0)
    obs = _with_obstacle_at_hand(obs)
    policy.reset(seed=1)
    assert policy.belief() == {}  # nothing planned yet
    policy.act(obs)
    first = policy.belief()
    diag = policy.diagnostics[-1]
    assert first["plan_cost"] == diag.best_cost > 0 and first["candidates"] == 24  # none free: 2 wider batches
    assert first["zero_cost_share"] == 0.0  # every candidate starts inside the box
    assert first["plan_age"] == 1 and first["label_change"] is None
    plan_row = policy._plan[1, policy.layout.key_slice("robot_joint_pos")]
    assert np.allclose(first["planned_joint_pos"], plan_row)
    judged = policy.belief(obs)  # the scorer's view of a state inside the box
    assert judged["executed_cost"] > 0 and judged["executed_clearance"] < 0
    assert "executed_cost" not in policy.belief(checkpoint[1])  # no obstacle in view: nothing to judge
    policy.act(obs)
    assert policy.belief()["plan_age"] == 2
    policy.act(obs)  # a replan: a fresh label
    third = policy.belief()
    assert third["plan_age"] == 1 and third["label_change"] == pytest.approx(
        float(np.linalg.norm(policy.diagnostics[-1].label - policy.diagnostics[-2].label)))


def test_tiebreak_margin_prefers_the_plan_furthest_into_the_clear(checkpoint):
    """Among equal lowest costs, ``tiebreak_margin`` picks the candidate least inside the wider margin; without it
    the least bent wins."""
    path, obs = checkpoint
    near = _with_obstacle_at_hand(obs)
    offset = np.array([0.0, 0.0, 0.8], np.float32)  # the box 80 cm above the hand: clear of the 1.5 cm inflation
    near.update(obstacle_points=near["obstacle_points"] + offset,
                obstacle_pose=near["obstacle_pose"] + np.r_[offset, 0, 0, 0, 0].astype(np.float32))
    for margin in (0.0, 1.0):
        policy = DetAugPolicy(checkpoint=path, k=8, seed=0, tiebreak_margin=margin)
        policy.reset(seed=5)
        labels = policy.sample_labels(near, 8)
        candidates = policy.plan(near, labels)
        policy.reset(seed=5)  # the same labels and noise again
        chosen = torch.as_tensor(policy.next_plan(near))
        costs, wide = policy.score(candidates, near), policy.score(candidates, near, policy.inflate + 1.0)
        tied = np.flatnonzero(np.round(costs, 6) == np.round(costs, 6).min())
        index = int(np.flatnonzero([torch.equal(chosen, c) for c in candidates])[0])
        assert index in tied
        if margin:
            assert wide[index] == pytest.approx(wide[tied].min())
        else:
            assert np.linalg.norm(labels[index]) == pytest.approx(np.linalg.norm(labels[tied], axis=1).min())
    assert len(tied) > 1 and len(set(np.round(wide[tied], 6))) > 1  # a real tie, broken two ways


def test_support_labels_are_uniform_within_each_transits_training_range(checkpoint):
    """``labels="support"``: the unbent label first, then per transit ``phi`` and ``theta`` inside the range the
    task's bent training labels span (and spread over it, not copies of training rows)."""
    path, obs = checkpoint
    policy = DetAugPolicy(checkpoint=path, k=400, labels="support", seed=0)
    policy.reset(seed=0)
    labels = policy.sample_labels(obs, 400)
    assert labels.shape == (400, policy.label_dim) and np.all(labels[0] == 0.0)
    bank = policy.labels.bank[policy.labels.task == int(np.argmax(obs["task_id"]))]
    for j in range(0, policy.label_dim, 2):
        phi, theta = np.hypot(bank[:, j], bank[:, j + 1]), np.arctan2(bank[:, j + 1], bank[:, j])
        got_phi, got_theta = np.hypot(labels[1:, j], labels[1:, j + 1]), np.arctan2(labels[1:, j + 1], labels[1:, j])
        if not (phi > 0).any():
            assert np.all(got_phi == 0.0)
            continue
        lo, hi = phi[phi > 0].min(), phi[phi > 0].max()
        assert got_phi.min() >= lo - 1e-5 and got_phi.max() <= hi + 1e-5
        assert theta[phi > 0].min() - 1e-5 <= got_theta.min() and got_theta.max() <= theta[phi > 0].max() + 1e-5
        if hi - lo > 1e-3:  # a continuous spread, not the bank's few rows
            assert len(np.unique(got_phi.round(6))) > 300
    policy.next_plan(obs)  # and they plan
    assert policy.diagnostics[-1].k == 400


def test_support_scale_stretches_phi_beyond_the_training_support(checkpoint):
    path, obs = checkpoint
    bank = DetAugPolicy(checkpoint=path, k=4).labels
    bank = bank.bank[bank.task == int(np.argmax(obs["task_id"]))]
    for scale in (1.0, 2.0):
        policy = DetAugPolicy(checkpoint=path, k=400, seed=0, support_scale=scale)
        policy.reset(seed=0)
        labels = policy.sample_labels(obs, 400)
        for j in range(0, policy.label_dim, 2):
            phi, got = np.hypot(bank[:, j], bank[:, j + 1]), np.hypot(labels[1:, j], labels[1:, j + 1])
            if not (phi > 0).any():
                continue
            hi = phi[phi > 0].max()
            assert got.max() <= scale * hi + 1e-5
            assert (got > hi + 1e-5).any() == (scale > 1.0)  # beyond the training support only when stretched
    with pytest.raises(ValueError, match="support_scale must be > 0"):
        DetAugPolicy(checkpoint=path, support_scale=0.0)



def test_wider_batches_are_drawn_only_while_no_candidate_is_free(checkpoint):
    """Inside a box every plan penetrates: the policy draws its 2 wider batches (phi up to 2x and 3x the
    training support) and chooses among all 3 x K; with every plan free it stops at the first batch."""
    path, obs = checkpoint
    policy = DetAugPolicy(checkpoint=path, k=8, seed=0, wider_batches=2)
    scales = []
    sample = policy.sample_labels
    policy.sample_labels = lambda o, k, scale=None: scales.append(scale) or sample(o, k, scale)
    policy.reset(seed=1)
    plan = policy.next_plan(_with_obstacle_at_hand(obs))
    diag = policy.diagnostics[-1]
    assert scales == [None, 2.0, 3.0] and diag.k == 24 and diag.best_cost > 0
    assert policy.score(torch.as_tensor(plan)[None], _with_obstacle_at_hand(obs))[0] == pytest.approx(
        diag.best_cost, rel=1e-5)
    scales.clear()
    policy.next_plan(obs)  # no obstacle: every plan is free
    assert scales == [None] and policy.diagnostics[-1].k == 8
    with pytest.raises(ValueError, match="wider_batches must be >= 0"):
        DetAugPolicy(checkpoint=path, wider_batches=-1)


def test_commit_keeps_the_previous_label_while_it_is_as_good_as_the_best(checkpoint):
    """With ``commit`` the previous replan's (bent) label is a candidate and wins a tie of free plans over the
    least bent; without it the fresh draw's least bent (the unbent label) wins; in penetration the lowest cost
    still comes first."""
    path, obs = checkpoint
    bent = DetAugPolicy(checkpoint=path, k=8, seed=0).sample_labels(obs, 8)[1]
    assert np.linalg.norm(bent) > 0
    for commit, expected in ((True, bent), (False, np.zeros_like(bent))):
        policy = DetAugPolicy(checkpoint=path, k=8, seed=0, commit=commit)
        policy.reset(seed=1)
        policy.next_plan(obs)  # no obstacle: every plan is free, the unbent label wins
        assert np.allclose(policy.diagnostics[-1].label, 0.0)
        policy.diagnostics[-1].label = bent  # as if a detour had been chosen
        policy.next_plan(obs)
        assert np.allclose(policy.diagnostics[-1].label, expected)
    policy.diagnostics[-1].label = bent
    policy.commit = True
    plan = policy.next_plan(_with_obstacle_at_hand(obs))
    diag = policy.diagnostics[-1]
    assert 0 < diag.best_cost <= diag.median_cost
    assert policy.score(torch.as_tensor(plan)[None], _with_obstacle_at_hand(obs))[0] == \
        pytest.approx(diag.best_cost, rel=1e-5)
