"""DiT denoiser over plan chunks, conditioned through AdaLN-Zero (bare ``nn`` blocks, no sampling logic).

A plan chunk ``x`` has shape ``(B, H, D)``: ``H`` timesteps of ``D`` features (plan state + action, see
:mod:`detaug_gym.models.dataset`). The token layout groups ``steps_per_token`` consecutive timesteps into
one token (``H / steps_per_token`` plan tokens), which is what makes a suite trainable on two CPU cores:
attention and MLP cost scale with the token count, and five 20 Hz steps per token still resolve motion at
4 Hz, far finer than the chunk's shape needs.

Conditioning, two paths:

* **AdaLN-Zero** (Peebles & Xie, DiT): ``c = phi_t(t) + phi_z(z) + proj(extra)`` modulates every block
  (shift, scale, gate) and the output layer. The modulation layers start at zero, so every block is the
  identity at initialisation; ``phi_z`` and ``proj`` end in zero-initialised layers too, so grafting a label
  or a point-cloud embedding onto a trained backbone leaves its output unchanged at step 0. With label
  dropout, ``phi_z(z)`` is replaced by a learned *null token* and the model samples unconditionally.
* **Observation prefix tokens**: the observation vector (robot state, object poses, task id) is projected
  to ``obs_tokens`` tokens placed before the plan tokens. We keep the observation out of the AdaLN path
  on purpose: the AdaLN path is the *adapter* that fine-tuning trains (paper, "Adapting a Pre-Trained
  Policy"), so the observation pathway belongs to the frozen backbone, and every plan token can attend to
  the object poses instead of receiving one global shift. The exact current robot state is additionally
  *inpainted* as the plan's first state by the flow sampler (:mod:`detaug_gym.models.flow`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass
class DiTConfig:
    """Architecture of :class:`DiT`. ``plan_dim``, ``obs_dim``, ``label_dim`` and ``extra_dim`` come from data."""

    plan_dim: int
    """D: features per plan timestep (plan state + action)."""
    obs_dim: int
    """C: length of the flattened observation conditioning vector."""
    horizon: int = 50
    """H: timesteps per plan chunk."""
    steps_per_token: int = 5
    """Consecutive timesteps packed into one token; must divide ``horizon``."""
    d_model: int = 128
    """Transformer width."""
    n_layers: int = 4
    """Number of AdaLN-Zero blocks."""
    n_heads: int = 4
    """Attention heads; must divide ``d_model``."""
    mlp_ratio: float = 4.0
    """Hidden width of each block's MLP, as a multiple of ``d_model``."""
    obs_tokens: int = 1
    """Observation prefix tokens."""
    label_dim: int = 0
    """L: augmentation label size (0: no label encoder, e.g. the ``base`` policy)."""
    extra_dim: int = 0
    """E: size of an extra conditioning vector added to ``c`` through a zero-initialised projection."""
    label_tokens: bool = False
    """Also add the label to the observation prefix tokens (a zero-initialised path beside AdaLN), so attention
    can combine it with the object poses: a sideways arc's direction depends on the chord the obs gives, which
    one global modulation hardly expresses (``benchmarks/label_fidelity.py``). False is the paper's network."""

    def __post_init__(self) -> None:
        if self.horizon % self.steps_per_token:
            raise ValueError(f"steps_per_token={self.steps_per_token} must divide horizon={self.horizon}")
        if self.d_model % self.n_heads:
            raise ValueError(f"n_heads={self.n_heads} must divide d_model={self.d_model}")
        if min(self.plan_dim, self.obs_dim, self.obs_tokens, self.n_layers) < 1:
            raise ValueError(f"plan_dim, obs_dim, obs_tokens and n_layers must be >= 1: {self}")

    @property
    def plan_tokens(self) -> int:
        return self.horizon // self.steps_per_token

    def to_dict(self) -> dict:
        return asdict(self)


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10_000.0) -> torch.Tensor:
    """Sinusoidal features of flow time ``t`` (B,) in [0, 1] -> (B, dim). ``t`` is scaled by 1000 so that
    the fastest frequencies resolve the 10-step sampler's grid."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = 1000.0 * t.float()[:, None] * freqs[None]
    emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
    return F.pad(emb, (0, dim % 2))


class TanhGELU(nn.Module):
    """GELU's tanh approximation, ``0.5 x (1 + tanh(u)) = x sigmoid(2u)`` with ``u = sqrt(2 / pi) (x + 0.044715
    x^3)``: the same function as ``nn.GELU(approximate="tanh")`` (within 5e-7), 1.6x faster on one CPU thread
    (benchmarks/detaug_latency.py), where the MLP's activation is a sixth of a replan."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(GELU_TANH_SCALE * (x + 0.044715 * x * x * x))


GELU_TANH_SCALE = 2.0 * math.sqrt(2.0 / math.pi)


def _zero(layer: nn.Linear) -> nn.Linear:
    nn.init.zeros_(layer.weight)
    nn.init.zeros_(layer.bias)
    return layer


class SelfAttention(nn.Module):
    """Multi-head bidirectional self-attention over all tokens."""

    def __init__(self, d_model: int, n_heads: int) -> None:
        super().__init__()
        self.n_heads = n_heads
        self.qkv = nn.Linear(d_model, 3 * d_model)
        self.proj = nn.Linear(d_model, d_model)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, d = x.shape
        q, k, v = self.qkv(x).view(b, n, 3, self.n_heads, d // self.n_heads).permute(2, 0, 3, 1, 4)
        y = F.scaled_dot_product_attention(q, k, v)
        return self.proj(y.transpose(1, 2).reshape(b, n, d))


class AdaLNZeroBlock(nn.Module):
    """Pre-norm transformer block whose norms are shifted/scaled and whose residual branches are gated by
    ``c``. ``modulation`` is zero-initialised, so the gates are 0 and the block is the identity at init."""

    def __init__(self, d_model: int, n_heads: int, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        hidden = int(d_model * mlp_ratio)
        self.norm1 = nn.LayerNorm(d_model, elementwise_affine=False, eps=1e-6)
        self.attn = SelfAttention(d_model, n_heads)
        self.norm2 = nn.LayerNorm(d_model, elementwise_affine=False, eps=1e-6)
        self.mlp = nn.Sequential(nn.Linear(d_model, hidden), TanhGELU(), nn.Linear(hidden, d_model))
        self.modulation = nn.Sequential(nn.SiLU(), _zero(nn.Linear(d_model, 6 * d_model)))

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        """x (B, N, d), c (B, d) -> (B, N, d)."""
        shift1, scale1, gate1, shift2, scale2, gate2 = self.modulation(c)[:, None].chunk(6, dim=-1)
        x = x + gate1 * self.attn(self.norm1(x) * (1 + scale1) + shift1)
        return x + gate2 * self.mlp(self.norm2(x) * (1 + scale2) + shift2)


class FinalLayer(nn.Module):
    """Modulated norm and a zero-initialised linear read-out from tokens to timesteps."""

    def __init__(self, d_model: int, out_dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(d_model, elementwise_affine=False, eps=1e-6)
        self.modulation = nn.Sequential(nn.SiLU(), _zero(nn.Linear(d_model, 2 * d_model)))
        self.linear = _zero(nn.Linear(d_model, out_dim))

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        shift, scale = self.modulation(c)[:, None].chunk(2, dim=-1)
        return self.linear(self.norm(x) * (1 + scale) + shift)


class DiT(nn.Module):
    """Velocity network ``v(x, t | obs, z, extra)`` over plan chunks; see the module docstring."""

    def __init__(self, config: DiTConfig) -> None:
        super().__init__()
        self.config = config
        d, token_dim = config.d_model, config.plan_dim * config.steps_per_token
        self.plan_in = nn.Linear(token_dim, d)
        self.obs_in = nn.Linear(config.obs_dim, config.obs_tokens * d)
        self.pos_emb = nn.Parameter(0.02 * torch.randn(config.obs_tokens + config.plan_tokens, d))
        self.time_mlp = nn.Sequential(nn.Linear(d, d), nn.SiLU(), nn.Linear(d, d))  # phi_t
        if config.label_dim > 0:  # phi_z and the null token
            self.label_mlp = nn.Sequential(nn.Linear(config.label_dim, d), nn.SiLU(), _zero(nn.Linear(d, d)))
            self.null_label = nn.Parameter(torch.zeros(d))
            if config.label_tokens:
                self.label_obs = nn.Sequential(nn.Linear(config.label_dim, d), nn.SiLU(),
                                               _zero(nn.Linear(d, config.obs_tokens * d)))
        elif config.label_tokens:
            raise ValueError("label_tokens needs label_dim > 0")
        if config.extra_dim > 0:
            self.extra_proj = _zero(nn.Linear(config.extra_dim, d))
        self.blocks = nn.ModuleList(
            AdaLNZeroBlock(d, config.n_heads, config.mlp_ratio) for _ in range(config.n_layers)
        )
        self.final = FinalLayer(d, token_dim)

    def condition(self, t: torch.Tensor, label: torch.Tensor | None = None, extra: torch.Tensor | None = None,
                  drop_label: torch.Tensor | None = None) -> torch.Tensor:
        """The AdaLN conditioning vector ``c`` (B, d).

        Args:
            t: flow time (B,).
            label: augmentation label (B, L), or ``None`` for the null token everywhere.
            extra: extra conditioning vector (B, E), e.g. a point-cloud embedding; ``None`` adds nothing.
            drop_label: (B,) bool, True where the label is replaced by the null token (label dropout).
        """
        c = self.time_mlp(timestep_embedding(t, self.config.d_model))
        if self.config.label_dim > 0:
            null = self.null_label.expand_as(c)
            if label is None:
                c = c + null
            else:
                z = self.label_mlp(label.to(c.dtype))
                c = c + (z if drop_label is None else torch.where(drop_label[:, None], null, z))
        elif label is not None and label.shape[-1] > 0:
            raise ValueError("this model has no label encoder (label_dim=0) but a label was given")
        if extra is not None:
            if self.config.extra_dim == 0:
                raise ValueError("this model has no extra conditioning (extra_dim=0) but `extra` was given")
            c = c + self.extra_proj(extra.to(c.dtype))
        return c

    def forward(self, x: torch.Tensor, t: torch.Tensor, obs_cond: torch.Tensor, label: torch.Tensor | None = None,
                extra: torch.Tensor | None = None, drop_label: torch.Tensor | None = None) -> torch.Tensor:
        """Predict the flow velocity.

        Args:
            x: noisy normalised plan (B, H, D).
            t: flow time (B,), 0 = noise, 1 = data.
            obs_cond: normalised observation vector (B, C).
            label, extra, drop_label: see :meth:`condition`.
        Returns:
            velocity (B, H, D).
        """
        cfg = self.config
        b, h, dim = x.shape
        if (h, dim) != (cfg.horizon, cfg.plan_dim):
            raise ValueError(f"x must be (B, {cfg.horizon}, {cfg.plan_dim}), got {tuple(x.shape)}")
        c = self.condition(t, label, extra, drop_label)
        plan = self.plan_in(x.reshape(b, cfg.plan_tokens, cfg.steps_per_token * dim))
        obs = self.obs_in(obs_cond).view(b, cfg.obs_tokens, cfg.d_model)
        if cfg.label_tokens and label is not None:  # the null token adds nothing here
            add = self.label_obs(label.to(obs.dtype))
            add = add if drop_label is None else add * (~drop_label)[:, None].to(add.dtype)
            obs = obs + add.view(b, cfg.obs_tokens, cfg.d_model)
        tokens = torch.cat([obs, plan], dim=1) + self.pos_emb
        for block in self.blocks:
            tokens = block(tokens, c)
        out = self.final(tokens[:, cfg.obs_tokens:], c)
        return out.reshape(b, h, dim)

    def adapter_modules(self) -> dict[str, nn.Module | nn.Parameter]:
        """The adapter for adapter-only fine-tuning: label encoder phi_z, null token, extra projection and
        every AdaLN modulation layer (paper, "Adapting a Pre-Trained Policy")."""
        parts: dict[str, nn.Module | nn.Parameter] = {}
        if self.config.label_dim > 0:
            parts["label_mlp"], parts["null_label"] = self.label_mlp, self.null_label
            if self.config.label_tokens:
                parts["label_obs"] = self.label_obs
        if self.config.extra_dim > 0:
            parts["extra_proj"] = self.extra_proj
        for i, block in enumerate(self.blocks):
            parts[f"blocks.{i}.modulation"] = block.modulation
        parts["final.modulation"] = self.final.modulation
        return parts
