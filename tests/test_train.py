"""Training, checkpoints and the FlowPolicy protocol, end to end on tiny synthetic data (CPU, seconds)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from detaug_gym import train as train_module
from detaug_gym.models import CheckpointError, FlowPolicy, load_checkpoint
from detaug_gym.models.dataset import PlanLayout, WindowDataset, read_demos
from detaug_gym.models.synthetic import write_synthetic_demos
from detaug_gym.policies import load
from detaug_gym.train import TrainConfig, build_network, parse_args, train

TINY = dict(horizon=10, steps_per_token=2, d_model=64, layers=2, heads=4, obs_tokens=1, batch_size=64,
            warmup_steps=30, lr=2e-3, threads=1, progress=False, log_every=10, checkpoint_every=1000)


def single_obs(demo, t: int) -> dict[str, np.ndarray]:
    return {key: value[t] for key, value in demo.obs.items()}


@pytest.fixture(scope="module")
def detaug_run(tmp_path_factory):
    """A tiny detaug policy trained to overfit 4 demos (module-scoped: trained once)."""
    root = tmp_path_factory.mktemp("detaug")
    data = write_synthetic_demos(root / "demos.hdf5", n_demos=4, length=24, label_dim=4)
    cfg = TrainConfig(method="detaug", data=str(data), out=str(root / "policy"), steps=700, label_dropout=0.1,
                      action_steps=3, **TINY)
    summary = train(cfg)
    return cfg, summary


def test_tiny_model_overfits_and_reproduces_the_data(detaug_run):
    cfg, summary = detaug_run
    rows = list(csv.DictReader(open(Path(cfg.out) / "train_log.csv")))
    first, last = float(rows[0]["loss"]), float(rows[-1]["loss"])
    assert summary["steps"] == 700 and last < first / 10, (first, last)
    policy = load(cfg.out, seed=0)
    demos = read_demos(cfg.data)
    layout = PlanLayout()
    spread = np.ptp(np.concatenate([np.c_[layout.state_vector(d.obs), d.actions] for d in demos]), axis=0)
    errors = []
    for demo in demos:
        for t in (0, 8):
            plans = policy.plan(single_obs(demo, t), np.tile(demo.label, (4, 1))).numpy()
            truth = np.c_[layout.state_vector(demo.obs), demo.actions][t:t + cfg.horizon]
            assert np.allclose(plans[:, 0, layout.state_slice], truth[0, layout.state_slice], atol=1e-4)
            errors.append(np.abs(plans - truth).mean(axis=(0, 1)) / np.maximum(spread, 1e-3))
    assert np.mean(errors) < 0.06, np.mean(errors, axis=0)


def test_null_token_path_and_label_support(detaug_run):
    cfg, _ = detaug_run
    policy = FlowPolicy(load_checkpoint(cfg.out), label_mode="null", seed=0)  # plain, not DetAug
    demo = read_demos(cfg.data)[1]
    plans = policy.plan(single_obs(demo, 0), None, num_samples=3)
    assert plans.shape == (3, cfg.horizon, 19) and torch.isfinite(plans).all()
    policy.reset(seed=1)
    assert policy.act(single_obs(demo, 0)).shape == (7,)
    assert policy.labels.bank.shape == (4, 4) and np.allclose(policy.labels.bank[1], demo.label)
    with pytest.raises(ValueError, match="labels"):
        policy.plan(single_obs(demo, 0), np.zeros((2, 4)), num_samples=3)


def test_save_load_roundtrip_gives_identical_outputs(detaug_run):
    cfg, _ = detaug_run
    a, b = load_checkpoint(cfg.out), load_checkpoint(cfg.out)
    x, t, obs = torch.randn(2, cfg.horizon, 19), torch.rand(2), torch.randn(2, a.network.config.dit.obs_dim)
    label = torch.randn(2, 4)
    assert torch.equal(a.network(x, t, obs, label), b.network(x, t, obs, label))
    state = torch.load(Path(cfg.out) / "train_state.pt", weights_only=False)["ema"]
    assert all(torch.equal(state[k], v) for k, v in a.network.state_dict().items())  # model.pt holds the EMA
    demo = read_demos(cfg.data)[2]
    p1, p2 = FlowPolicy(a, seed=5), FlowPolicy(b, seed=5)
    assert torch.equal(p1.plan(single_obs(demo, 3), demo.label[None]), p2.plan(single_obs(demo, 3), demo.label[None]))


def test_act_replans_every_n_steps_and_reset_clears_queue(detaug_run):
    cfg, _ = detaug_run
    policy = FlowPolicy(load_checkpoint(cfg.out), action_steps=4)
    calls = []
    original = policy.next_plan
    policy.next_plan = lambda obs: calls.append(1) or original(obs)
    demo = read_demos(cfg.data)[0]
    policy.reset(seed=3)
    actions = [policy.act(single_obs(demo, t)) for t in range(9)]
    assert len(calls) == 3  # steps 0, 4, 8
    assert all(a.shape == (7,) and a.dtype == np.float32 and np.abs(a).max() <= 1.0 for a in actions)
    assert all(a[-1] in (-1.0, 1.0) for a in actions)
    policy.reset(seed=3)
    again = policy.act(single_obs(demo, 0))
    assert len(calls) == 4 and np.array_equal(again, actions[0])  # queue cleared, same seed, same plan
    with pytest.raises(ValueError, match="action_steps"):
        load(cfg.out, action_steps=cfg.horizon + 1)


def test_checkpoint_carries_its_replan_period(detaug_run, tmp_path):
    cfg, _ = detaug_run
    assert json.loads((Path(cfg.out) / "config.json").read_text())["policy"] == {"action_steps": 3}
    assert load(cfg.out).action_steps == 3  # the trained-with default
    assert load(cfg.out, action_steps=7).action_steps == 7  # a load overrides it
    legacy = tmp_path / "legacy"
    legacy.mkdir()
    for name in ("model.pt", "normalization.json"):
        (legacy / name).write_bytes((Path(cfg.out) / name).read_bytes())
    config = json.loads((Path(cfg.out) / "config.json").read_text())
    del config["policy"]
    (legacy / "config.json").write_text(json.dumps(config))
    assert load(legacy).action_steps == 10  # no policy section: the paper's N
    with pytest.raises(SystemExit, match="action-steps"):
        train(replace(cfg, out=str(tmp_path / "bad"), action_steps=cfg.horizon + 1))


def test_zero_label_weight_shifts_batches_to_unaugmented_windows(detaug_run):
    cfg, _ = detaug_run  # demos 0, 4, ... carry the zero label: one window in four
    demos = read_demos(cfg.data)
    counts = {}
    for weight in (1.0, 3.0):
        data = WindowDataset(demos, cfg.horizon, use_labels=True, zero_label_weight=weight)
        batch = data.sample(4000, torch.Generator().manual_seed(0))
        counts[weight] = float((batch.label == 0).all(dim=1).float().mean())
    assert abs(counts[1.0] - 0.25) < 0.03 and abs(counts[3.0] - 0.5) < 0.03, counts  # 3 * 1/4 : 3/4
    with pytest.raises(ValueError, match="labelled demos"):
        WindowDataset(demos, cfg.horizon, zero_label_weight=2.0)
    with pytest.raises(SystemExit, match="detaug only"):
        train(replace(cfg, method="base", zero_label_weight=2.0))


def test_resume_after_interruption_matches_an_uninterrupted_run(tmp_path, monkeypatch):
    data = write_synthetic_demos(tmp_path / "demos.hdf5", n_demos=3, length=16)
    base = dict(TINY, batch_size=16, d_model=32)
    straight = TrainConfig(method="base", data=str(data), out=str(tmp_path / "straight"), steps=30, snapshot_every=10,
                           **base)
    train(straight)
    resumed = replace(straight, out=str(tmp_path / "resumed"))
    real_step = train_module.train_step
    count = {"n": 0}

    def interrupt_at_12(*args):
        count["n"] += 1
        if count["n"] > 12:
            raise KeyboardInterrupt
        return real_step(*args)

    monkeypatch.setattr(train_module, "train_step", interrupt_at_12)
    with pytest.raises(SystemExit, match="resume"):
        train(resumed)
    assert json.loads((tmp_path / "resumed" / "config.json").read_text())["summary"]["steps"] == 12
    monkeypatch.setattr(train_module, "train_step", real_step)
    assert train(resumed)["steps"] == 30  # the same command continues
    a = torch.load(tmp_path / "straight" / "model.pt")
    b = torch.load(tmp_path / "resumed" / "model.pt")
    assert all(torch.allclose(a[k], b[k], atol=1e-6) for k in a)
    # snapshots: loadable checkpoint folders of the EMA weights at every 10th step, the same after a resume
    for run in ("straight", "resumed"):
        assert sorted(p.name for p in (tmp_path / run / "snapshots").iterdir()) == [
            "step_000010", "step_000020", "step_000030"]
    snap = load_checkpoint(train_module.snapshot_dir(tmp_path / "resumed", 20))
    assert snap.config["summary"]["steps"] == 20
    a20 = torch.load(train_module.snapshot_dir(tmp_path / "straight", 20) / "model.pt")
    assert all(torch.allclose(a20[k], snap.network.state_dict()[k], atol=1e-6) for k in a20)
    assert not all(torch.allclose(a20[k], a[k]) for k in a)
    with pytest.raises(SystemExit, match="different run"):
        train(replace(resumed, lr=1e-2))


def test_compiled_training_follows_the_eager_run(tmp_path):
    """``--compile`` runs the same computation through inductor's kernels: the loss curve and the weights match
    eager mode's to float rounding, and the checkpoint loads as any other (its keys have no compile prefix)."""
    data = write_synthetic_demos(tmp_path / "demos.hdf5", n_demos=3, length=16)
    eager = TrainConfig(method="base", data=str(data), out=str(tmp_path / "eager"), steps=20,
                        **dict(TINY, batch_size=16, d_model=32, log_every=5))
    compiled = replace(eager, out=str(tmp_path / "compiled"), compile=True)
    train(eager)
    train(compiled)
    losses = [[float(r["loss"]) for r in csv.DictReader(open(Path(c.out) / "train_log.csv"))]
              for c in (eager, compiled)]
    assert len(losses[1]) == 4 and np.allclose(losses[0], losses[1], rtol=1e-3), losses
    a, b = (torch.load(Path(c.out) / "model.pt") for c in (eager, compiled))
    assert a.keys() == b.keys() and all(torch.allclose(a[k], b[k], atol=1e-4) for k in a)
    assert load(compiled.out, seed=0) is not None


def test_demogen_policy_reads_obstacle_points(tmp_path):
    data = write_synthetic_demos(tmp_path / "demos.hdf5", n_demos=4, length=16, with_points=True)
    cfg = TrainConfig(method="demogen", data=str(data), out=str(tmp_path / "demogen"), steps=5, n_points=32,
                      **dict(TINY, d_model=32))
    train(cfg)
    policy = load(cfg.out, seed=0)
    assert policy.network.point_encoder is not None and policy.checkpoint.n_points == 32
    obs = single_obs(read_demos(data)[0], 0)
    obs |= {"obstacle_points": np.random.default_rng(0).normal(size=(256, 3)).astype(np.float32),
            "obstacle_mask": np.ones(1, np.float32)}
    assert policy.act(obs).shape == (7,)
    obs["obstacle_mask"] = np.zeros(1, np.float32)  # a Free env: empty cloud
    policy.reset(seed=0)
    assert policy.act(obs).shape == (7,)


def test_adapter_only_finetune_starts_from_base_and_freezes_backbone(tmp_path):
    base_data = write_synthetic_demos(tmp_path / "base.hdf5", n_demos=3, length=16)
    aug_data = write_synthetic_demos(tmp_path / "aug.hdf5", n_demos=4, length=16, label_dim=4, seed=1)
    common = dict(TINY, d_model=32, batch_size=16)
    train(TrainConfig(method="base", data=str(base_data), out=str(tmp_path / "base"), steps=20, **common))
    base = load_checkpoint(tmp_path / "base")
    cfg = TrainConfig(method="detaug", data=str(aug_data), out=str(tmp_path / "adapter"), steps=10,
                      init_from=str(tmp_path / "base"), adapter_only=True, **common)
    # at step 0 the grafted label changes nothing
    grafted = build_network(cfg, train_module.load_data(cfg, base), base)
    x, t = torch.randn(2, 10, 19), torch.rand(2)
    obs = torch.randn(2, base.network.config.dit.obs_dim)
    assert torch.equal(grafted(x, t, obs, torch.randn(2, 4)), base.network(x, t, obs))
    train(cfg)
    tuned = load_checkpoint(tmp_path / "adapter")
    adapter_ids = {id(p) for p in tuned.network.adapter_parameters()}
    adapter = {n for n, p in tuned.network.named_parameters() if id(p) in adapter_ids}
    before, after = base.network.state_dict(), tuned.network.state_dict()
    frozen = [k for k in before if k not in adapter]
    assert frozen and all(torch.equal(before[k], after[k]) for k in frozen)
    assert any(not torch.equal(before[k], after[k]) for k in before if k in adapter)


def test_finetune_observes_through_the_keys_its_base_was_trained_on(tmp_path, monkeypatch):
    """A base trained before a derived key joined OBS_KEYS stays fine-tunable: its fine-tunes read its keys."""
    base_data = write_synthetic_demos(tmp_path / "base.hdf5", n_demos=3, length=16)
    aug_data = write_synthetic_demos(tmp_path / "aug.hdf5", n_demos=3, length=16, label_dim=4, seed=1)
    common = dict(TINY, d_model=32, batch_size=16)
    older = tuple(k for k in train_module.OBS_KEYS if k != "object_pair_rel_pos")
    with monkeypatch.context() as patch:
        patch.setattr(train_module, "OBS_KEYS", older)
        train(TrainConfig(method="base", data=str(base_data), out=str(tmp_path / "base"), steps=3, **common))
    assert load_checkpoint(tmp_path / "base").obs_keys == older
    train(TrainConfig(method="detaug", data=str(aug_data), out=str(tmp_path / "tuned"), steps=3,
                      init_from=str(tmp_path / "base"), **common))
    tuned = load(tmp_path / "tuned", seed=0)
    assert tuned.checkpoint.obs_keys == older
    assert tuned.act(single_obs(read_demos(aug_data)[0], 0)).shape == (7,)


def test_missing_or_corrupt_checkpoint_names_the_train_command(tmp_path, detaug_run):
    with pytest.raises(CheckpointError, match=r"python -m detaug_gym\.train --method base .*--out .*base"):
        load(tmp_path / "policies" / "base" / "spatial")
    cfg, _ = detaug_run
    broken = tmp_path / "detaug" / "spatial"
    broken.mkdir(parents=True)
    for name in ("config.json", "normalization.json"):
        (broken / name).write_bytes((Path(cfg.out) / name).read_bytes())
    (broken / "model.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match=r"(?s)corrupt.*--method detaug"):
        load_checkpoint(broken)
    (broken / "model.pt").unlink()
    with pytest.raises(CheckpointError, match="model.pt missing"):
        load_checkpoint(broken)


def test_data_files_are_pooled_and_unlabelled_demos_get_the_zero_label(tmp_path):
    labelled = write_synthetic_demos(tmp_path / "aug.hdf5", n_demos=3, length=16, label_dim=4)
    plain = write_synthetic_demos(tmp_path / "plain.hdf5", n_demos=2, length=16, seed=1)
    cfg = TrainConfig(method="detaug", data=f"{labelled}, {plain}", out=str(tmp_path / "o"), **TINY)
    data = train_module.load_data(cfg)
    assert data.label_dim == 4 and len(data.labels) == 5
    assert torch.count_nonzero(data.labels[:3]) > 0 and torch.count_nonzero(data.labels[3:]) == 0
    with pytest.raises(SystemExit, match="missing.hdf5: no such file"):
        train(replace(cfg, data=f"{labelled},{tmp_path / 'missing.hdf5'}"))


def test_cli_errors_and_options(tmp_path):
    result = subprocess.run([sys.executable, "-m", "detaug_gym.train", "--method", "base"],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode != 0 and "--data is required" in result.stderr
    with pytest.raises(SystemExit, match="no such file"):
        train(TrainConfig(data=str(tmp_path / "missing.hdf5"), out=str(tmp_path / "o")))
    cfg = parse_args(["--method", "detaug", "--data", "x.hdf5", "--out", "o", "--d-model", "64", "--adapter-only"])
    assert cfg.method == "detaug" and cfg.d_model == 64 and cfg.adapter_only


def test_default_model_checkpoint_is_under_10_mb():
    cfg = TrainConfig(method="detaug")
    data = type("D", (), {"layout": PlanLayout(), "obs_dim": 69, "label_dim": 8})()  # Long-suite sizes
    network = build_network(cfg, data)
    size = sum(v.numel() * v.element_size() for v in network.state_dict().values())
    assert size < 10e6, size
