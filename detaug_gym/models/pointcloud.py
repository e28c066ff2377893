"""DP3-style obstacle point-cloud encoder for the ``demogen`` baseline.

A shared per-point MLP (3 -> 64 -> 128 -> 256, LayerNorm + ReLU), a max-pool over points and a linear map
to a 64-D embedding (Ze et al., DP3; DemoGen uses the same encoder). Max-pooling makes it invariant to the
order of the points. The embedding reaches the DiT through the DiT's zero-initialised ``extra_proj``, so
adding this encoder to a trained backbone leaves its output unchanged at step 0.

An absent obstacle (a Free env, or a demo without a cloud) has mask 0 and gives a zero embedding.
"""

from __future__ import annotations

import torch
from torch import nn


class PointCloudEncoder(nn.Module):
    """``points (B, P, 3), mask (B,) or (B, P) -> (B, out_dim)``."""

    def __init__(self, widths: tuple[int, ...] = (64, 128, 256), out_dim: int = 64) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        width_in = 3
        for width in widths:
            layers += [nn.Linear(width_in, width), nn.LayerNorm(width), nn.ReLU()]
            width_in = width
        self.point_mlp = nn.Sequential(*layers)
        self.out = nn.Linear(width_in, out_dim)
        self.out_dim = out_dim

    def forward(self, points: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Encode clouds.

        Args:
            points: world-frame points (B, P, 3).
            mask: (B,) 1 where the sample has an obstacle, or (B, P) per-point validity; None = all valid.
        """
        features = self.point_mlp(points)  # (B, P, W)
        if mask is None:
            return self.out(features.max(dim=1).values)
        mask = mask.to(features.dtype).reshape(points.shape[0], -1)
        point_mask = mask.expand(-1, points.shape[1]) if mask.shape[1] == 1 else mask
        pooled = features.masked_fill(point_mask[..., None] <= 0, float("-inf")).max(dim=1).values
        present = (point_mask > 0).any(dim=1, keepdim=True)
        pooled = torch.where(present, pooled, torch.zeros_like(pooled))
        return self.out(pooled) * present.to(pooled.dtype)
