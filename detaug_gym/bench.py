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
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from multiprocessing import get_context
from pathlib import Path

from tqdm import tqdm

from detaug_gym.envs.suites import SUITES
from detaug_gym.report import read_records, write_report
from detaug_gym.rollout import EpisodeKey, run_episode

LEVEL_NAMES = {"1": "L1", "2": "L2", "free": "Free", "l1": "L1", "l2": "L2"}
DEFAULT_METHODS = ("detaug", "base", "scripted")


@dataclass(frozen=True)
class Job:
    key: EpisodeKey
    suite: str
    level: str
    threads: int = 1


def parse_levels(values: list[str]) -> list[str]:
    out = []
    for value in values:
        if value.lower() not in LEVEL_NAMES:
            raise SystemExit(f"unknown level {value!r}; valid levels: 1, 2, free")
        out.append(LEVEL_NAMES[value.lower()])
    return out


def parse_suites(values: list[str]) -> list[str]:
    valid = [*SUITES, "newton"]
    for value in values:
        if value.lower() not in valid:
            raise SystemExit(f"unknown suite {value!r}; valid suites: {', '.join(valid)}")
    return [v.lower() for v in values]


def parse_method(spec: str) -> tuple[str, dict]:
    """``"detaug:k=8,labels=zero"`` -> ``("detaug", {"k": 8, "labels": "zero"})``; values are Python
    literals where they parse as one (``8``, ``True``, ``0.5``) and strings otherwise."""
    name, _, options = spec.partition(":")
    kwargs = {}
    for item in filter(None, options.split(",")):
        key, eq, value = item.partition("=")
        if not eq or not key.strip().isidentifier():
            raise SystemExit(f"bad method option {item!r} in {spec!r}; write name:key=value[,key=value]")
        try:
            kwargs[key.strip()] = ast.literal_eval(value.strip())
        except (ValueError, SyntaxError):
            kwargs[key.strip()] = value.strip()
    return name.lower(), kwargs


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


def env_id_for(suite: str, level: str) -> str:
    if suite == "newton":
        return "Newton-PickPlace-v0" if level == "Free" else "Newton-PickPlace-Cylinder-v0"
    return f"SafeLibero-{suite.capitalize()}-{level}-v0"


def episode_seed(base_seed: int, suite: str, level: str, episode: int) -> int:
    """A seed per (run seed, cell, episode), independent of the method and of the worker count."""
    return (zlib.crc32(f"{base_seed}/{suite}/{level}".encode()) + 7919 * episode) % (2**31)


def plan_jobs(methods, suites, levels, episodes, seed) -> list[Job]:
    jobs = []
    for suite in suites:
        for level in levels:
            if suite == "newton" and level == "L1":
                continue  # the Newton task has one obstacle level (the cylinder on the path)
            n_tasks = 1 if suite == "newton" else len(SUITES[suite].tasks_for(level))
            for method in methods:
                for ep in range(episodes):
                    key = EpisodeKey(method, env_id_for(suite, level), ep % n_tasks, ep,
                                     episode_seed(seed, suite, level, ep))
                    jobs.append(Job(key, suite, level))
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
    env_key, pol_key = ("env", job.key.env_id), ("policy", job.key.method, job.suite)
    try:
        if env_key not in _CACHE:
            _CACHE[env_key] = gym.make(job.key.env_id)
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


def run(args: argparse.Namespace) -> str:
    methods = [m if ":" in m else m.lower() for m in args.methods]
    suites, levels = parse_suites(args.suites), parse_levels(args.levels)
    check_methods(methods, suites[0])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log = out / "episodes.jsonl"
    done = {(r["method"], r["env_id"], r["task"], r["episode"], r["seed"]) for r in read_records(log)}
    jobs = [replace(j, threads=args.threads) for j in plan_jobs(methods, suites, levels, args.episodes, args.seed)
            if j.key.as_tuple() not in done]
    print(f"{len(done)} episodes already in {log}; {len(jobs)} to run")
    with open(log, "a") as f, tqdm(total=len(jobs), desc="episodes", unit="ep") as bar:

        def record(result: dict) -> None:
            f.write(json.dumps(result) + "\n")
            f.flush()
            os.fsync(f.fileno())
            bar.set_postfix_str(f"{result['method']} {result['env_id']} {result['termination']}")
            bar.update()

        if args.workers <= 1:
            for job in jobs:
                record(_run_job(job))
        else:
            with ProcessPoolExecutor(args.workers, mp_context=get_context("spawn")) as pool:
                for result in pool.map(_run_job, jobs, chunksize=1):
                    record(result)
    text = write_report(read_records(log), out)
    print(text)
    print(f"wrote {out}/table.md, table.csv, levels.csv, results.png")
    return text


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m detaug_gym.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS),
                   help="registered policy names, each optionally with options: detaug:k=8,latch=True")
    p.add_argument("--suites", nargs="+", default=["spatial"], help="spatial object goal long newton")
    p.add_argument("--levels", nargs="+", default=["1", "2"], help="1 2 free")
    p.add_argument("--episodes", type=int, default=4, help="episodes per (method, suite, level) cell")
    p.add_argument("--seed", type=int, default=0, help="run seed; episode seeds derive from it")
    p.add_argument("--workers", type=int, default=1, help="parallel worker processes")
    p.add_argument("--threads", type=int, default=1, help="torch threads per worker")
    p.add_argument("--out", default="results/default", help="output folder (rerun the same command to resume)")
    return p


def main(argv: list[str] | None = None) -> None:
    run(build_parser().parse_args(argv))


if __name__ == "__main__":
    main()
