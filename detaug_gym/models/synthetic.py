"""Synthetic demonstration files in the dataset layout, for tests and the training-budget benchmark.

The motions are smooth reach-grasp-carry curves whose shape depends on the task id, the object position
and (optionally) an arc label, so a policy must read its conditioning to reproduce them. They are not
physically consistent with any simulator: use them to exercise the pipeline, never to evaluate a policy.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from detaug_gym.actions import POS_SCALE

HOME = np.array([0.0, 0.2, 0.0, -2.4, 0.0, 2.6, 0.8])


def synthetic_demo(rng: np.random.Generator, length: int, task: int, n_tasks: int, n_slots: int,
                   label: np.ndarray | None) -> dict[str, np.ndarray]:
    """One demo as ``{"actions", "states", "gripper_command", "obs/<key>"...}`` arrays."""
    obj = rng.uniform([-0.1, -0.2, 0.9], [0.1, 0.2, 0.95])
    phase = np.linspace(0.0, 1.0, length)
    progress = np.clip(phase * 1.25, 0.0, 1.0) ** 2 * (3 - 2 * np.clip(phase * 1.25, 0.0, 1.0))
    bend = np.zeros(3) if label is None else np.array([label[0], label[1], 0.5 * label[0]]) * 0.05
    start = np.array([-0.2, 0.0, 1.1])
    goal = obj + np.array([0.0, 0.1 * (task - n_tasks / 2), 0.05])
    eef = start + np.outer(progress, goal - start) + np.outer(np.sin(np.pi * progress), bend)
    joints = HOME + np.outer(progress, np.r_[goal - start, goal - start, 0.1 * task]) \
        + np.outer(np.sin(np.pi * progress), np.r_[bend, bend, 0.0])
    grip = np.where(phase > 0.6, 1.0, -1.0)
    actions = np.zeros((length, 7))
    actions[:-1, :3] = np.clip(np.diff(eef, axis=0) / POS_SCALE * 5, -1, 1)
    actions[:, 6] = grip
    poses = np.zeros((length, n_slots, 7))
    poses[:, 0, :3] = obj
    poses[:, :, 6] = 1.0
    poses[phase > 0.6, 0, :3] = eef[phase > 0.6]
    task_id = np.zeros((length, n_tasks))
    task_id[:, task] = 1.0
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (length, 1))
    return {
        "actions": actions.astype(np.float32), "states": np.c_[joints, eef], "gripper_command": grip,
        "obs/robot_joint_pos": joints, "obs/robot_joint_vel": np.gradient(joints, axis=0) * 20,
        "obs/gripper_qpos": np.c_[0.04 - 0.03 * (grip > 0), -(0.04 - 0.03 * (grip > 0))],
        "obs/eef_pos": eef, "obs/eef_quat": quat, "obs/object_poses": poses,
        "obs/object_mask": np.ones((length, n_slots)), "obs/task_id": task_id,
    }


def write_synthetic_demos(path: str | Path, n_demos: int = 8, length: int = 60, n_tasks: int = 2, n_slots: int = 2,
                          label_dim: int = 0, with_points: bool = False, seed: int = 0) -> Path:
    """Write ``n_demos`` synthetic demos to ``path`` (``data/demo_<i>``); labels are arc-like (L,) vectors
    (zeros for every fourth demo, like original demos), clouds are boxes near the path."""
    rng = np.random.default_rng(seed)
    path = Path(path)
    with h5py.File(path, "w") as f:
        for i in range(n_demos):
            label = None
            if label_dim:
                phi, theta = rng.uniform(0.15 * np.pi, 0.85 * np.pi), rng.uniform(0.0, np.pi)
                label = np.resize(phi * np.array([np.cos(theta), np.sin(theta)]), label_dim) * (i % 4 != 0)
            demo = synthetic_demo(rng, length, i % n_tasks, n_tasks, n_slots, label)
            g = f.create_group(f"data/demo_{i}")
            for key, value in demo.items():
                dtype = np.float64 if key == "states" else np.float32
                g.create_dataset(key, data=value.astype(dtype))
            if label is not None:
                g.create_dataset("label", data=label.astype(np.float32))
            if with_points and i % 2 == 0:
                center = demo["obs/eef_pos"][length // 3]
                cloud = center + rng.uniform(-0.04, 0.04, (128, 3))
                g.create_dataset("obstacle_points", data=cloud.astype(np.float32))
            g.attrs["task"] = i % n_tasks
    return path
