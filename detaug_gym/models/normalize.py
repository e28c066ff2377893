"""Per-dimension affine normalisation, fitted on the training data and saved with the model.

``normalize(x) = (x - center) / scale``. Two fits:

* ``"minmax"`` maps the data range of every dim to [-1, 1] (plans: the flow's noise is unit-scale, and
  bounded targets keep the actions inside the env's [-1, 1] box after unnormalising);
* ``"meanstd"`` standardises (observations: robust to a few outlying object poses).

``scale`` is floored at ``min_scale`` (in data units) so that a dimension that is constant in the data (an
object that never moves, a one-hot that is always on) maps to 0 instead of dividing by ~0, and a small
change at test time does not explode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

MODES = ("minmax", "meanstd")


@dataclass
class Normalizer:
    """Affine map with per-dim ``center`` and ``scale`` (both shape (D,))."""

    center: np.ndarray
    scale: np.ndarray
    mode: str = "minmax"

    @classmethod
    def fit(cls, data: np.ndarray, mode: str = "minmax", min_scale: float = 1e-2) -> Normalizer:
        """Fit on ``data`` (N, D) (any leading dims are flattened)."""
        if mode not in MODES:
            raise ValueError(f"unknown normalisation mode {mode!r}; valid: {', '.join(MODES)}")
        flat = np.asarray(data, dtype=np.float64).reshape(-1, np.shape(data)[-1])
        if flat.shape[0] == 0 or not np.isfinite(flat).all():
            raise ValueError("cannot fit a normaliser on empty or non-finite data")
        if mode == "minmax":
            low, high = flat.min(0), flat.max(0)
            center, scale = (low + high) / 2.0, (high - low) / 2.0
        else:
            center, scale = flat.mean(0), flat.std(0)
        return cls(center.astype(np.float32), np.maximum(scale, min_scale).astype(np.float32), mode)

    @property
    def dim(self) -> int:
        return int(self.center.shape[0])

    def _params(self, x):
        if isinstance(x, torch.Tensor):
            return (torch.as_tensor(self.center, dtype=x.dtype, device=x.device),
                    torch.as_tensor(self.scale, dtype=x.dtype, device=x.device))
        return self.center, self.scale

    def normalize(self, x):
        """Data units -> normalised; numpy arrays or torch tensors (differentiable), shape (..., D)."""
        center, scale = self._params(x)
        return (x - center) / scale

    def unnormalize(self, x):
        """Normalised -> data units; numpy arrays or torch tensors (differentiable), shape (..., D)."""
        center, scale = self._params(x)
        return x * scale + center

    def to_dict(self) -> dict:
        return {"mode": self.mode, "center": self.center.tolist(), "scale": self.scale.tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> Normalizer:
        center = np.asarray(data["center"], dtype=np.float32)
        scale = np.asarray(data["scale"], dtype=np.float32)
        if center.shape != scale.shape or center.ndim != 1 or not (scale > 0).all():
            raise ValueError("normaliser needs 1-D center and positive scale of equal length")
        if not (np.isfinite(center).all() and np.isfinite(scale).all()):
            raise ValueError("normaliser statistics are not finite (NaN or inf)")
        return cls(center, scale, data.get("mode", "minmax"))
