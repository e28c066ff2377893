"""Training windows for the flow policies, and the feature maps shared by training and inference.

**Plan** (what the model generates, ``D = 19`` per timestep by default)::

    s_t = [robot_joint_pos (7), gripper_qpos (2), eef_pos (3)]      a_t = env action (7)

The joint positions let a plan be checked for collisions by forward kinematics (DetAug's selection, CAPE's
guidance); the gripper opening and end-effector position make the chunk readable and give the network a
Cartesian view of the motion it commands in OSC deltas. The plan at time ``t`` is ``[s_t..s_{t+H-1},
a_t..a_{t+H-1}]``: its first state is the *current* state, which the sampler inpaints.

**Observation conditioning** (vector ``C``): robot joint positions and velocities, gripper qpos, eef pose,
object poses, object mask, task id and two derived relative positions: ``object_rel_pos`` (S, 3), each
tracked object's position minus the end effector's, and ``object_pair_rel_pos`` (S(S-1)/2, 3), object ``j``'s
position minus object ``i``'s for every pair ``i < j`` of tracked slots (zero where a mask is 0). The tracked
objects come in pick-place order (object, its target, ...), so the pairs include every carried object's offset
from where it goes. The network could subtract absolute positions itself, but grasping a bowl's rim or setting
it down on a plate needs ~1 cm precision and the relative vectors hand it over directly (see ``docs/models.md``
for the measured effect). Quaternions (xyzw) become the first two columns of their rotation
matrix: continuous and sign-free (a top-down gripper has ``w ~ 0``, where a canonical-sign rule would flip).
The obstacle keys are never part of it; only the ``demogen`` method reads ``obstacle_points``, through its
point-cloud encoder.

**Windows** start at every timestep of every demo with equal probability. A window running past the end
of its demo is padded with the final state and a *hold* action: zero arm delta (OSC keeps the pose) and
the final gripper command (the grip is kept, not released). So the model learns to stay put at the end.

**File format** (``data/demo_<i>``): ``actions`` (T, 7), ``obs/<key>`` (T, ...), optional ``label`` (L,)
(the DetAug label, zeros for original demos) and ``obstacle_points`` (P, 3). Labels of different lengths
(tasks with one or two grasps) are zero-padded to the longest.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from detaug_gym.actions import ACTION_DIM
from detaug_gym.data.dataset import Demo, load
from detaug_gym.models.normalize import Normalizer
from detaug_gym.rotations import quat_xyzw_to_mat

PLAN_STATE_KEYS = ("robot_joint_pos", "gripper_qpos", "eef_pos")
OBS_KEYS = ("robot_joint_pos", "robot_joint_vel", "gripper_qpos", "eef_pos", "eef_quat",
            "object_poses", "object_mask", "task_id", "object_rel_pos", "object_pair_rel_pos")
DERIVED_KEYS = {"object_rel_pos": ("object_poses", "eef_pos", "object_mask"),  # computed, not stored
                "object_pair_rel_pos": ("object_poses", "object_mask")}


# ---------------------------------------------------------------------------------------------- features
def quat_to_rot6d(quat: np.ndarray) -> np.ndarray:
    """xyzw quaternions (..., 4) -> first two rotation-matrix columns (..., 6); zeros stay finite."""
    rot = quat_xyzw_to_mat(quat)
    return np.concatenate([rot[..., :, 0], rot[..., :, 1]], axis=-1)


def source_keys(keys: tuple[str, ...]) -> tuple[str, ...]:
    """The stored observation keys that ``keys`` (which may name :data:`DERIVED_KEYS`) are computed from."""
    out: list[str] = []
    for key in keys:
        for name in DERIVED_KEYS.get(key, (key,)):
            if name not in out:
                out.append(name)
    return tuple(out)


def object_rel_pos(obs: Mapping[str, np.ndarray]) -> np.ndarray:
    """Tracked objects' positions relative to the end effector, (N, S, 3); masked slots are zero."""
    poses, eef = np.asarray(obs["object_poses"], np.float64), np.asarray(obs["eef_pos"], np.float64)
    mask = np.asarray(obs["object_mask"], np.float64)
    return (poses[..., :3] - eef[..., None, :]) * mask[..., None]


def object_pair_rel_pos(obs: Mapping[str, np.ndarray]) -> np.ndarray:
    """Object ``j``'s position minus object ``i``'s for every pair of tracked slots ``i < j`` (in
    ``np.triu_indices`` order), (N, S(S-1)/2, 3); a pair with a masked slot is zero."""
    poses, mask = np.asarray(obs["object_poses"], np.float64), np.asarray(obs["object_mask"], np.float64)
    i, j = np.triu_indices(poses.shape[-2], k=1)
    return (poses[..., j, :3] - poses[..., i, :3]) * (mask[..., i] * mask[..., j])[..., None]


DERIVED = {"object_rel_pos": object_rel_pos, "object_pair_rel_pos": object_pair_rel_pos}


def observation_vector(obs: Mapping[str, np.ndarray], keys: tuple[str, ...] = OBS_KEYS) -> np.ndarray:
    """Flatten observation ``keys`` with one leading batch dim, (N, ...) each, into (N, C) float32."""
    parts = []
    for key in keys:
        missing = [k for k in DERIVED_KEYS.get(key, (key,)) if k not in obs]
        if missing:
            raise KeyError(f"observation has no key {missing[0]!r}; the policy was trained on {list(keys)}")
        if key in DERIVED:
            parts.append(DERIVED[key](obs).reshape(len(obs[DERIVED_KEYS[key][0]]), -1))
            continue
        value = np.asarray(obs[key], dtype=np.float64)
        if key == "eef_quat":
            value = quat_to_rot6d(value)
        elif key == "object_poses":
            value = np.concatenate([value[..., :3], quat_to_rot6d(value[..., 3:7])], axis=-1)
        parts.append(value.reshape(value.shape[0], -1))
    return np.concatenate(parts, axis=-1).astype(np.float32)


@dataclass
class PlanLayout:
    """Which features a plan timestep holds: ``state_keys`` (with sizes) then the action."""

    state_keys: tuple[str, ...] = PLAN_STATE_KEYS
    state_sizes: tuple[int, ...] = (7, 2, 3)
    action_dim: int = ACTION_DIM

    @property
    def state_dim(self) -> int:
        return sum(self.state_sizes)

    @property
    def plan_dim(self) -> int:
        return self.state_dim + self.action_dim

    @property
    def action_slice(self) -> slice:
        return slice(self.state_dim, self.plan_dim)

    @property
    def state_slice(self) -> slice:
        return slice(0, self.state_dim)

    def key_slice(self, key: str) -> slice:
        """Slice of state key ``key`` (e.g. ``"robot_joint_pos"`` -> joints for FK) in a plan timestep."""
        start = 0
        for name, size in zip(self.state_keys, self.state_sizes):
            if name == key:
                return slice(start, start + size)
            start += size
        raise KeyError(f"plan state has no {key!r}; it holds {self.state_keys}")

    def state_vector(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        """Plan state from observation keys with one leading dim, (N, ...) -> (N, state_dim) float32."""
        parts = [np.asarray(obs[k], dtype=np.float32).reshape(len(obs[k]), -1) for k in self.state_keys]
        return np.concatenate(parts, axis=-1)

    def to_dict(self) -> dict:
        return {"state_keys": list(self.state_keys), "state_sizes": list(self.state_sizes),
                "action_dim": self.action_dim}

    @classmethod
    def from_dict(cls, data: dict) -> PlanLayout:
        return cls(tuple(data["state_keys"]), tuple(data["state_sizes"]), int(data["action_dim"]))


# ---------------------------------------------------------------------------------------------- reading
def read_demos(path: str | Path, obs_keys: tuple[str, ...] = OBS_KEYS) -> list[Demo]:
    """Read every ``data/demo_<i>`` of a demonstration HDF5 through :func:`detaug_gym.data.load` (which also
    maps LIBERO's own files), keeping what the policies need.

    Returns:
        :class:`detaug_gym.data.Demo` s with float32 ``actions`` (T, 7), only the stored observation keys that
        ``obs_keys`` are computed from, ``label`` (L,) and ``obstacle_points`` (P, 3) as float32 (or None);
        the simulator ``states`` are dropped (``(0, 0)``: training never reads them).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no demonstration file at {path}")
    raw = load(path).demos
    if not raw:
        raise ValueError(f"{path} holds no demos")
    demos = []
    stored = source_keys(obs_keys)
    for d in raw:
        missing = [k for k in stored if k not in d.obs]
        if missing:
            raise ValueError(f"{path}:data/{d.name} lacks obs keys {missing} (the policies read {list(stored)})")
        label = None if d.label is None else np.asarray(d.label, np.float32).reshape(-1)
        points = None if d.obstacle_points is None else np.asarray(d.obstacle_points, np.float32).reshape(-1, 3)
        demos.append(dataclasses.replace(d, actions=np.asarray(d.actions, np.float32), states=np.zeros((0, 0)),
                                         obs={k: np.asarray(d.obs[k]) for k in stored}, label=label,
                                         obstacle_points=points))
    return demos


# ---------------------------------------------------------------------------------------------- windows
@dataclass
class Batch:
    """A training batch, normalised. Shapes: plan (B, H, D), obs (B, C), label (B, L), points (B, P, 3)."""

    plan: torch.Tensor
    obs: torch.Tensor
    label: torch.Tensor | None = None
    points: torch.Tensor | None = None
    point_mask: torch.Tensor | None = None  # (B,) 1 where the demo has an obstacle cloud


def pad_window(states: np.ndarray, actions: np.ndarray, start: int, horizon: int) -> np.ndarray:
    """The raw plan window ``[s, a]`` (horizon, S + A) from ``start``, padded past the end with the final
    state and the hold action (zero arm delta, final gripper command). Reference for :class:`WindowDataset`."""
    hold = np.zeros(actions.shape[1], dtype=np.float32)
    hold[-1] = actions[-1, -1]
    real = np.concatenate([states[start:start + horizon], actions[start:start + horizon]], axis=1)
    pad = np.tile(np.concatenate([states[-1], hold]), (horizon - len(real), 1))
    return np.concatenate([real, pad]).astype(np.float32)


class WindowDataset:
    """All windows of a demonstration set, kept in memory as tensors and sampled by index.

    Args:
        demos: from :func:`read_demos`.
        horizon: H.
        layout: plan features.
        obs_keys: observation conditioning keys.
        use_labels: keep the per-demo labels (``detaug``).
        n_points: point-cloud size for ``demogen`` (0: no points). Clouds are resampled to this size once;
            demos without a cloud get a zero cloud and ``point_mask`` 0.
        normalizers: reuse these (fine-tuning) instead of fitting on the data.
        zero_label_weight: sampling weight of the windows of zero-label demos (the unaugmented ones) relative
            to the others (with ``use_labels``); 1 samples every window alike.
    """

    def __init__(self, demos: list[Demo], horizon: int, layout: PlanLayout | None = None,
                 obs_keys: tuple[str, ...] = OBS_KEYS, use_labels: bool = False, n_points: int = 0,
                 normalizers: dict[str, Normalizer] | None = None, seed: int = 0,
                 zero_label_weight: float = 1.0) -> None:
        self.layout = layout or PlanLayout()
        self.horizon, self.obs_keys = horizon, tuple(obs_keys)
        rows, obs, starts, demo_of_start = [], [], [], []
        offset = 0
        for i, demo in enumerate(demos):
            states = self.layout.state_vector(demo.obs)
            if demo.actions.shape != (len(demo), self.layout.action_dim) or len(states) != len(demo):
                raise ValueError(f"{demo.name}: actions {demo.actions.shape} and obs of {len(states)} steps")
            raw = pad_window(states, demo.actions, 0, len(demo) + horizon - 1)
            rows.append(raw)
            obs.append(observation_vector(demo.obs, self.obs_keys))
            starts.append(offset + np.arange(len(demo)))
            demo_of_start.append(np.full(len(demo), i))
            offset += len(raw)
        flat_plan = np.concatenate(rows)
        valid = np.concatenate([r[:len(o)] for r, o in zip(rows, obs)])  # unpadded rows fit the stats
        flat_obs = np.concatenate(obs)
        self.normalizers = normalizers or {"plan": Normalizer.fit(valid, "minmax"),
                                           "obs": Normalizer.fit(flat_obs, "meanstd")}
        self.plan_rows = torch.from_numpy(self.normalizers["plan"].normalize(flat_plan))
        self.obs = torch.from_numpy(self.normalizers["obs"].normalize(flat_obs))
        self.start_rows = torch.from_numpy(np.concatenate(starts))
        self.demo_of_start = torch.from_numpy(np.concatenate(demo_of_start))
        self.labels = self._labels(demos) if use_labels else None
        self.weights = self._weights(zero_label_weight)
        self.points, self.point_mask = self._points(demos, n_points, seed) if n_points else (None, None)
        self.num_demos = len(demos)
        self.demo_task = np.array([int(np.argmax(d.obs["task_id"][0])) if "task_id" in d.obs else 0
                                   for d in demos])

    @staticmethod
    def _labels(demos: list[Demo]) -> torch.Tensor:
        width = max((d.label.size for d in demos if d.label is not None), default=0)
        if width == 0:
            raise ValueError("use_labels=True but no demo has a 'label' (train the 'base' method instead)")
        labels = np.zeros((len(demos), width), dtype=np.float32)
        for i, d in enumerate(demos):
            if d.label is not None:
                labels[i, :d.label.size] = d.label
        return torch.from_numpy(labels)

    def _weights(self, zero_label_weight: float) -> torch.Tensor | None:
        """Per-window sampling weights (N,), or None for uniform sampling."""
        if zero_label_weight <= 0.0:
            raise ValueError(f"zero_label_weight must be > 0, got {zero_label_weight}")
        if zero_label_weight == 1.0:
            return None
        if self.labels is None:
            raise ValueError("zero_label_weight needs labelled demos (use_labels=True, the detaug method)")
        zero = (self.labels == 0).all(dim=1)[self.demo_of_start]
        return torch.where(zero, zero_label_weight, 1.0).double()

    @staticmethod
    def _points(demos: list[Demo], n_points: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        rng = np.random.default_rng(seed)
        clouds = np.zeros((len(demos), n_points, 3), dtype=np.float32)
        mask = np.zeros(len(demos), dtype=np.float32)
        for i, d in enumerate(demos):
            if d.obstacle_points is not None and len(d.obstacle_points):
                pts = d.obstacle_points.reshape(-1, 3)
                clouds[i] = pts[rng.choice(len(pts), n_points, replace=len(pts) < n_points)]
                mask[i] = 1.0
        return torch.from_numpy(clouds), torch.from_numpy(mask)

    def __len__(self) -> int:
        return len(self.start_rows)

    @property
    def obs_dim(self) -> int:
        return int(self.obs.shape[1])

    @property
    def label_dim(self) -> int:
        return 0 if self.labels is None else int(self.labels.shape[1])

    def label_bank(self) -> tuple[np.ndarray, np.ndarray]:
        """Distinct training labels (N, L) and the task id of each: the support DetAug samples from."""
        if self.labels is None:
            return np.zeros((0, 0), np.float32), np.zeros(0, np.int64)
        return self.labels.numpy(), self.demo_task.astype(np.int64)

    def window(self, index: torch.Tensor) -> Batch:
        """Windows for start indices ``index`` (B,) in ``[0, len(self))``."""
        rows = self.start_rows[index][:, None] + torch.arange(self.horizon)
        demo = self.demo_of_start[index]
        return Batch(
            plan=self.plan_rows[rows],
            obs=self.obs[index],
            label=None if self.labels is None else self.labels[demo],
            points=None if self.points is None else self.points[demo],
            point_mask=None if self.point_mask is None else self.point_mask[demo],
        )

    def sample(self, batch_size: int, generator: torch.Generator | None = None) -> Batch:
        """A batch of windows at random start positions: uniform, or by ``zero_label_weight``."""
        if self.weights is None:
            return self.window(torch.randint(len(self), (batch_size,), generator=generator))
        return self.window(torch.multinomial(self.weights, batch_size, replacement=True, generator=generator))
