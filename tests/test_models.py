"""Unit tests of the flow-policy building blocks (no training): DiT, flow sampler, windows, encoder."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from detaug_gym.models.dataset import PlanLayout, WindowDataset, observation_vector, pad_window, read_demos
from detaug_gym.models.dit import AdaLNZeroBlock, DiT, DiTConfig
from detaug_gym.models.flow import Guidance, Inpaint, euler_times, flow_matching_loss, sample
from detaug_gym.models.network import FlowNetwork, NetworkConfig
from detaug_gym.models.normalize import Normalizer
from detaug_gym.models.pointcloud import PointCloudEncoder
from detaug_gym.models.policy import shift_plan
from detaug_gym.models.synthetic import write_synthetic_demos


def tiny_config(**overrides) -> DiTConfig:
    base = dict(plan_dim=5, obs_dim=6, horizon=8, steps_per_token=2, d_model=32, n_layers=2, n_heads=4,
                obs_tokens=2, label_dim=3)
    return DiTConfig(**(base | overrides))


def randomize(module: torch.nn.Module, seed: int = 0) -> None:
    """Give every parameter (zero-initialised ones too) random values, like a trained network."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(0.2 * torch.randn(p.shape, generator=gen))


def test_adaln_zero_block_is_identity_at_init():
    torch.manual_seed(0)
    block = AdaLNZeroBlock(32, 4)
    x, c = torch.randn(3, 7, 32), torch.randn(3, 32)
    assert torch.equal(block(x, c), x)


def test_dit_shapes_label_paths_and_zero_output_at_init():
    torch.manual_seed(0)
    model = DiT(tiny_config())
    x, t, obs = torch.randn(4, 8, 5), torch.rand(4), torch.randn(4, 6)
    assert torch.equal(model(x, t, obs, torch.randn(4, 3)), torch.zeros(4, 8, 5))  # zero read-out at init
    randomize(model)
    label = torch.randn(4, 3)
    null = model(x, t, obs, None)  # null token everywhere
    dropped = model(x, t, obs, label, drop_label=torch.ones(4, dtype=torch.bool))
    assert null.shape == (4, 8, 5) and torch.isfinite(null).all()
    assert torch.allclose(null, dropped)
    assert not torch.allclose(null, model(x, t, obs, label))
    mixed = model(x, t, obs, label, drop_label=torch.tensor([True, False, True, False]))
    assert torch.allclose(mixed[0], null[0]) and torch.allclose(mixed[1], model(x, t, obs, label)[1])


def test_label_tokens_start_as_the_adaln_only_network_and_reach_the_obs_tokens():
    """``label_tokens``: grafted onto a trained AdaLN-only DiT it changes nothing at step 0; trained, the label
    changes the output through the observation tokens too, and a dropped label (null) adds nothing there."""
    torch.manual_seed(0)
    plain = DiT(tiny_config())
    randomize(plain)
    tokens = DiT(tiny_config(label_tokens=True))
    missing, unexpected = tokens.load_state_dict(plain.state_dict(), strict=False)
    assert not unexpected and all(k.startswith("label_obs") for k in missing)
    x, t, obs, label = torch.randn(4, 8, 5), torch.rand(4), torch.randn(4, 6), torch.randn(4, 3)
    assert torch.equal(tokens(x, t, obs, label), plain(x, t, obs, label))
    randomize(tokens.label_obs, seed=1)
    assert not torch.allclose(tokens(x, t, obs, label), plain(x, t, obs, label))
    dropped = torch.ones(4, dtype=torch.bool)
    assert torch.allclose(tokens(x, t, obs, label, drop_label=dropped), plain(x, t, obs, None))
    assert "label_obs" in {name.split(".")[0] for name in tokens.adapter_modules()}
    with pytest.raises(ValueError, match="label_tokens needs label_dim"):
        DiT(tiny_config(label_dim=0, label_tokens=True))


def test_dit_rejects_bad_layout_and_unexpected_inputs():
    with pytest.raises(ValueError, match="divide horizon"):
        tiny_config(horizon=9)
    model = DiT(tiny_config(label_dim=0))
    with pytest.raises(ValueError, match="no label encoder"):
        model(torch.randn(1, 8, 5), torch.rand(1), torch.randn(1, 6), torch.randn(1, 3))
    with pytest.raises(ValueError, match="no extra"):
        model(torch.randn(1, 8, 5), torch.rand(1), torch.randn(1, 6), extra=torch.randn(1, 4))


def test_adapter_is_label_encoder_null_token_and_modulation():
    model = FlowNetwork(NetworkConfig(tiny_config(extra_dim=64), point_cloud=True, point_embed_dim=64))
    adapter = {id(p) for p in model.adapter_parameters()}
    names = {n for n, p in model.named_parameters() if id(p) in adapter}
    assert any("label_mlp" in n for n in names) and "dit.null_label" in names
    assert any("modulation" in n for n in names) and any("point_encoder" in n for n in names)
    assert not any(n.startswith(("dit.plan_in", "dit.obs_in", "dit.time_mlp")) or ".attn." in n or ".mlp." in n
                   for n in names)


def test_point_encoder_permutation_invariant_and_empty_mask():
    torch.manual_seed(0)
    enc = PointCloudEncoder()
    pts = torch.randn(2, 50, 3)
    perm = pts[:, torch.randperm(50)]
    assert torch.allclose(enc(pts), enc(perm), atol=1e-6)
    assert torch.allclose(enc(pts, torch.tensor([[1.0], [0.0]]))[1], torch.zeros(64))
    point_mask = torch.ones(2, 50)
    point_mask[:, 25:] = 0
    assert torch.allclose(enc(pts, point_mask), enc(pts[:, :25]), atol=1e-6)


def test_zero_initialised_point_encoder_leaves_backbone_unchanged():
    torch.manual_seed(0)
    base = FlowNetwork(NetworkConfig(tiny_config(label_dim=0)))
    randomize(base)
    demogen = FlowNetwork(NetworkConfig(tiny_config(label_dim=0, extra_dim=64), point_cloud=True))
    missing, unexpected = demogen.load_state_dict(base.state_dict(), strict=False)
    assert not unexpected and all(k.startswith(("point_encoder", "dit.extra_proj")) for k in missing)
    x, t, obs = torch.randn(3, 8, 5), torch.rand(3), torch.randn(3, 6)
    out = demogen(x, t, obs, points=torch.randn(3, 40, 3), point_mask=torch.ones(3, 1))
    assert torch.equal(out, base(x, t, obs))


def test_euler_sampler_reaches_a_point_target_and_holds_inpainted_entries():
    target = torch.tensor([[0.5, -1.0, 2.0]]).expand(4, 2, 3)

    def exact_velocity(x, t):  # the exact flow to a single data point along x_t = (1 - t) x0 + t x1
        return (target - x) / (1.0 - t).view(-1, 1, 1)

    assert euler_times(10)[0] == 0.0 and euler_times(10)[-1] == pytest.approx(1.0)
    x = sample(exact_velocity, (4, 2, 3), steps=10, generator=torch.Generator().manual_seed(0))
    assert torch.allclose(x, target, atol=1e-5)
    mask = torch.zeros(1, 2, 3, dtype=torch.bool)
    mask[0, 0, :2] = True
    inpaint = Inpaint(mask, torch.full((1, 2, 3), 7.0))
    x = sample(lambda x, t: torch.zeros_like(x), (4, 2, 3), inpaint=inpaint)
    assert (x[:, 0, :2] == 7.0).all()
    # partial noise: starting near the end from a plan keeps most of it
    plan = torch.randn(4, 2, 3)
    x = sample(lambda x, t: torch.zeros_like(x), (4, 2, 3), t_start=0.99, steps=1, x_start=plan)
    assert (x - plan).abs().max() < 0.1


def test_guidance_lowers_cost_only_late():
    cost = Guidance(cost=lambda x, t: (x - 3.0).pow(2).sum(dim=(1, 2)), scale=0.2, t_min=0.8)
    gen = torch.Generator().manual_seed(0)
    plain = sample(lambda x, t: torch.zeros_like(x), (8, 4, 2), generator=gen)
    gen.manual_seed(0)
    guided = sample(lambda x, t: torch.zeros_like(x), (8, 4, 2), guidance=cost, generator=gen)
    assert (cost.cost(guided, 1.0) < cost.cost(plain, 1.0)).all()
    gen.manual_seed(0)
    never = sample(lambda x, t: torch.zeros_like(x), (8, 4, 2), generator=gen,
                   guidance=Guidance(cost.cost, scale=0.2, t_min=1.1))
    assert torch.equal(never, plain)


def test_flow_loss_ignores_inpainted_entries():
    x1 = torch.randn(6, 4, 3)
    mask = torch.zeros(1, 4, 3, dtype=torch.bool)
    mask[0, 0] = True

    def bad_on_known(x, t):  # perfect except on the known entries
        return torch.where(mask, torch.full_like(x, 1e3), torch.zeros_like(x))

    assert flow_matching_loss(bad_on_known, x1, Inpaint(mask, x1)) < 10.0
    assert flow_matching_loss(bad_on_known, x1) > 1e3


def test_normalizer_roundtrip_and_constant_dims():
    data = np.c_[np.linspace(-2, 4, 20), np.full(20, 3.0)]
    for mode in ("minmax", "meanstd"):
        norm = Normalizer.fit(data, mode)
        back = Normalizer.from_dict(norm.to_dict())
        assert np.allclose(back.unnormalize(back.normalize(data)), data, atol=1e-5)
        assert np.allclose(norm.normalize(data)[:, 1], 0.0)
    assert np.allclose(Normalizer.fit(data).normalize(data)[:, 0].min(), -1.0)
    t = torch.tensor(data, dtype=torch.float32, requires_grad=True)
    Normalizer.fit(data).normalize(t).sum().backward()
    assert t.grad is not None


def test_window_padding_holds_final_state_and_gripper(tmp_path):
    states = np.arange(12, dtype=np.float32).reshape(4, 3)
    actions = np.tile(np.r_[0.3 * np.ones(6), 1.0], (4, 1)).astype(np.float32)
    window = pad_window(states, actions, start=2, horizon=5)
    assert np.array_equal(window[:2, :3], states[2:])
    assert np.array_equal(window[2:, :3], np.tile(states[-1], (3, 1)))
    assert np.array_equal(window[2:, 3:], np.tile(np.r_[np.zeros(6), 1.0], (3, 1)))
    # the same through the dataset, on a synthetic file
    path = write_synthetic_demos(tmp_path / "d.hdf5", n_demos=2, length=12, label_dim=4)
    demos = read_demos(path)
    data = WindowDataset(demos, horizon=8, use_labels=True)
    assert len(data) == 24
    last = data.window(torch.tensor([11]))  # last step of demo 0: 1 real row + 7 padded
    plan = data.normalizers["plan"].unnormalize(last.plan[0].numpy())
    layout = PlanLayout()
    final_state = layout.state_vector(demos[0].obs)[-1]
    assert np.allclose(plan[:, layout.state_slice], final_state, atol=1e-5)
    assert np.allclose(plan[1:, layout.action_slice][:, :6], 0.0, atol=1e-5)
    assert np.allclose(plan[1:, -1], demos[0].actions[-1, -1], atol=1e-5)
    assert np.allclose(plan[0, layout.action_slice], demos[0].actions[-1], atol=1e-5)
    assert torch.equal(last.label[0], torch.from_numpy(demos[0].label))


def test_observation_vector_uses_rotation_columns():
    obs = {"eef_quat": np.array([[1.0, 0.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0]])}  # q and -q: same rotation
    vec = observation_vector(obs, ("eef_quat",))
    assert vec.shape == (2, 6) and np.allclose(vec[0], vec[1])
    assert np.allclose(vec[0], [1, 0, 0, 0, -1, 0])


def test_object_rel_pos_is_derived_from_stored_keys_and_masked():
    obs = {"eef_pos": np.array([[0.1, 0.2, 1.0]]), "object_mask": np.array([[1.0, 0.0]]),
           "object_poses": np.array([[[0.3, 0.1, 0.9, 0, 0, 0, 1], [5.0, 5.0, 5.0, 0, 0, 0, 1]]])}
    vec = observation_vector(obs, ("object_rel_pos",))
    assert np.allclose(vec, [[0.2, -0.1, -0.1, 0.0, 0.0, 0.0]])
    with pytest.raises(KeyError, match="eef_pos"):
        observation_vector({k: v for k, v in obs.items() if k != "eef_pos"}, ("object_rel_pos",))


def test_object_pair_rel_pos_gives_every_pair_and_masks_absent_slots():
    poses = np.zeros((1, 3, 7))
    poses[0, :, :3] = [[0.1, 0.0, 0.9], [0.3, -0.2, 0.9], [9.0, 9.0, 9.0]]
    obs = {"object_poses": poses, "object_mask": np.array([[1.0, 1.0, 0.0]])}
    vec = observation_vector(obs, ("object_pair_rel_pos",))
    # pairs (0, 1), (0, 2), (1, 2): slot 2 is absent, so its pairs are zero
    assert np.allclose(vec, [[0.2, -0.2, 0.0, 0, 0, 0, 0, 0, 0]])
    with pytest.raises(KeyError, match="object_mask"):
        observation_vector({"object_poses": poses}, ("object_pair_rel_pos",))


def test_shift_plan_pads_like_training_windows():
    plan = torch.arange(2 * 5 * 9, dtype=torch.float32).reshape(2, 5, 9)
    shifted = shift_plan(plan, 2)
    assert shifted.shape == plan.shape and torch.equal(shifted[:, :3], plan[:, 2:])
    assert torch.equal(shifted[:, 3:, :2], plan[:, -1:, :2].expand(-1, 2, -1))
    assert (shifted[:, 3:, 2:8] == 0).all() and torch.equal(shifted[:, 3:, 8], plan[:, -1:, 8].expand(-1, 2))
