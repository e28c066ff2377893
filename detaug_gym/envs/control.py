"""How one 20 Hz control step advances the physics.

``stock`` runs robosuite's own ``env.step`` (its Python OSC_POSE controller at every 2 ms substep, plus its
observables): the reference, and a safety valve. Both steppers expose ``reset()`` (start of episode, after
the state was loaded) and ``step(action)`` (one control step of 25 physics substeps).
"""

from __future__ import annotations

import numpy as np

CONTROLLERS = ("stock",)


class StockStepper:
    """Delegates to robosuite's ``MujocoEnv.step`` unchanged."""

    def __init__(self, scene) -> None:
        self.sim_env = scene.sim_env

    def reset(self) -> None:
        self.sim_env.timestep = 0
        self.sim_env.done = False
        # robosuite caches the arm state between policy steps; after a state load it must be re-read,
        # or the first goal of the episode is computed from the previous episode's last pose.
        self.sim_env.robots[0].controller.update(force=True)

    def step(self, action: np.ndarray) -> None:
        self.sim_env.step(action)


def make_stepper(kind: str, scene):
    """The stepper called ``kind`` for ``scene``; ``ValueError`` lists the valid kinds."""
    if kind == "stock":
        return StockStepper(scene)
    raise ValueError(f"unknown controller {kind!r}; valid controllers: {', '.join(CONTROLLERS)}")
