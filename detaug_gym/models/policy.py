"""``FlowPolicy``: inference for a trained flow checkpoint (no training code here).

Chunking protocol (what the bench sees)::

    policy.reset(seed)   # clears the action queue, reseeds the sampling noise
    policy.act(obs)      # queue empty -> plan H steps from obs, queue the first `action_steps` actions;
                         # pop and return one action (7,) float32

So the policy replans every ``action_steps`` (N = 10) env steps; a plan covers ``horizon`` (H = 50) steps.
Actions are predicted normalised, unnormalised to env units (OSC_POSE delta in [-1, 1] + gripper),
clipped to [-1, 1], and the gripper is snapped to -1 (open) / +1 (close).

Methods built on the same model (DetAug selection, CAPE, guidance ablations) call :meth:`FlowPolicy.plan`
for batches of K plans and override :meth:`FlowPolicy.next_plan` to choose one.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections import deque
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch

from detaug_gym.actions import GRIPPER_CLOSE, GRIPPER_OPEN
from detaug_gym.models.batching import PlanBatcher, PlanRequest, run_requests
from detaug_gym.models.checkpoint import Checkpoint, load_checkpoint, resolve_device
from detaug_gym.models.dataset import observation_vector
from detaug_gym.models.flow import Guidance, Inpaint, remaining_steps
from detaug_gym.policies.options import FlowOptions

DEFAULT_ACTION_STEPS = 10  # the paper's replan period N, for checkpoints whose config.json names none


def zoo_dir(method: str, suite: str) -> Path:
    """``policies/<method>/<suite>/`` of the repository (or under ``$DETAUG_ZOO`` when set)."""
    root = Path(os.environ.get("DETAUG_ZOO", Path(__file__).resolve().parents[2] / "policies"))
    return root / method / suite


class FlowPolicy:
    """A flow-matching chunking policy.

    Args:
        checkpoint: a checkpoint folder or a loaded :class:`Checkpoint`.
        action_steps: N, actions executed from each plan before replanning (1..horizon); default the
            checkpoint's own (``config.json`` ``policy.action_steps``, written by ``train --action-steps``),
            else 10.
        flow_steps: Euler steps per plan.
        label_mode: label used by :meth:`act`: ``"zero"`` (the unaugmented demos' label), ``"null"`` (the
            null token: unconditional) or ``"auto"`` (zero for label models, nothing for ``base``).
        binarize_gripper: snap the gripper command to -1 / +1.
        seed: default seed for :meth:`reset` without one.
        device: where the network runs (``cpu``, ``cuda``, ``cuda:N``, ``auto``); plans come back on the CPU,
            and the noise is drawn on the CPU, so a seed gives the same noise on every device.
    """

    zoo_method: str | None = None  # the zoo folder ``policies/<zoo_method>/<suite>/`` a subclass loads by default

    @classmethod
    def checkpoint_dirs(cls, suite: str = "spatial", checkpoint: str | Path | None = None, **_) -> list[Path]:
        """The checkpoint folder(s) this policy loads for ``suite`` with these options, without loading them."""
        if checkpoint is not None:
            return [Path(checkpoint)]
        return [zoo_dir(cls.zoo_method, suite)] if cls.zoo_method else []

    def __init__(self, checkpoint: Checkpoint | str | Path, action_steps: int | None = None, flow_steps: int = 10,
                 label_mode: str = "auto", binarize_gripper: bool = True, noise_scale: float = 1.0,
                 seed: int | None = None, device: str = "cpu") -> None:
        options = FlowOptions(action_steps=action_steps, flow_steps=flow_steps, label_mode=label_mode,
                              binarize_gripper=binarize_gripper, noise_scale=noise_scale, seed=seed,
                              device=device)  # type and range checks
        self.device = resolve_device(options.device)
        self.checkpoint = checkpoint if isinstance(checkpoint, Checkpoint) else load_checkpoint(checkpoint)
        self.network = self.checkpoint.network.to(self.device)
        self.layout = self.checkpoint.layout
        self.horizon = self.network.config.dit.horizon
        action_steps = options.action_steps or self.checkpoint.action_steps or DEFAULT_ACTION_STEPS
        if not 1 <= action_steps <= self.horizon:
            raise ValueError(f"action_steps must lie in [1, {self.horizon}], got {action_steps}")
        self.action_steps, self.flow_steps = action_steps, options.flow_steps
        self.label_mode, self.binarize_gripper = options.label_mode, options.binarize_gripper
        self.noise_scale = options.noise_scale
        self._default_seed = options.seed
        self._queue: deque[np.ndarray] = deque()
        self._plan: np.ndarray | None = None
        self._plan_step = -1
        self._warned_suite = False
        self._batcher: PlanBatcher | None = None
        self.generator = torch.Generator()
        self.reset(options.seed)

    # ------------------------------------------------------------------ properties
    @property
    def label_dim(self) -> int:
        return self.network.config.dit.label_dim

    @property
    def labels(self):
        """Training label support (:class:`~detaug_gym.models.checkpoint.LabelSupport`)."""
        return self.checkpoint.labels

    # ------------------------------------------------------------------ protocol
    def reset(self, seed: int | None = None, context=None) -> None:
        """Clear the action queue and reseed the sampling noise; warns once when ``context`` (the episode's)
        names another suite than the checkpoint was trained on."""
        self._queue.clear()
        self._plan, self._plan_step = None, -1
        suite = self.checkpoint.trained_on.get("suite")
        if context is not None and suite and context.suite != suite and not self._warned_suite:
            warnings.warn(f"{self.checkpoint.path} was trained on {suite} demos and now runs in {context.env_id}; "
                          "its numbers there say little", stacklevel=2)
            self._warned_suite = True
        seed = self._default_seed if seed is None else seed
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(int(seed))

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Next env action (7,) float32; replans when the queue is empty."""
        if not self._queue:
            self._plan, self._plan_step = self.next_plan(obs), -1
            self._queue.extend(self.env_actions(self._plan)[: self.action_steps])
        self._plan_step += 1
        return self._queue.popleft()

    def belief(self, obs: Mapping[str, np.ndarray] | None = None) -> dict:
        """What the policy expects of the action :meth:`act` returned last (empty before the first): the
        plan's arm joints once that action is executed, ``planned_joint_pos`` (7,), and ``plan_age``, the
        actions executed from the plan so far. Subclasses add what their selection knew (DetAug: the chosen
        plan's predicted cost) and, given ``obs`` (the observation that action led to), how their own model
        judges the state reached. The bench reads it at the first collision (``EpisodeRecord.collision_cause``)."""
        if self._plan is None:
            return {}
        row = min(self._plan_step + 1, len(self._plan) - 1)
        joints = self._plan[row, self.layout.key_slice("robot_joint_pos")]
        return {"planned_joint_pos": [float(v) for v in joints], "plan_age": self._plan_step + 1}

    def next_plan(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """The plan (H, D) to execute from ``obs``; subclasses override this to select among candidates."""
        mode = self.label_mode
        if mode == "auto":
            mode = "zero" if self.label_dim else "null"
        labels = np.zeros((1, self.label_dim), np.float32) if mode == "zero" and self.label_dim else None
        return self.plan(obs, labels, num_samples=1)[0].numpy()

    # ------------------------------------------------------------------ planning
    def env_actions(self, plan: np.ndarray | torch.Tensor) -> np.ndarray:
        """Env actions (..., H, 7) float32 of plans in physical units: clipped, gripper snapped."""
        actions = np.asarray(plan[..., self.layout.action_slice], dtype=np.float32).clip(-1.0, 1.0)
        if self.binarize_gripper:
            actions[..., -1] = np.where(actions[..., -1] >= 0.0, GRIPPER_CLOSE, GRIPPER_OPEN)
        return actions

    def plan(self, obs: Mapping[str, np.ndarray], labels: np.ndarray | torch.Tensor | None = None, *,
             num_samples: int | None = None, guidance: Guidance | None = None,
             init_plan: np.ndarray | torch.Tensor | None = None, t_start: float = 0.0, steps: int | None = None,
             generator: torch.Generator | None = None) -> torch.Tensor:
        """Sample K plans in one batched call.

        Args:
            obs: one env observation (keys unbatched) or a batch (leading dim B = K).
            labels: (K, L) augmentation labels; ``None`` uses the null token (or nothing for ``base``).
            num_samples: K when ``labels`` is None (default 1 or the obs batch size).
            guidance: gradient guidance whose ``cost`` takes *physical-unit* plans (K, H, D); the gradient
                step is taken in normalised coordinates.
            init_plan: (K, H, D) physical plans to re-noise to ``t_start`` and denoise again (CAPE); see
                :func:`shift_plan`. Without it sampling starts from pure noise at ``t_start = 0``.
            steps: Euler steps; default ``flow_steps`` scaled to the remaining flow time.
            generator: noise source; default the policy's (seeded by :meth:`reset`).
        Returns:
            plans (K, H, D) float32 in physical units; ``plan[:, 0, state]`` is the current state.
        """
        net, norm, dev = self.network, self.checkpoint.normalizers, self.device
        batch = _batched(obs)
        k = _count(batch, labels, num_samples)
        obs_cond = torch.from_numpy(norm["obs"].normalize(self._observation_features(batch)))
        state = torch.from_numpy(self.layout.state_vector(batch))
        obs_cond, state = obs_cond.to(dev).expand(k, -1), state.expand(k, -1)
        label = self._label_tensor(labels, k)
        label = None if label is None else label.to(dev)
        points, point_mask = self._points(batch, k)
        shape = (k, self.horizon, self.layout.plan_dim)
        known = torch.zeros(shape, dtype=torch.bool)
        known[:, 0, self.layout.state_slice] = True
        first = torch.cat([state, torch.zeros(k, self.layout.action_dim)], dim=-1)
        inpaint = Inpaint(known.to(dev), norm["plan"].normalize(first)[:, None].expand(shape).to(dev))
        x_start = None if init_plan is None else norm["plan"].normalize(torch.as_tensor(init_plan).float()).to(dev)
        if guidance is not None:  # the cost runs on the CPU, its gradient flows back to the device
            user_cost = guidance.cost
            guidance = dataclasses.replace(guidance,
                                           cost=lambda x, t: user_cost(norm["plan"].unnormalize(x.cpu()), t))
        with torch.no_grad():
            extra = net.extra(*(None if p is None else p.to(dev) for p in (points, point_mask)))
        steps = steps or (self.flow_steps if init_plan is None else remaining_steps(self.flow_steps, t_start))
        noise = (self.noise_scale * torch.randn(shape, generator=generator or self.generator)).to(dev)
        weights = (self.checkpoint.digest or id(net), str(dev))
        request = PlanRequest(net, weights, obs_cond, label, extra, inpaint, noise, x_start, t_start, steps, guidance)
        x = run_requests([request])[0] if self._batcher is None else self._batcher.submit(request)
        return norm["plan"].unnormalize(x.cpu())

    def share_planner(self, batcher: PlanBatcher | None) -> None:
        """Plan through ``batcher`` (None: alone): the bench's vector rollout gives the policies of its envs one
        :class:`~detaug_gym.models.batching.PlanBatcher`, so those that replan at the same step share one
        network call (:func:`detaug_gym.policies.act_batch`)."""
        self._batcher = batcher

    def _label_tensor(self, labels, k: int) -> torch.Tensor | None:
        if labels is None:
            return None
        if not self.label_dim:
            raise ValueError(f"{self.checkpoint.method!r} policy has no label input; pass labels=None")
        label = torch.as_tensor(np.asarray(labels, np.float32)).reshape(-1, self.label_dim)
        if len(label) != k:
            raise ValueError(f"got {len(label)} labels for {k} samples")
        return label

    def _observation_features(self, batch: Mapping[str, np.ndarray]) -> np.ndarray:
        """(N, C) conditioning features of a batched observation; ``ValueError`` when C is not the checkpoint's
        (an observation from another env than the one it was trained on), naming each key's size."""
        keys = self.checkpoint.obs_keys
        features = observation_vector(batch, keys)
        trained = self.checkpoint.normalizers["obs"].dim
        if features.shape[-1] != trained:
            sizes = ", ".join(f"{k} {observation_vector(batch, (k,)).shape[-1]}" for k in keys)
            raise ValueError(f"the observation gives {features.shape[-1]} conditioning features ({sizes}) but "
                             f"{self.checkpoint.path} was trained on {trained}: its env's observation differs "
                             "from the training env's")
        return features

    def _points(self, batch: dict, k: int) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        if self.network.point_encoder is None:
            return None, None
        if "obstacle_points" not in batch:
            raise KeyError("the demogen policy reads 'obstacle_points' (and 'obstacle_mask') from the observation")
        points = torch.as_tensor(np.asarray(batch["obstacle_points"], np.float32)).expand(k, -1, -1)
        mask = np.asarray(batch.get("obstacle_mask", np.ones((len(batch["obstacle_points"]), 1))), np.float32)
        return points, torch.as_tensor(mask).reshape(len(mask), -1)[:, :1].expand(k, 1)


def shift_plan(plan: np.ndarray | torch.Tensor, executed: int, action_dim: int = 7) -> torch.Tensor:
    """Drop the first ``executed`` steps of plans (K, H, D) and pad the end like the training windows (the
    final state, zero arm delta, the final gripper command): CAPE's unexecuted remainder, ready to re-noise."""
    plan = torch.as_tensor(plan)
    tail = plan[:, -1:].clone()
    tail[..., -action_dim:-1] = 0.0
    return torch.cat([plan[:, executed:], tail.expand(-1, executed, -1)], dim=1)


def _batched(obs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Add a leading batch dim to a single env observation (detected on ``robot_joint_pos``)."""
    single = np.ndim(obs["robot_joint_pos"]) == 1
    return {key: np.asarray(value)[None] if single else np.asarray(value) for key, value in obs.items()}


def _count(batch: dict, labels, num_samples: int | None) -> int:
    b = len(batch["robot_joint_pos"])
    if labels is not None and num_samples not in (None, len(labels)):
        raise ValueError(f"got {len(labels)} labels for num_samples={num_samples}")
    k = len(labels) if labels is not None else (num_samples or b)
    if b not in (1, k):
        raise ValueError(f"observation batch of {b} does not match {k} samples")
    return k
