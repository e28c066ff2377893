"""Demonstration datasets in LIBERO's / robomimic's HDF5 layout: load, write (append + resume), replay.

Layout (see ``docs/data.md``)::

    data/                       attrs: env_args (JSON: env_name, env_version, type, env_kwargs), total
      demo_<i>/                 attrs: num_samples, env_id, task, task_key, init_state, seed, controller
        actions       (T, 7)    float32, the env's action
        states        (T, S)    float64, flattened simulator state before each action
        obs/<key>     (T, ...)  float32, every non-obstacle observation key
        gripper_command (T,)    float32
        rewards, dones (T,)
        label         (L,)      float32, optional (augmented demos)
        obstacle_points (P, 3)  float32, optional (DemoGen demos)
        executed_actions (T, 7) float32, optional (demos collected with ``--action-noise``: what was sent to
                                the env; ``actions`` then holds the expert's clean commands, the targets)

LIBERO's own demo files (``obs/joint_states``, ``obs/gripper_states``, ``obs/ee_pos``, ``obs/ee_ori``, ...)
load through the same :func:`load`; their keys are mapped to ours and images are skipped.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from detaug_gym.rollout import Hook, Step, rollout

OBSTACLE_PREFIX = "obstacle_"
DERIVED_OBS = ("object_points",)  # rebuilt from the object poses and the scene: not worth storing per step


def is_recorded(key: str) -> bool:
    """Whether a dataset stores observation ``key``: not the obstacle's (demos are collected in free space)
    and not :data:`DERIVED_OBS`."""
    return not key.startswith(OBSTACLE_PREFIX) and key not in DERIVED_OBS

# LIBERO demo observation keys -> ours. Image keys are skipped.
LIBERO_OBS_KEYS = {
    "joint_states": "robot_joint_pos",
    "gripper_states": "gripper_qpos",
    "ee_pos": "eef_pos",
    "ee_ori": "eef_ori",  # LIBERO stores axis-angle (3,), not our quaternion
    "ee_states": "eef_state",
}
IMAGE_HINTS = ("image", "rgb", "depth")


class DatasetError(RuntimeError):
    """A dataset file is missing, unreadable or not in the expected layout (the message names the file)."""


def _h5py():
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - h5py is a declared dependency
        raise ImportError("reading and writing datasets needs h5py: pip install h5py") from exc
    return h5py


@dataclass
class Demo:
    """One demonstration.

    Attributes:
        actions: ``(T, 7)`` float32.
        states: ``(T, S)`` float64 simulator states before each action (``(0, 0)`` if the file has none).
        obs: observation arrays keyed like the env's observation, each ``(T, ...)``.
        gripper_command: ``(T,)`` float32 (taken from ``actions[:, -1]`` when the file has none).
        attrs: the demo group's attributes (env_id, task, init_state, seed, ...), JSON strings decoded.
        label: ``(L,)`` float32 or ``None``.
        obstacle_points: ``(P, 3)`` float32 or ``None``.
        executed_actions: ``(T, 7)`` float32 sent to the env when it differs from ``actions`` (collection
            with action noise, DART-style), else ``None``.
        name: group name inside ``data/`` (``"demo_3"``).
    """

    actions: np.ndarray
    states: np.ndarray
    obs: dict[str, np.ndarray]
    gripper_command: np.ndarray
    attrs: dict = field(default_factory=dict)
    label: np.ndarray | None = None
    obstacle_points: np.ndarray | None = None
    rewards: np.ndarray | None = None
    dones: np.ndarray | None = None
    executed_actions: np.ndarray | None = None
    name: str = ""

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    @property
    def key(self) -> tuple[int, int, int]:
        """``(task, init_state, seed)``: what identifies a collected demo for resuming."""
        return demo_key(self.attrs)


@dataclass
class Dataset:
    """A loaded dataset: ``demos`` in file order and the ``data`` group's attributes."""

    path: Path
    demos: list[Demo]
    attrs: dict

    def __len__(self) -> int:
        return len(self.demos)

    def __iter__(self):
        return iter(self.demos)

    def __getitem__(self, index: int) -> Demo:
        return self.demos[index]


def demo_key(attrs: dict) -> tuple[int, int, int]:
    return (int(attrs.get("task", -1)), int(attrs.get("init_state", -1)), int(attrs.get("seed", -1)))


def _decode(value):
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str) and value[:1] in "{[":
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    if isinstance(value, np.generic):
        return value.item()
    return value


def _open(path: Path, mode: str = "r"):
    h5py = _h5py()
    if not path.exists():
        raise DatasetError(f"{path}: no such dataset file")
    try:
        return h5py.File(path, mode)
    except OSError as exc:
        raise DatasetError(f"{path}: not a readable HDF5 file ({exc})") from exc


def _demo_names(group) -> list[str]:
    names = [n for n in group if n.startswith("demo_")]

    def index(name: str) -> int:
        try:
            return int(name.split("_", 1)[1])
        except ValueError:
            return 1 << 30

    return sorted(names, key=index)


def load(path: str | os.PathLike) -> Dataset:
    """Read a dataset written by :class:`DatasetWriter` or one of LIBERO's demonstration files.

    Raises:
        DatasetError: the file is missing, not HDF5, has no ``data`` group, or a demo lacks ``actions``.
    """
    path = Path(path)
    with _open(path) as f:
        if "data" not in f:
            raise DatasetError(f"{path}: no 'data' group; expected LIBERO/robomimic layout data/demo_<i>/...")
        data = f["data"]
        attrs = {k: _decode(v) for k, v in data.attrs.items()}
        demos = []
        for name in _demo_names(data):
            try:
                demos.append(_read_demo(data[name], name))
            except KeyError as exc:
                raise DatasetError(f"{path}: data/{name} is incomplete ({exc})") from exc
            except OSError as exc:
                raise DatasetError(f"{path}: data/{name} is unreadable ({exc})") from exc
    return Dataset(path, demos, attrs)


def read_env_args(path: str | os.PathLike) -> dict:
    """The ``data`` group's ``env_args`` (env name, kwargs) of a dataset file without reading its demos
    (``{}`` when the file stores none)."""
    path = Path(path)
    with _open(path) as f:
        data = f.get("data")
        value = _decode(data.attrs["env_args"]) if data is not None and "env_args" in data.attrs else {}
    return value if isinstance(value, dict) else {}


@dataclass(frozen=True)
class DatasetSummary:
    """Sizes of a dataset file, read without loading its arrays: ``demos`` (``augmented`` of them made by an
    augmentation), ``steps`` over all demos, and demos per task (``{task: count}``)."""

    demos: int
    augmented: int
    steps: int
    per_task: dict[int, int]


def summarize(path: str | os.PathLike) -> DatasetSummary:
    """The :class:`DatasetSummary` of a dataset file (``DatasetError`` when it is not one)."""
    path = Path(path)
    with _open(path) as f:
        if "data" not in f:
            raise DatasetError(f"{path}: no 'data' group; expected LIBERO/robomimic layout data/demo_<i>/...")
        demos = augmented = steps = 0
        per_task: dict[int, int] = {}
        for name in _demo_names(f["data"]):
            group = f["data"][name]
            demos += 1
            augmented += bool(group.attrs.get("augmented", False))
            steps += int(group["actions"].shape[0])
            task = int(group.attrs.get("task", -1))
            per_task[task] = per_task.get(task, 0) + 1
    return DatasetSummary(demos, augmented, steps, dict(sorted(per_task.items())))


def _read_demo(group, name: str) -> Demo:
    if "actions" not in group:
        raise KeyError("no 'actions' dataset")
    actions = np.asarray(group["actions"][()], dtype=np.float32)
    states = np.asarray(group["states"][()], dtype=np.float64) if "states" in group else np.zeros((0, 0))
    obs: dict[str, np.ndarray] = {}
    if "obs" in group:
        for key, value in group["obs"].items():
            if any(hint in key for hint in IMAGE_HINTS):
                continue
            obs[LIBERO_OBS_KEYS.get(key, key)] = np.asarray(value[()], dtype=np.float32)
    if "robot_joint_pos" not in obs and "robot_states" in group:
        pass  # LIBERO's robot_states is a concatenation we do not need to split
    gripper = (np.asarray(group["gripper_command"][()], dtype=np.float32) if "gripper_command" in group
               else actions[:, -1].copy())

    def optional(key):
        return np.asarray(group[key][()], dtype=np.float32) if key in group else None

    return Demo(
        actions=actions,
        states=states,
        obs=obs,
        gripper_command=gripper,
        attrs={k: _decode(v) for k, v in group.attrs.items()},
        label=optional("label"),
        obstacle_points=optional("obstacle_points"),
        rewards=optional("rewards"),
        dones=optional("dones"),
        executed_actions=optional("executed_actions"),
        name=name,
    )


class DatasetWriter:
    """Append demos one at a time to an HDF5 file, flushing after each, so an interrupted run keeps them.

    Opening an existing file resumes it: :meth:`has` tells which ``(task, init_state, seed)`` demos are
    already there, and new demos get the next free ``demo_<i>`` index. ``env_args`` must match the file's.

    Args:
        path: output file (parent folders are created).
        env_args: ``{"env_name", "env_version", "type", "env_kwargs"}``; stored as JSON in ``data.attrs``.
    """

    def __init__(self, path: str | os.PathLike, env_args: dict) -> None:
        h5py = _h5py()
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            try:
                self._file = h5py.File(self.path, "a")
            except OSError as exc:
                raise DatasetError(f"{self.path}: cannot resume, not a readable HDF5 file ({exc})") from exc
        else:
            self._file = h5py.File(self.path, "w")
        data = self._file.require_group("data")
        if "env_args" in data.attrs:
            old = _decode(data.attrs["env_args"])
            if old.get("env_name") != env_args.get("env_name"):
                self.close()
                raise DatasetError(f"{self.path}: holds demos of {old.get('env_name')!r}, "
                                   f"not {env_args.get('env_name')!r}; use another --out")
        else:
            data.attrs["env_args"] = json.dumps(env_args)
        self._data = data
        self._keys = set()
        self._next = 0
        self._total = 0
        for name in _demo_names(data):
            group = data[name]
            if "actions" not in group:  # a demo cut off mid-write: drop it, it is re-collected
                del data[name]
                continue
            self._keys.add(demo_key({k: _decode(v) for k, v in group.attrs.items()}))
            self._next = max(self._next, int(name.split("_", 1)[1]) + 1)
            self._total += int(group["actions"].shape[0])
        data.attrs["total"] = self._total

    def __enter__(self) -> DatasetWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __len__(self) -> int:
        return len(self._keys)

    def has(self, task: int, init_state: int, seed: int) -> bool:
        """Whether a demo with these identifiers is already in the file."""
        return (int(task), int(init_state), int(seed)) in self._keys

    def append(self, demo: Demo) -> str:
        """Write ``demo`` as the next ``demo_<i>`` and flush; returns the group name."""
        name = f"demo_{self._next}"
        group = self._data.create_group(name)
        for key, value in demo.attrs.items():
            group.attrs[key] = json.dumps(value) if isinstance(value, (dict, list)) else value
        group.attrs["num_samples"] = len(demo)
        obs = group.create_group("obs")
        for key, value in demo.obs.items():
            if is_recorded(key):
                obs.create_dataset(key, data=np.asarray(value, dtype=np.float32), compression="gzip")
        group.create_dataset("states", data=np.asarray(demo.states, dtype=np.float64), compression="gzip")
        group.create_dataset("gripper_command", data=np.asarray(demo.gripper_command, dtype=np.float32))
        n = len(demo)
        rewards = demo.rewards if demo.rewards is not None else np.zeros(n, dtype=np.float32)
        dones = demo.dones if demo.dones is not None else np.zeros(n, dtype=np.float32)
        group.create_dataset("rewards", data=np.asarray(rewards, dtype=np.float32))
        group.create_dataset("dones", data=np.asarray(dones, dtype=np.float32))
        if demo.executed_actions is not None:
            group.create_dataset("executed_actions", data=np.asarray(demo.executed_actions, dtype=np.float32))
        if demo.label is not None:
            group.create_dataset("label", data=np.asarray(demo.label, dtype=np.float32))
        if demo.obstacle_points is not None:
            group.create_dataset("obstacle_points", data=np.asarray(demo.obstacle_points, dtype=np.float32))
        # actions last: a group with actions is complete (a crash before this leaves a group we drop on resume)
        group.create_dataset("actions", data=np.asarray(demo.actions, dtype=np.float32))
        self._next += 1
        self._total += n
        self._data.attrs["total"] = self._total
        self._keys.add(demo.key)
        self._file.flush()
        return name

    def close(self) -> None:
        if getattr(self, "_file", None) is not None:
            self._file.close()
            self._file = None


class ActionSequence:
    """A policy that plays recorded actions ``(T, 7)`` in order (the rollout loop's replay driver)."""

    def __init__(self, actions: np.ndarray) -> None:
        self.actions = np.asarray(actions)
        self._next = 0

    def reset(self, seed: int | None = None) -> None:
        self._next = 0

    def act(self, obs) -> np.ndarray:
        action = self.actions[self._next]
        self._next += 1
        return action


class StateLog(Hook):
    """Keeps the simulator state before every step."""

    needs_states = True

    def __init__(self) -> None:
        self.states: list[np.ndarray] = []

    def on_step(self, step: Step) -> None:
        self.states.append(step.state)


def replay(env, demo: Demo, *, reset_seed: int | None = None) -> np.ndarray:
    """Re-execute the demo's actions (``executed_actions`` when it has them) from its recorded first state;
    returns the states before each action.

    The env is restored to the demo's episode (its task, init state and seed, so the scene and any obstacle
    match; ``reset_seed`` overrides the seed) and its recorded first state, then the actions are stepped
    through the rollout loop. With a deterministic env the result equals ``demo.states``. Stepping stops
    early if the episode ends, unless the demo was recorded past its first success (``tail_steps``,
    ``collect --tail-steps``).

    Returns:
        ``(T, S)`` float64 states, ``T <= len(demo)``.
    """
    if demo.states.size == 0:
        raise ValueError(f"demo {demo.name or '?'} has no recorded states; cannot replay")
    attrs = dict(demo.attrs) if reset_seed is None else {**demo.attrs, "seed": reset_seed}
    actions = demo.actions if demo.executed_actions is None else demo.executed_actions
    through_end = int(demo.attrs.get("tail_steps", 0)) > 0
    log = StateLog()

    def stop(step: Step) -> bool:
        return step.index + 1 >= len(actions) or (not through_end and (step.terminated or step.truncated))

    base = env.unwrapped  # restored, not reset through the wrappers: step the env itself (no TimeLimit needed)
    rollout(base, ActionSequence(actions), start=lambda e: e.restore(attrs, demo.states[0]), hooks=[log], stop=stop)
    return np.asarray(log.states)
