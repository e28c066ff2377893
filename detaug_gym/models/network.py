"""The trainable network of a flow policy: the DiT plus, for ``demogen``, the point-cloud encoder."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from detaug_gym.models.dit import DiT, DiTConfig
from detaug_gym.models.pointcloud import PointCloudEncoder


@dataclass
class NetworkConfig:
    """Everything needed to rebuild the network (saved in ``config.json`` under ``"network"``)."""

    dit: DiTConfig
    point_cloud: bool = False
    """Encode ``obstacle_points`` (DemoGen) into the DiT's extra conditioning."""
    point_embed_dim: int = 64
    """Point-cloud embedding size (the DiT's ``extra_dim`` when ``point_cloud``)."""

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> NetworkConfig:
        return cls(DiTConfig(**data["dit"]), bool(data.get("point_cloud", False)),
                   int(data.get("point_embed_dim", 64)))


class FlowNetwork(nn.Module):
    """``velocity = dit(x, t, obs, label, extra=point_encoder(points))``."""

    def __init__(self, config: NetworkConfig) -> None:
        super().__init__()
        if config.point_cloud and config.dit.extra_dim != config.point_embed_dim:
            raise ValueError("with point_cloud=True the DiT's extra_dim must equal point_embed_dim")
        self.config = config
        self.dit = DiT(config.dit)
        self.point_encoder = PointCloudEncoder(out_dim=config.point_embed_dim) if config.point_cloud else None

    def extra(self, points: torch.Tensor | None, point_mask: torch.Tensor | None) -> torch.Tensor | None:
        """The extra conditioning vector (B, E) or None (no encoder, or no cloud given)."""
        if self.point_encoder is None or points is None:
            return None
        return self.point_encoder(points, point_mask)

    def forward(self, x: torch.Tensor, t: torch.Tensor, obs: torch.Tensor, label: torch.Tensor | None = None,
                points: torch.Tensor | None = None, point_mask: torch.Tensor | None = None,
                drop_label: torch.Tensor | None = None) -> torch.Tensor:
        """Velocity (B, H, D); shapes as in :meth:`DiT.forward`, ``points`` (B, P, 3)."""
        return self.dit(x, t, obs, label, self.extra(points, point_mask), drop_label)

    def adapter_parameters(self) -> list[nn.Parameter]:
        """Parameters trained in adapter-only fine-tuning: the DiT's adapter (label encoder, null token,
        extra projection, AdaLN modulation) and the point-cloud encoder when there is one."""
        params: list[nn.Parameter] = []
        for part in self.dit.adapter_modules().values():
            params += [part] if isinstance(part, nn.Parameter) else list(part.parameters())
        if self.point_encoder is not None:
            params += list(self.point_encoder.parameters())
        return params

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())
