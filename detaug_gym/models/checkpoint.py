"""Flow-policy checkpoint folders: what is in them, how to write them safely and how to read them.

A checkpoint folder (``policies/<method>/<suite>/``) holds::

    model.pt            EMA weights of the network (state dict; the only file inference needs besides the two below)
    config.json         network architecture, plan layout, observation keys, the training config and summary
    normalization.json  plan / observation normalisers and the training labels (DetAug's sampling support)
    train_state.pt      (training only) raw weights, EMA, optimiser, scheduler, step: lets training resume;
                        not needed for inference and not meant for the zoo

Every file is written to a temporary name and renamed, so an interrupted save never leaves a torn file.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from detaug_gym.models.dataset import OBS_KEYS, PlanLayout
from detaug_gym.models.network import FlowNetwork, NetworkConfig
from detaug_gym.models.normalize import Normalizer

METHODS = ("base", "detaug", "demogen")
WEIGHTS, CONFIG, NORMALIZATION, TRAIN_STATE = "model.pt", "config.json", "normalization.json", "train_state.pt"
FORMAT_VERSION = 1


class CheckpointError(RuntimeError):
    """A checkpoint folder is missing or unreadable; the message names the command that makes it."""


def train_command(path: str | Path, method: str | None = None, data: str | None = None) -> str:
    """The command that (re)creates the checkpoint at ``path``."""
    path = Path(path)
    if method is None:
        method = next((part for part in reversed(path.parts) if part in METHODS), "|".join(METHODS))
    return f"python -m detaug_gym.train --method {method} --data {data or '<demos.hdf5>'} --out {path}"


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_json(path: Path, data: dict) -> None:
    _atomic_write(path, lambda p: p.write_text(json.dumps(data, indent=2) + "\n"))


def torch_save(path: Path, obj) -> None:
    _atomic_write(path, lambda p: torch.save(obj, p))


@dataclass
class LabelSupport:
    """The labels seen in training: ``bank`` (N, L) with the task id of each row, and per-dim bounds."""

    bank: np.ndarray
    task: np.ndarray

    @property
    def dim(self) -> int:
        return int(self.bank.shape[1]) if self.bank.ndim == 2 else 0

    @property
    def low(self) -> np.ndarray:
        return self.bank.min(0) if len(self.bank) else np.zeros(self.dim, np.float32)

    @property
    def high(self) -> np.ndarray:
        return self.bank.max(0) if len(self.bank) else np.zeros(self.dim, np.float32)

    def to_dict(self) -> dict:
        return {"bank": self.bank.tolist(), "task": self.task.tolist(), "low": self.low.tolist(),
                "high": self.high.tolist()}

    @classmethod
    def from_dict(cls, data: dict | None) -> LabelSupport:
        if not data or not data.get("bank"):
            return cls(np.zeros((0, 0), np.float32), np.zeros(0, np.int64))
        return cls(np.asarray(data["bank"], np.float32), np.asarray(data["task"], np.int64))


@dataclass
class Checkpoint:
    """A loaded checkpoint: the network in eval mode with its EMA weights, and everything around it."""

    path: Path
    method: str
    network: FlowNetwork
    layout: PlanLayout
    obs_keys: tuple[str, ...]
    normalizers: dict[str, Normalizer]
    labels: LabelSupport
    n_points: int = 0
    config: dict = field(default_factory=dict)
    digest: str = ""
    """sha256 of the weights file: policies whose networks have the same digest (and device) can share one
    batched network call (:mod:`detaug_gym.models.batching`)."""

    @property
    def action_steps(self) -> int | None:
        """The replan period N saved with the checkpoint (``config.json`` ``policy.action_steps``), or None."""
        policy = self.config.get("policy") or {}
        return policy.get("action_steps") if isinstance(policy, dict) else None

    @property
    def trained_on(self) -> dict:
        """``{"suite": ..., "env_ids": [...]}`` of the demos it was trained on (empty for older checkpoints)."""
        return dict(self.config.get("trained_on") or {})


def save_checkpoint(path: str | Path, *, method: str, network: FlowNetwork, ema_state: dict, layout: PlanLayout,
                    obs_keys: tuple[str, ...], normalizers: dict[str, Normalizer], labels: LabelSupport,
                    n_points: int = 0, action_steps: int | None = None, extra_config: dict | None = None) -> None:
    """Write ``model.pt`` (the EMA weights ``ema_state``), ``config.json`` and ``normalization.json``;
    ``action_steps`` is the policy's default replan period (:attr:`Checkpoint.action_steps`)."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    torch_save(path / WEIGHTS, ema_state)
    write_json(path / NORMALIZATION, {name: n.to_dict() for name, n in normalizers.items()}
               | {"labels": labels.to_dict()})
    write_json(path / CONFIG, {
        "format": FORMAT_VERSION, "method": method, "network": network.config.to_dict(),
        "layout": layout.to_dict(), "obs_keys": list(obs_keys), "n_points": n_points,
        "parameters": network.num_parameters(),
        **({"policy": {"action_steps": int(action_steps)}} if action_steps is not None else {}),
        **(extra_config or {}),
    })


def read_config(path: str | Path) -> dict:
    """``config.json`` of a checkpoint folder, or a :class:`CheckpointError` naming the train command."""
    path = Path(path)
    try:
        config = json.loads((path / CONFIG).read_text())
        if not isinstance(config, dict):
            raise ValueError(f"it holds a JSON {type(config).__name__}, not an object")
        return config
    except FileNotFoundError:
        raise CheckpointError(f"no flow-policy checkpoint at {path} ({CONFIG} missing). Make it with:\n  "
                              f"{train_command(path)}") from None
    except (OSError, ValueError) as err:
        raise CheckpointError(f"unreadable {path / CONFIG} ({err}). Remake it with:\n  "
                              f"{train_command(path)}") from None


def resolve_device(device: str | torch.device = "cpu") -> torch.device:
    """The torch device for ``device`` (``"auto"``: cuda when torch sees one, else cpu); a clear error when the
    asked one is not there."""
    if str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (dev.index or 0) >= count:
            build = f"a CUDA {torch.version.cuda} build" if torch.version.cuda else "a CPU-only build"
            raise ValueError(f"device {str(device)!r} asked, but torch {torch.__version__} ({build}) sees "
                             f"{count} CUDA device(s); use device=cpu" + (" or auto" if count == 0 else ""))
    elif dev.type != "cpu":
        raise ValueError(f"device must be cpu, cuda, cuda:N or auto, got {str(device)!r}")
    return dev


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> Checkpoint:
    """Load a checkpoint folder written by ``python -m detaug_gym.train``.

    Raises:
        CheckpointError: a file is missing, corrupt or does not match its config; the message gives the
            train command that (re)creates the folder.
    """
    path = Path(path)
    device = resolve_device(device)
    config = read_config(path)
    method = config.get("method")
    train = config.get("train") if isinstance(config.get("train"), dict) else {}
    command = train_command(path, method, train.get("data"))
    try:
        network = FlowNetwork(NetworkConfig.from_dict(config["network"]))
        weights = (path / WEIGHTS).read_bytes()
        state = torch.load(io.BytesIO(weights), map_location=device, weights_only=True)
        network.load_state_dict(state)
        norm = json.loads((path / NORMALIZATION).read_text())
        normalizers = {name: Normalizer.from_dict(norm[name]) for name in ("plan", "obs")}
        checkpoint = Checkpoint(
            path=path, method=method, network=network.to(device).eval(),
            layout=PlanLayout.from_dict(config["layout"]), obs_keys=tuple(config.get("obs_keys", OBS_KEYS)),
            normalizers=normalizers, labels=LabelSupport.from_dict(norm.get("labels")),
            n_points=int(config.get("n_points", 0)), config=config, digest=hashlib.sha256(weights).hexdigest())
    except FileNotFoundError as err:
        raise CheckpointError(f"incomplete checkpoint at {path}: {Path(err.filename or WEIGHTS).name} missing. "
                              f"Remake it with:\n  {command}") from None
    except Exception as err:  # noqa: BLE001  (any decoding failure means the same thing to the user)
        reason = (str(err).strip().splitlines() or [""])[0][:160]
        raise CheckpointError(f"corrupt checkpoint at {path} ({type(err).__name__}: {reason}). "
                              f"Remake it with:\n  {command}") from None
    problem = _mismatch(checkpoint)
    if problem:
        raise CheckpointError(f"{path}: {problem}. Remake it with:\n  {command}")
    return checkpoint


def _mismatch(checkpoint: Checkpoint) -> str | None:
    """What in a loaded checkpoint contradicts the rest (normalisers vs network and layout, keys, replan period)."""
    from detaug_gym.models.dataset import DERIVED_KEYS

    dit = checkpoint.network.config.dit
    if checkpoint.normalizers["plan"].dim != checkpoint.layout.plan_dim:
        return (f"{NORMALIZATION}: the plan normaliser has {checkpoint.normalizers['plan'].dim} dims, the plan layout "
                f"{checkpoint.layout.plan_dim}")
    if checkpoint.normalizers["obs"].dim != dit.obs_dim:
        return f"{NORMALIZATION}: the observation normaliser has {checkpoint.normalizers['obs'].dim} dims, the " \
               f"network reads {dit.obs_dim}"
    known = set(OBS_KEYS) | set(DERIVED_KEYS)
    unknown = [k for k in checkpoint.obs_keys if k not in known]
    if unknown:
        return f"{CONFIG}: unknown observation keys {unknown}; known: {', '.join(sorted(known))}"
    steps = checkpoint.action_steps
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= dit.horizon):
        return f"{CONFIG}: policy.action_steps must be an integer in [1, {dit.horizon}], got {steps!r}"
    if checkpoint.labels.dim not in (0, dit.label_dim) and len(checkpoint.labels.bank):
        return f"{NORMALIZATION}: the training labels have {checkpoint.labels.dim} dims, the network {dit.label_dim}"
    return None
