"""Train a flow-matching DiT policy on demonstrations (CPU).

Commands (one per method; rerunning the same command resumes an interrupted run)::

    python -m detaug_gym.train --method base    --data data/spatial.hdf5         --out policies/base/spatial
    python -m detaug_gym.train --method detaug  --data data/spatial_detaug.hdf5  --out policies/detaug/spatial
    python -m detaug_gym.train --method demogen --data data/spatial_demogen.hdf5 --out policies/demogen/spatial
    # graft the label onto the trained base policy and train only the adapter (paper, "Adapting ...")
    python -m detaug_gym.train --method detaug --data data/spatial_detaug.hdf5 \\
        --out policies/detaug-adapter/spatial --init-from policies/base/spatial --adapter-only
    python -m detaug_gym.train --help       # every option with its meaning

``base`` learns the unaugmented demos without a label (the frozen prior of CAPE and AEGIS); ``detaug`` learns
the augmented demos with their labels, dropped to the null token with probability ``label_dropout``;
``demogen`` encodes each demo's obstacle cloud with a DP3-style encoder added to the AdaLN conditioning.

The output folder gets ``model.pt`` (EMA weights), ``config.json``, ``normalization.json`` (what inference
needs, see :mod:`detaug_gym.models.checkpoint`), plus ``train_state.pt`` (resume) and ``train_log.csv``.
Load the result with ``detaug_gym.policies.load(out)`` (the policy of its method).
"""

from __future__ import annotations

import csv
import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from detaug_gym.config import parse_config
from detaug_gym.data.dataset import DatasetError, read_env_args
from detaug_gym.envs.suites import suite_of_env
from detaug_gym.models.checkpoint import (
    METHODS,
    TRAIN_STATE,
    LabelSupport,
    load_checkpoint,
    resolve_device,
    save_checkpoint,
    torch_save,
)
from detaug_gym.models.dataset import OBS_KEYS, PlanLayout, WindowDataset, read_demos
from detaug_gym.models.dit import DiTConfig
from detaug_gym.models.flow import Inpaint, flow_matching_loss
from detaug_gym.models.network import FlowNetwork, NetworkConfig

# Fields that may change when resuming with the same command (the rest must match the saved run).
RESUMABLE_CHANGES = ("steps", "checkpoint_every", "snapshot_every", "threads", "progress", "log_every", "action_steps",
                     "device", "compile")


@dataclass
class TrainConfig:
    method: str = "base"
    """base (no label, unaugmented data) | detaug (labels + null token) | demogen (obstacle point cloud)."""
    data: str = ""
    """Demonstration HDF5 (data/demo_<i>/{actions, obs/...}, plus label or obstacle_points); several files,
    comma-separated, are pooled (a demo without a label gets the zero label)."""
    out: str = ""
    """Output folder, e.g. policies/<method>/<suite>/."""
    steps: int = 9_000
    """Optimiser steps in total (a resumed run continues up to this number). 9000 take ~28 min on one core."""
    batch_size: int = 128
    """Windows per step."""
    lr: float = 5e-4
    """Peak AdamW learning rate."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    warmup_steps: int = 500
    """Linear warmup steps before the cosine decay to zero."""
    grad_clip: float = 1.0
    """Global gradient-norm clip."""
    ema_decay: float = 0.999
    """EMA decay of the saved weights (ramped up over the first steps)."""
    label_dropout: float = 0.15
    """detaug: probability of replacing a label by the null token."""
    zero_label_weight: float = 1.0
    """detaug: sampling weight of windows from zero-label (unaugmented) demos relative to augmented ones;
    above 1 spends more of training on the z = 0 behaviour the clean demos show."""
    horizon: int = 50
    """H: timesteps per plan."""
    action_steps: int = 10
    """N: actions the trained policy executes from each plan before it replans. Inference only: stored in
    config.json's "policy" section as the checkpoint's default (a load can override it)."""
    steps_per_token: int = 5
    """Timesteps packed into one transformer token (divides horizon)."""
    d_model: int = 128
    """Transformer width."""
    layers: int = 4
    """AdaLN-Zero blocks."""
    heads: int = 4
    """Attention heads."""
    obs_tokens: int = 2
    """Observation prefix tokens."""
    n_points: int = 256
    """demogen: points per obstacle cloud."""
    label_tokens: bool = False
    """detaug: also add the label to the observation tokens (:attr:`DiTConfig.label_tokens`; off: the paper's
    AdaLN-only injection)."""
    init_from: str = ""
    """Checkpoint folder whose weights (and normalisers) initialise the network: fine-tuning."""
    adapter_only: bool = False
    """Train only the adapter (label encoder, null token, AdaLN modulation, point encoder); needs init_from."""
    checkpoint_every: int = 1000
    """Steps between checkpoints (also written at the end and on Ctrl-C)."""
    snapshot_every: int = 0
    """Steps between snapshots of the EMA weights, each a loadable checkpoint folder <out>/snapshots/step_<N>/ that
    a resumed run keeps (0: none); for learning curves (python -m detaug_gym.finetune)."""
    log_every: int = 50
    """Steps between rows of train_log.csv."""
    seed: int = 0
    """Seed of initialisation and batch sampling."""
    threads: int = 1
    """torch CPU threads. One is faster than two whenever anything else runs on this 2-core machine
    (see docs/models.md); train two policies side by side instead."""
    compile: bool = False
    """Run the network's forward and backward through ``torch.compile`` (inductor's generated C++ kernels; about
    40 s once at the start): a training step 1.4x faster on this CPU (docs/models.md). The same computation; the
    float rounding differs from eager mode's, so a run is reproducible with the same setting, not across it."""
    device: str = "cpu"
    """Torch device: cpu, cuda, cuda:N or auto (cuda when torch sees one). Batches and noise are drawn on the CPU
    with the run's seed and moved there; the checkpoint is written with CPU tensors (the format is the same)."""
    progress: bool = True
    """Show a progress bar."""
    restart: bool = False
    """Ignore an existing train_state.pt in --out and start over."""


# ---------------------------------------------------------------------------------------------- CLI
def parse_args(argv: list[str] | None = None) -> TrainConfig:
    """``TrainConfig`` from the command line: one ``--flag`` per field, help from the field docstrings."""
    return parse_config(TrainConfig, argv, prog="python -m detaug_gym.train", description=__doc__,
                        choices={"method": METHODS})


def check_config(cfg: TrainConfig) -> None:
    """Fail before any work with a message that says what to pass."""
    if not cfg.data:
        raise SystemExit("error: --data is required: the demonstrations HDF5 to learn from "
                         "(data/demo_<i>/{actions, obs/...}), made by the collection or augmentation commands")
    for path in data_files(cfg):
        if not Path(path).is_file():
            raise SystemExit(f"error: --data {path}: no such file")
    if not cfg.out:
        raise SystemExit(f"error: --out is required, e.g. --out policies/{cfg.method}/<suite>")
    if cfg.adapter_only and not cfg.init_from:
        raise SystemExit("error: --adapter-only fine-tunes a trained policy: pass --init-from <checkpoint folder>")
    if cfg.steps < 1 or cfg.batch_size < 1 or not 0.0 <= cfg.label_dropout < 1.0:
        raise SystemExit("error: need steps >= 1, batch_size >= 1 and 0 <= label_dropout < 1")
    if cfg.zero_label_weight <= 0.0 or (cfg.zero_label_weight != 1.0 and cfg.method != "detaug"):
        raise SystemExit(f"error: --zero-label-weight must be > 0 and applies to --method detaug only, got "
                         f"{cfg.zero_label_weight} with --method {cfg.method}")
    if cfg.label_tokens and cfg.method != "detaug":
        raise SystemExit(f"error: --label-tokens applies to --method detaug only, got --method {cfg.method}")
    if cfg.snapshot_every < 0:
        raise SystemExit(f"error: --snapshot-every must be >= 0 (0: no snapshots), got {cfg.snapshot_every}")
    if not 1 <= cfg.action_steps <= cfg.horizon:
        raise SystemExit(f"error: --action-steps must lie in [1, horizon = {cfg.horizon}], got {cfg.action_steps}")
    try:
        resolve_device(cfg.device)
    except (ValueError, RuntimeError) as err:
        raise SystemExit(f"error: --device: {err}") from None


# ---------------------------------------------------------------------------------------------- pieces
class EMA:
    """Exponential moving average of a model's state; the decay ramps as min(decay, (1 + n) / (10 + n))
    so short runs and early checkpoints are not dominated by the random initialisation."""

    def __init__(self, model: torch.nn.Module, decay: float) -> None:
        self.decay, self.updates = decay, 0
        self.state = {k: v.detach().clone() for k, v in model.state_dict().items()}

    @torch.no_grad()
    def update(self, model: torch.nn.Module) -> None:
        self.updates += 1
        decay = min(self.decay, (1 + self.updates) / (10 + self.updates))
        for key, value in model.state_dict().items():
            if value.dtype.is_floating_point:
                self.state[key].lerp_(value, 1.0 - decay)
            else:
                self.state[key].copy_(value)


def lr_factor(step: int, warmup: int, total: int) -> float:
    """Linear warmup to 1, then cosine decay to 0 at ``total``."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return 0.5 * (1.0 + math.cos(math.pi * progress))


def build_network(cfg: TrainConfig, data: WindowDataset, init=None) -> FlowNetwork:
    """The network for ``cfg.method``; with ``init`` (a loaded checkpoint) its architecture and weights."""
    arch = init.network.config.dit if init is not None else None
    dit = DiTConfig(
        plan_dim=data.layout.plan_dim, obs_dim=data.obs_dim, horizon=cfg.horizon,
        steps_per_token=arch.steps_per_token if arch else cfg.steps_per_token,
        d_model=arch.d_model if arch else cfg.d_model, n_layers=arch.n_layers if arch else cfg.layers,
        n_heads=arch.n_heads if arch else cfg.heads, obs_tokens=arch.obs_tokens if arch else cfg.obs_tokens,
        label_dim=data.label_dim, extra_dim=64 if cfg.method == "demogen" else 0,
        label_tokens=(cfg.label_tokens or bool(arch and arch.label_tokens)) and data.label_dim > 0)
    network = FlowNetwork(NetworkConfig(dit, point_cloud=cfg.method == "demogen"))
    if init is not None:
        missing, unexpected = network.load_state_dict(init.network.state_dict(), strict=False)
        if unexpected:
            raise SystemExit(f"error: --init-from {cfg.init_from} has weights this {cfg.method} network "
                             f"lacks: {unexpected[:5]}")
        new_parts = sorted({".".join(k.split(".")[:2]) for k in missing})
        print(f"initialised from {cfg.init_from}; new parts (zero-initialised outputs): {new_parts}")
    return network


def data_files(cfg: TrainConfig) -> list[str]:
    """The demonstration files named by ``--data`` (comma-separated)."""
    return [part.strip() for part in cfg.data.split(",") if part.strip()]


def load_data(cfg: TrainConfig, init=None) -> WindowDataset:
    """The training windows of ``--data``, observed through ``init``'s keys when fine-tuning (the network
    reads what it was trained on), else :data:`OBS_KEYS`."""
    keys = init.obs_keys if init is not None else OBS_KEYS
    demos = []
    for path in data_files(cfg):
        try:
            loaded = read_demos(path, keys)
        except (ValueError, OSError, DatasetError) as err:
            raise SystemExit(f"error: --data {path}: {err}") from None
        for demo in loaded:
            bad = [k for k, v in {"actions": demo.actions, **demo.obs}.items() if not np.isfinite(v).all()]
            if bad:
                raise SystemExit(f"error: --data {path}: data/{demo.name} has non-finite values in {', '.join(bad)}; "
                                 "drop or re-collect that demo")
        demos += loaded
    return WindowDataset(demos, cfg.horizon, PlanLayout(), keys, use_labels=cfg.method == "detaug",
                         n_points=cfg.n_points if cfg.method == "demogen" else 0,
                         normalizers=init.normalizers if init is not None else None, seed=cfg.seed,
                         zero_label_weight=cfg.zero_label_weight)


def trained_on(cfg: TrainConfig) -> dict:
    """The suite and env ids of the ``--data`` files (recorded in the checkpoint; empty when they name none)."""
    ids = sorted({env_id for path in data_files(cfg) if (env_id := read_env_args(path).get("env_name"))})
    try:
        suites = sorted({suite_of_env(env_id)[0].name for env_id in ids})
    except ValueError:
        return {"env_ids": ids}
    return {"suite": suites[0], "env_ids": ids} if len(suites) == 1 else {"env_ids": ids}


def resume_state(cfg: TrainConfig) -> dict | None:
    """The saved training state in ``cfg.out`` (None to start fresh); refuses a different run's folder."""
    path = Path(cfg.out) / TRAIN_STATE
    if cfg.restart or not path.is_file():
        return None
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # noqa: BLE001
        raise SystemExit(f"error: cannot read {path} ({err}); rerun with --restart to start over") from None
    saved = state["config"]
    changed = {k: (saved[k], v) for k, v in dataclasses.asdict(cfg).items()
               if k not in RESUMABLE_CHANGES and k != "restart" and saved.get(k) != v}
    if changed:
        raise SystemExit(f"error: {cfg.out} holds a different run (saved vs now: {changed}); "
                         "use the same options to resume, another --out, or --restart")
    return state


# ---------------------------------------------------------------------------------------------- training
@dataclass
class Run:
    """Everything a training run holds, so that it can be saved and resumed as one."""

    cfg: TrainConfig
    data: WindowDataset
    network: FlowNetwork
    optimizer: torch.optim.Optimizer
    schedule: torch.optim.lr_scheduler.LambdaLR
    ema: EMA
    generator: torch.Generator
    step: int = 0
    elapsed: float = 0.0
    losses: list = dataclasses.field(default_factory=list)

    @classmethod
    def start(cls, cfg: TrainConfig) -> Run:
        """Build data, network and optimiser for ``cfg``; resume from ``cfg.out`` when it holds this run."""
        init = load_checkpoint(cfg.init_from) if cfg.init_from else None
        data = load_data(cfg, init)
        network = build_network(cfg, data, init).to(resolve_device(cfg.device))
        trainable = network.adapter_parameters() if cfg.adapter_only else list(network.parameters())
        trainable_ids = {id(p) for p in trainable}
        for p in network.parameters():
            p.requires_grad_(id(p) in trainable_ids)
        optimizer = torch.optim.AdamW(trainable, lr=cfg.lr, weight_decay=cfg.weight_decay)
        schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: lr_factor(s, cfg.warmup_steps, cfg.steps))
        run = cls(cfg, data, network, optimizer, schedule, EMA(network, cfg.ema_decay),
                  torch.Generator().manual_seed(cfg.seed))
        state = resume_state(cfg)
        if state is not None:
            run.restore(state)
            print(f"resuming {cfg.out} at step {run.step}/{cfg.steps}")
        print(f"{cfg.method}: {len(data)} windows from {data.num_demos} demos, "
              f"{network.num_parameters() / 1e6:.2f}M parameters ({sum(p.numel() for p in trainable) / 1e6:.2f}M "
              f"trained), label dim {data.label_dim}")
        return run

    def restore(self, state: dict) -> None:
        self.network.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])  # moves the moments to the parameters' device
        self.schedule.load_state_dict(state["schedule"])
        device = next(self.network.parameters()).device
        self.ema.state = {k: v.to(device) for k, v in state["ema"].items()}
        self.ema.updates = state["ema_updates"]
        self.generator.set_state(state["generator"])
        self.step, self.elapsed, self.losses = state["step"], state["elapsed"], state["recent_losses"]

    def save(self, final: bool = False) -> dict:
        """Write the checkpoint folder (EMA weights) and the resume state; return the summary."""
        cfg, out = self.cfg, Path(self.cfg.out)
        summary, ema = self.write_weights(out, final)
        torch_save(out / TRAIN_STATE, {
            "config": dataclasses.asdict(cfg), "model": _cpu(self.network.state_dict()),
            "optimizer": _cpu(self.optimizer.state_dict()), "schedule": self.schedule.state_dict(),
            "ema": ema, "ema_updates": self.ema.updates, "generator": self.generator.get_state(),
            "step": self.step, "elapsed": self.elapsed, "recent_losses": self.losses[-100:]})
        return summary


    def write_weights(self, folder: Path, final: bool = False) -> tuple[dict, dict]:
        """Write the EMA weights as a checkpoint folder (no resume state); return its summary and the weights."""
        cfg = self.cfg
        summary = {"steps": self.step, "final_loss": float(np.mean(self.losses[-100:])) if self.losses else None,
                   "wall_time_s": round(self.elapsed, 1), "step_time_s": round(self.elapsed / max(1, self.step), 4),
                   "parameters": self.network.num_parameters(), "finished": final}
        ema = {k: v.cpu() for k, v in self.ema.state.items()}
        save_checkpoint(folder, method=cfg.method, network=self.network, ema_state=ema,
                        layout=self.data.layout, obs_keys=self.data.obs_keys, normalizers=self.data.normalizers,
                        labels=LabelSupport(*self.data.label_bank()),
                        n_points=cfg.n_points if cfg.method == "demogen" else 0, action_steps=cfg.action_steps,
                        extra_config={"train": dataclasses.asdict(cfg), "summary": summary,
                                      "trained_on": trained_on(cfg)})
        return summary, ema


def snapshot_dir(out: str | Path, step: int) -> Path:
    """The snapshot folder of ``step`` in a run's ``out`` (``--snapshot-every``)."""
    return Path(out) / "snapshots" / f"step_{step:06d}"


def _cpu(tree):
    """A state dict (nested dicts / lists of tensors) with every tensor on the CPU."""
    if isinstance(tree, torch.Tensor):
        return tree.cpu()
    if isinstance(tree, dict):
        return {k: _cpu(v) for k, v in tree.items()}
    if isinstance(tree, list | tuple):
        return type(tree)(_cpu(v) for v in tree)
    return tree


def train(cfg: TrainConfig) -> dict:
    """Train (or resume) and return a summary: steps, final loss, wall time, step time, parameters."""
    check_config(cfg)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    run = Run.start(cfg)
    forward = torch.compile(run.network) if cfg.compile else run.network  # shares run.network's parameters
    known = torch.zeros(1, cfg.horizon, run.data.layout.plan_dim, dtype=torch.bool)
    known[:, 0, run.data.layout.state_slice] = True  # the current state is inpainted, never predicted
    known = known.to(next(run.network.parameters()).device)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    log = open(out / "train_log.csv", "a", newline="")  # noqa: SIM115  (closed in finally)
    writer = csv.writer(log)
    if log.tell() == 0:
        writer.writerow(["step", "loss", "lr", "elapsed_s"])
    bar = tqdm(total=cfg.steps, initial=run.step, disable=not cfg.progress, desc=f"train {cfg.method}", unit="step")
    try:
        while run.step < cfg.steps:
            tic = time.perf_counter()
            run.losses.append(train_step(forward, run.data, run.optimizer, cfg, known, run.generator))
            run.schedule.step()
            run.ema.update(run.network)
            run.elapsed += time.perf_counter() - tic
            run.step += 1
            bar.update()
            if run.step % cfg.log_every == 0 or run.step == cfg.steps:
                mean, lr = float(np.mean(run.losses[-cfg.log_every:])), run.schedule.get_last_lr()[0]
                bar.set_postfix(loss=f"{mean:.4f}", lr=f"{lr:.1e}")
                writer.writerow([run.step, f"{mean:.6f}", f"{lr:.3e}", f"{run.elapsed:.1f}"])
                log.flush()
            if cfg.snapshot_every and run.step % cfg.snapshot_every == 0:
                run.write_weights(snapshot_dir(cfg.out, run.step))
            if run.step % cfg.checkpoint_every == 0 and run.step < cfg.steps:
                run.save()
    except KeyboardInterrupt:
        bar.close()
        run.save()
        raise SystemExit(f"interrupted at step {run.step}; checkpoint saved. Rerun the same command to resume.") \
            from None
    finally:
        bar.close()
        log.close()
    summary = run.save(final=True)
    print(f"done: {summary}")
    return summary


def train_step(network: torch.nn.Module, data: WindowDataset, optimizer: torch.optim.Optimizer, cfg: TrainConfig,
               known: torch.Tensor, generator: torch.Generator) -> float:
    """One optimiser step on a fresh batch; returns the loss."""
    device = known.device
    batch = data.sample(cfg.batch_size, generator)
    drop = None
    if batch.label is not None and cfg.label_dropout > 0:
        drop = (torch.rand(cfg.batch_size, generator=generator) < cfg.label_dropout).to(device)
    obs, label, points, point_mask, plan = (None if x is None else x.to(device) for x in
                                            (batch.obs, batch.label, batch.points, batch.point_mask, batch.plan))

    def velocity(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return network(x, t, obs, label, points, point_mask, drop)

    loss = flow_matching_loss(velocity, plan, Inpaint(known, plan), generator)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    params = [p for group in optimizer.param_groups for p in group["params"]]
    torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
    optimizer.step()
    return loss.item()


def main(argv: list[str] | None = None) -> None:
    train(parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
