"""The project's seeding schemes, one place for each: which seed an episode of a bench cell gets, and which seed
collection attempt ``i`` of a task gets. Both are fixed formats: changing one changes every published number or
every collected dataset, so they are spelled only here.
"""

from __future__ import annotations

import zlib

DEMO_SEED_STRIDE = 1000


def bench_episode_seed(run_seed: int, suite: str, level: str, episode: int) -> int:
    """Seed of episode ``episode`` of the bench cell (suite, level) in run ``run_seed``; independent of the
    method and of the worker count, so every method sees the same episode."""
    return (zlib.crc32(f"{run_seed}/{suite}/{level}".encode()) + 7919 * episode) % (2**31)


def demo_seed(base: int, task: int, index: int) -> int:
    """Seed of collection attempt ``index`` of ``task`` (env reset and expert): ``base + 1000 task + index``."""
    return base + DEMO_SEED_STRIDE * task + index
