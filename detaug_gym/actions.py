"""The action convention of every env in the package: robosuite's OSC_POSE delta controller at 20 Hz.

An action ``a`` ``(7,)`` in ``[-1, 1]`` (the env clips it) moves the controller's goal relative to the
end-effector pose ``(p, R)`` at which it is sent, and commands the gripper:

    goal_pos = p + POS_SCALE a[:3],    goal_rot = exp(ROT_SCALE a[3:6]) R,    a[6]: -1 open, +1 close,

with ``exp`` of a world-frame rotation vector (robosuite's ``control_delta`` with ``output_max`` 0.05 m and
0.5 rad). :func:`action_to_goal` and :func:`goal_to_action` are the two directions; the second clips, so
it is exact only for goals within one step's reach. Rotations follow :mod:`detaug_gym.rotations`.
"""

from __future__ import annotations

import numpy as np

from detaug_gym.rotations import rotation_error, rotvec_to_mat

POS_SCALE = 0.05  # m of goal displacement per action unit (OSC_POSE output_max)
ROT_SCALE = 0.5  # rad of goal rotation per action unit
CONTROL_HZ = 20  # control steps per second
CONTROL_DT = 0.05  # s per control step (1 / CONTROL_HZ)
ACTION_DIM = 7  # 3 position, 3 rotation, 1 gripper
GRIPPER_OPEN = -1.0
GRIPPER_CLOSE = 1.0


def action_to_goal(pos: np.ndarray, rot: np.ndarray, action: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The controller goal an action sets when sent at end-effector pose ``pos`` ``(3,)``, ``rot`` ``(3, 3)``.

    ``action`` ``(7,)`` (or ``(6,)``, the gripper is ignored) is clipped to [-1, 1] first, as the env does.
    Returns ``goal_pos`` ``(3,)`` and ``goal_rot`` ``(3, 3)``.
    """
    action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
    goal_pos = np.asarray(pos, dtype=np.float64) + POS_SCALE * action[:3]
    goal_rot = rotvec_to_mat(ROT_SCALE * action[3:6]) @ np.asarray(rot, dtype=np.float64)
    return goal_pos, goal_rot


def goal_to_action(pos: np.ndarray, rot: np.ndarray, goal_pos: np.ndarray, goal_rot: np.ndarray,
                   gripper: float) -> np.ndarray:
    """The action ``(7,)`` float64 that moves the goal from pose ``pos`` ``(3,)``, ``rot`` ``(3, 3)`` to
    ``goal_pos`` ``(3,)``, ``goal_rot`` ``(3, 3)``, clipped to [-1, 1], with gripper command ``gripper``."""
    action = np.zeros(ACTION_DIM)
    action[:3] = np.clip((goal_pos - pos) / POS_SCALE, -1.0, 1.0)
    action[3:6] = np.clip(rotation_error(goal_rot, rot) / ROT_SCALE, -1.0, 1.0)
    action[6] = gripper
    return action


def controller_settings(stepper: str) -> dict:
    """The convention as stored with recorded demos; ``stepper`` names the implementation of the controller
    that stepped the env (``"fast"``, the package's re-implementation, or ``"stock"``, robosuite's own)."""
    return {"type": "OSC_POSE", "stepper": stepper, "control_freq": CONTROL_HZ, "pos_scale": POS_SCALE,
            "rot_scale": ROT_SCALE, "gripper": f"{GRIPPER_OPEN:+.0f} open, {GRIPPER_CLOSE:+.0f} close"}
