"""How one 20 Hz control step advances the physics.

``fast`` (the default) is :class:`~detaug_gym.envs.fast_osc.FastStepper`: robosuite 1.4's OSC_POSE law and
gripper ramp computed directly on MuJoCo's arrays, one pipeline pass per 2 ms substep, no observables.
``stock`` runs robosuite's own ``env.step`` (its Python controller at every substep, plus its observables):
the reference, and a safety valve. Both steppers expose ``reset()`` (start of episode, after the state was
loaded and forwarded) and ``step(action)`` (one control step of 25 physics substeps), and both produce the
same trajectories (see ``tests/test_fast_control.py``).
"""

from __future__ import annotations

import numpy as np

from detaug_gym.envs.fast_osc import FastStepper

CONTROLLERS = ("fast", "stock")


class StockStepper:
    """Delegates to robosuite's ``MujocoEnv.step`` unchanged."""

    def __init__(self, scene) -> None:
        self.sim_env = scene.sim_env

    def reset(self) -> None:
        self.sim_env.timestep = 0
        self.sim_env.done = False
        controller = self.sim_env.robots[0].controller
        # robosuite caches the arm state between policy steps; after a state load it must be re-read,
        # or the first goal of the episode is computed from the previous episode's last pose.
        controller.update(force=True)
        # A step with a zero rotation delta keeps the previous goal orientation; restart it where a freshly
        # reset LIBERO env has it (the end-effector orientation at the arm's init_qpos), so an episode does
        # not depend on the one before.
        controller.goal_ori = np.array(controller.initial_ee_ori_mat)

    def step(self, action: np.ndarray) -> None:
        self.sim_env.step(action)


def make_stepper(kind: str, scene):
    """The stepper called ``kind`` for ``scene``; ``ValueError`` lists the valid kinds."""
    if kind == "fast":
        return FastStepper(scene)
    if kind == "stock":
        return StockStepper(scene)
    raise ValueError(f"unknown controller {kind!r}; valid controllers: {', '.join(CONTROLLERS)}")
