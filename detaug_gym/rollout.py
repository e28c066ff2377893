"""The one rollout loop every method runs through, and the per-episode record it produces."""

from __future__ import annotations

import math
import time
import traceback
from dataclasses import asdict, dataclass

import numpy as np

from detaug_gym.policies.base import Policy


@dataclass(frozen=True)
class EpisodeKey:
    """Identifies an episode; every method sees the same (env_id, task, episode, seed) rollout."""

    method: str
    env_id: str
    task: int
    episode: int
    seed: int

    def as_tuple(self) -> tuple:
        return (self.method, self.env_id, self.task, self.episode, self.seed)


@dataclass
class EpisodeRecord:
    """One JSON line of the bench: what happened in one episode."""

    method: str
    env_id: str
    suite: str
    level: str
    task: int
    episode: int
    seed: int
    init_state: int | None = None
    obstacle: str | None = None
    success: bool = False
    collision: bool = False
    contact: bool = False
    steps: int = 0
    min_clearance: float | None = None
    wall_time: float = 0.0
    termination: str = "error"  # "success" | "timeout" | "error"
    error: str | None = None

    def to_json(self) -> dict:
        return asdict(self)


def run_episode(env, policy: Policy, key: EpisodeKey, suite: str, level: str) -> EpisodeRecord:
    """Roll ``policy`` out in ``env`` for one episode; never raises (errors are recorded)."""
    record = EpisodeRecord(key.method, key.env_id, suite, level, key.task, key.episode, key.seed)
    start = time.perf_counter()
    clearance = math.inf
    try:
        obs, info = env.reset(seed=key.seed, options={"task": key.task})
        policy.reset(seed=key.seed)
        record.init_state, record.obstacle = info.get("init_state"), info.get("obstacle")
        done = False
        while not done:
            obs, _, terminated, truncated, info = env.step(np.asarray(policy.act(obs), dtype=np.float32))
            record.steps += 1
            record.collision |= bool(info["collision"])
            record.contact |= bool(info["robot_obstacle_contact"])
            clearance = min(clearance, float(info["min_clearance"]))
            done = terminated or truncated
        record.success = bool(info["is_success"])
        record.termination = "success" if record.success else "timeout"
    except Exception as exc:  # one broken episode (policy bug, simulator instability) must not stop a run
        record.error = f"{type(exc).__name__}: {exc}\n{traceback.format_exc(limit=3)}"
        record.termination = "error"
    record.min_clearance = None if math.isinf(clearance) else clearance
    record.wall_time = time.perf_counter() - start
    return record
