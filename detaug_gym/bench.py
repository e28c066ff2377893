"""Run methods on identical SafeLIBERO / Newton rollouts and report the paper's Table I.

Examples (copy-paste)::

    # the small default: a few Spatial episodes at both levels, a few minutes on 2 CPU cores
    python -m detaug_gym.bench

    # the paper's comparison on every suite and level, 10 episodes per cell, 2 worker processes
    python -m detaug_gym.bench --methods detaug cape aegis demogen --suites spatial object goal long \\
        --levels 1 2 --episodes 10 --seed 0 --workers 2 --out results/table1

    # obstacle-free reference runs
    python -m detaug_gym.bench --methods scripted --levels free --episodes 20 --out results/free

    # method options after a colon (name:key=value,key=value): the paper's K sweep and ablations
    python -m detaug_gym.bench --methods detaug:k=1 detaug:k=8 detaug detaug:latch=True detaug:labels=zero

    # env options for every cell (gym.make kwargs): a shorter step limit, robosuite's own controller
    python -m detaug_gym.bench --methods scripted --env-kwargs max_episode_steps=100 controller=stock

Every method sees the same episodes: episode ``i`` of a (suite, level) cell uses task ``i mod #tasks``,
and the same seed (hence the same LIBERO init state and the same obstacle) for every method. Each
finished episode is appended to ``<out>/episodes.jsonl`` at once; rerunning the same command skips the
episodes already there, so an interrupted run loses nothing. Tables (Markdown, CSV) and a bar chart are
rewritten from all lines at the end.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path

from tqdm import tqdm

from detaug_gym.config import add_dataclass_arguments
from detaug_gym.envs.suites import SUITES, get_suite, parse_level
from detaug_gym.report import read_records, write_report
from detaug_gym.rollout import EpisodeKey, run_episode
from detaug_gym.seeds import bench_episode_seed

DEFAULT_METHODS = ("detaug", "base", "scripted")


@dataclass
class BenchConfig:
    """What ``python -m detaug_gym.bench`` runs (every field is a command-line flag)."""

    methods: list[str] = field(default_factory=lambda: list(DEFAULT_METHODS))
    """Registered policy names, each optionally with options: detaug:k=8,latch=True."""
    suites: list[str] = field(default_factory=lambda: ["spatial"])
    """Suites of the suite registry: spatial object goal long newton."""
    levels: list[str] = field(default_factory=lambda: ["1", "2"])
    """Levels: 1 2 free (a suite without a level, like newton's 1, skips it)."""
    episodes: int = 4
    """Episodes per (method, suite, level) cell."""
    seed: int = 0
    """Run seed; episode seeds derive from it (detaug_gym.seeds.bench_episode_seed)."""
    workers: int = 1
    """Parallel worker processes."""
    threads: int = 1
    """Torch threads per worker."""
    out: str = "results/default"
    """Output folder (rerun the same command to resume)."""
    env_kwargs: list[str] = field(default_factory=list)
    """gym.make kwargs for every cell, key=value (max_episode_steps=100 controller=stock)."""


@dataclass(frozen=True)
class Job:
    key: EpisodeKey
    suite: str
    level: str
    threads: int = 1
    env_kwargs: tuple[tuple[str, object], ...] = ()


def parse_levels(values: list[str]) -> list[str]:
    try:
        return [parse_level(v) for v in values]
    except ValueError as exc:
        raise SystemExit(f"{exc}") from None


def parse_suites(values: list[str]) -> list[str]:
    try:
        return [get_suite(v).name for v in values]
    except ValueError as exc:
        raise SystemExit(f"{exc}") from None


def _literal(value: str):
    try:
        return ast.literal_eval(value.strip())
    except (ValueError, SyntaxError):
        return value.strip()


def parse_method(spec: str) -> tuple[str, dict]:
    """``"detaug:k=8,labels=zero"`` -> ``("detaug", {"k": 8, "labels": "zero"})``; values are Python
    literals where they parse as one (``8``, ``True``, ``0.5``) and strings otherwise."""
    name, _, options = spec.partition(":")
    kwargs = {}
    for item in filter(None, options.split(",")):
        key, eq, value = item.partition("=")
        if not eq or not key.strip().isidentifier():
            raise SystemExit(f"bad method option {item!r} in {spec!r}; write name:key=value[,key=value]")
        kwargs[key.strip()] = _literal(value)
    return name.lower(), kwargs


def parse_env_kwargs(items: list[str]) -> dict:
    """``["max_episode_steps=100", "controller=stock"]`` -> ``{"max_episode_steps": 100, "controller": "stock"}``."""
    out = {}
    for item in items:
        key, eq, value = item.partition("=")
        if not eq or not key.strip().isidentifier():
            raise SystemExit(f"bad --env-kwargs item {item!r}; write key=value (max_episode_steps=100)")
        out[key.strip()] = _literal(value)
    return out


def check_methods(methods: list[str], suite: str = "spatial") -> None:
    """Fail before any episode runs on an unknown method or on options its policy rejects."""
    from detaug_gym.policies import available_policies, make_policy

    missing = [m for m in methods if parse_method(m)[0] not in available_policies()]
    if missing:
        raise SystemExit(f"unknown method(s) {', '.join(missing)}; registered policies: "
                         f"{', '.join(available_policies())} (options go after a colon: detaug:k=8)")
    for spec in methods:
        name, options = parse_method(spec)
        if options:
            try:
                make_policy(name, suite=suite, **options)
            except (TypeError, ValueError) as exc:
                raise SystemExit(f"method {spec!r}: {exc}") from exc


def check_env_kwargs(cells: list[tuple[str, str]], env_kwargs: dict) -> None:
    """Fail before any episode runs when the envs reject ``env_kwargs`` (making an env builds no scene)."""
    if not env_kwargs:
        return
    import gymnasium as gym

    import detaug_gym  # noqa: F401

    for suite, level in cells:
        try:
            gym.make(SUITES[suite].env_id(level), **env_kwargs).close()
        except (TypeError, ValueError) as exc:
            raise SystemExit(f"--env-kwargs {env_kwargs} rejected by {SUITES[suite].env_id(level)}: {exc}") from None


def plan_cells(suites: list[str], levels: list[str]) -> list[tuple[str, str]]:
    """The (suite, level) cells to run: each suite at the asked levels it has (Newton has no L1)."""
    return [(s, lv) for s in suites for lv in levels if lv in SUITES[s].levels]


def plan_jobs(methods, suites, levels, episodes, seed, env_kwargs: dict | None = None) -> list[Job]:
    jobs = []
    kwargs = tuple(sorted((env_kwargs or {}).items()))
    for suite, level in plan_cells(suites, levels):
        spec = SUITES[suite]
        n_tasks = len(spec.tasks_for(level))
        for method in methods:
            for ep in range(episodes):
                key = EpisodeKey(method, spec.env_id(level), ep % n_tasks, ep,
                                 bench_episode_seed(seed, suite, level, ep))
                jobs.append(Job(key, suite, level, env_kwargs=kwargs))
    # Group by env so a worker reuses its compiled scenes, and by method so policies load once.
    return sorted(jobs, key=lambda j: (j.key.env_id, j.key.method, j.key.episode))


_CACHE: dict = {}


def _run_job(job: Job) -> dict:
    """Worker entry: run one episode with cached env and policy."""
    import gymnasium as gym
    import torch

    import detaug_gym  # noqa: F401
    from detaug_gym.policies import make_policy

    torch.set_num_threads(job.threads)  # torch's worker threads stall when several processes share the cores
    env_key, pol_key = ("env", job.key.env_id, job.env_kwargs), ("policy", job.key.method, job.suite)
    try:
        if env_key not in _CACHE:
            _CACHE[env_key] = gym.make(job.key.env_id, **dict(job.env_kwargs))
        if pol_key not in _CACHE:
            name, options = parse_method(job.key.method)
            _CACHE[pol_key] = make_policy(name, suite=job.suite, **options)
    except Exception as exc:  # construction errors are recorded like episode errors
        from detaug_gym.rollout import EpisodeRecord

        rec = EpisodeRecord(job.key.method, job.key.env_id, job.suite, job.level, job.key.task,
                            job.key.episode, job.key.seed, error=f"{type(exc).__name__}: {exc}")
        return rec.to_json()
    record = run_episode(_CACHE[env_key], _CACHE[pol_key], job.key, job.suite, job.level)
    if record.termination == "error":
        _CACHE.pop(env_key).close()  # a broken simulator is rebuilt for the next episode
    return record.to_json()


def run(cfg: BenchConfig) -> str:
    """Run the episodes of ``cfg`` not yet in ``<out>/episodes.jsonl``, then rewrite the tables; returns the
    Markdown table."""
    methods = [m if ":" in m else m.lower() for m in cfg.methods]
    suites, levels = parse_suites(cfg.suites), parse_levels(cfg.levels)
    cells = plan_cells(suites, levels)
    if not cells:
        raise SystemExit(f"no cell to run: suites {', '.join(suites)} have none of the levels "
                         f"{', '.join(levels)} (their levels: "
                         + "; ".join(f"{s}: {', '.join(SUITES[s].levels)}" for s in suites) + ")")
    env_kwargs = parse_env_kwargs(cfg.env_kwargs)
    check_methods(methods, suites[0])
    check_env_kwargs(cells, env_kwargs)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "episodes.jsonl"
    done = {(r["method"], r["env_id"], r["task"], r["episode"], r["seed"]) for r in read_records(log)}
    jobs = [replace(j, threads=cfg.threads)
            for j in plan_jobs(methods, suites, levels, cfg.episodes, cfg.seed, env_kwargs)
            if j.key.as_tuple() not in done]
    print(f"{len(done)} episodes already in {log}; {len(jobs)} to run")
    with open(log, "a") as f, tqdm(total=len(jobs), desc="episodes", unit="ep") as bar:

        def record(result: dict) -> None:
            f.write(json.dumps(result) + "\n")
            f.flush()
            os.fsync(f.fileno())
            bar.set_postfix_str(f"{result['method']} {result['env_id']} {result['termination']}")
            bar.update()

        if cfg.workers <= 1:
            for job in jobs:
                record(_run_job(job))
        else:
            with ProcessPoolExecutor(cfg.workers, mp_context=get_context("spawn")) as pool:
                for result in pool.map(_run_job, jobs, chunksize=1):
                    record(result)
    text = write_report(read_records(log), out)
    print(text)
    print(f"wrote {out}/table.md, table.csv, levels.csv, results.png")
    return text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m detaug_gym.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_dataclass_arguments(p, BenchConfig)
    return p


def parse_config(argv: list[str] | None = None) -> BenchConfig:
    """The :class:`BenchConfig` of a command line."""
    return BenchConfig(**vars(build_parser().parse_args(argv)))


def main(argv: list[str] | None = None) -> None:
    run(parse_config(argv))


if __name__ == "__main__":
    main()
