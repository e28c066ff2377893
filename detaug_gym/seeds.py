"""The project's seeding schemes, one place for each: which seed an episode of a bench cell gets, which seed
collection attempt ``i`` of a task gets, and how an env turns its reset seed into the episode's random draws.
All are fixed formats: changing one changes every published number or every collected dataset, so they are
spelled only here.
"""

from __future__ import annotations

import zlib

import numpy as np

# Version of these formats as a whole; the bench records it in run.json and refuses to add episodes drawn under
# another one to a folder. 1: the env drew init state and obstacle from the reset seed alone; 2: episode_rng.
EPISODE_SCHEME = 2

DEMO_SEED_STRIDE = 1000


def bench_episode_seed(run_seed: int, suite: str, level: str, episode: int) -> int:
    """Seed of episode ``episode`` of the bench cell (suite, level) in run ``run_seed``; independent of the
    method and of the worker count, so every method sees the same episode."""
    return (zlib.crc32(f"{run_seed}/{suite}/{level}".encode()) + 7919 * episode) % (2**31)


def demo_seed(base: int, task: int, index: int) -> int:
    """Seed of collection attempt ``index`` of ``task`` (env reset and expert): ``base + 1000 task + index``."""
    return base + DEMO_SEED_STRIDE * task + index


def episode_rng(draw: int, suite: str, level: str, task: int) -> np.random.Generator:
    """The generator an env draws an episode's init state, obstacle and placement from.

    ``draw`` is the first value the env's reset stream gives after the task is chosen (so
    ``reset(seed=s)`` fixes it, and later resets without a seed continue the stream); the cell
    (``suite``, ``level``, ``task``) is mixed in, so one seed gives unrelated episodes in different cells
    instead of the same init-state index and obstacle type everywhere.
    """
    cell = zlib.crc32(f"{suite}/{level}/{task}".encode())
    return np.random.default_rng(np.random.SeedSequence(int(draw), spawn_key=(cell,)))
