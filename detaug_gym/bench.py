"""Run methods on identical SafeLIBERO / Newton rollouts and report the paper's Table I.

Examples (copy-paste)::

    # the small default: a few Spatial episodes at both levels, a few minutes on 2 CPU cores
    python -m detaug_gym.bench

    # the paper's comparison on every suite and level, 10 episodes per cell, 2 worker processes
    python -m detaug_gym.bench --methods detaug cape aegis demogen --suites spatial object goal long \\
        --levels 1 2 --episodes 10 --seeds 0 1 2 --workers 2 --out results/table1

    # videos: the first episode of every (method, cell) and every failed one, as mp4 beside the JSONL
    python -m detaug_gym.bench --seeds 0 1 --video 1 --video-failures

    # the official SafeLIBERO episodes (SAFELIBERO_ROOT or --safelibero-root), 50 per task, feasible cells only
    python -m detaug_gym.bench --methods detaug cape aegis demogen --scenarios official --suites spatial \\
        --levels 1 2 --episodes 50 --cells feasible --out results/official_spatial

    # obstacle-free reference runs
    python -m detaug_gym.bench --methods scripted --levels free --episodes 20 --out results/free

    # method options after a colon (name:key=value,key=value): the paper's K sweep and ablations
    python -m detaug_gym.bench --methods detaug:k=1 detaug:k=8 detaug detaug:latch=True detaug:labels=zero

    # env options for every cell (gym.make kwargs): a shorter step limit, robosuite's own controller
    python -m detaug_gym.bench --methods scripted --env-kwargs max_episode_steps=100 controller=stock

Every method sees the same episodes: episode ``i`` of a (suite, level) cell uses task ``i mod #tasks``,
and the same seed (hence the same LIBERO init state and the same obstacle) for every method; each run seed
(``--seeds``) is its own set of episodes. Each finished episode is appended to ``<out>/episodes.jsonl`` at
once; rerunning the same command skips the episodes already there (an errored episode is run again and its
new line supersedes the old one), so an interrupted run loses nothing; a line torn by a crash is dropped.
``<out>/run.json`` records the command, config, package version, git revision and checkpoint hashes; a rerun
whose env options or checkpoints differ is refused. Tables (Markdown, CSV: Clean / Total / Avoid with 95 %
Wilson intervals, mean ± std over seeds, errors, ETS), ``eval_info.json`` (LeRobot's schema) and a bar chart
are rewritten at the end from the lines of the asked cells, seeds and episodes (any method in the folder).
"""

from __future__ import annotations

import ast
import json
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from tqdm import tqdm

from detaug_gym.backends import run_jobs
from detaug_gym.config import build_parser as config_parser
from detaug_gym.config import config_from_namespace
from detaug_gym.envs.suites import NUM_INIT_STATES, OFFICIAL_ID_VERSION, SUITES, get_suite, parse_level
from detaug_gym.manifest import check_manifest, method_checkpoints, write_manifest
from detaug_gym.policies.options import check_device
from detaug_gym.report import read_records, record_key, repair_log, write_report
from detaug_gym.rollout import EpisodeKey, EpisodeRecord, run_episodes
from detaug_gym.seeds import bench_episode_seed

DEFAULT_METHODS = ("detaug", "base", "scripted")
LOG = "episodes.jsonl"


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
    """Episodes per (method, suite, level) cell and run seed."""
    seeds: list[int] = field(default_factory=lambda: [0])
    """Run seeds, each its own set of episodes (episode seeds derive from it); tables show mean ± std over them."""
    workers: int = 1
    """Parallel workers: processes (--backend local) or Ray actors (--backend ray)."""
    threads: int = 1
    """Torch threads per worker."""
    envs_per_worker: int = 1
    """Episodes each worker steps together, one env each; flow policies that replan at the same step plan in
    one batched network call (the same records as one at a time to float32 rounding, docs/performance.md)."""
    device: str = "cpu"
    """Torch device of the flow policies' networks: cpu, cuda, cuda:N or auto (a method option device=... wins)."""
    backend: Literal["local", "ray"] = "local"
    """local (processes on this machine) or ray (Ray actors, local or on a cluster; pip install -e ".[ray]")."""
    address: str | None = None
    """--backend ray: none (start a private local Ray instance with --workers x --threads CPUs), auto or HOST:PORT
    (join a running cluster; detaug_gym installed on every node)."""
    out: str = "results/default"
    """Output folder (rerun the same command to resume)."""
    env_kwargs: list[str] = field(default_factory=list)
    """gym.make kwargs for every cell, key=value (max_episode_steps=100 controller=stock)."""
    video: int = 0
    """Render the first N episodes of every (method, cell, seed) as mp4 under <out>/videos (needs MUJOCO_GL=egl)."""
    video_failures: bool = False
    """Also keep a video of every failed episode (renders every episode)."""
    scenarios: Literal["procedural", "official"] = "procedural"
    """procedural (an obstacle placed from the seed on LIBERO's scenes) or official (SafeLIBERO's own episodes from
    --safelibero-root; --episodes then counts per task, 50 = all)."""
    scenario_version: int | None = None
    """Procedural scenario version of the L1/L2 ids: 2 (calibrated to the official scenarios with SafeLIBERO's scene
    edits, the default), 1 (calibrated spots on LIBERO's layouts; tables of 2026-12-04) or 0 (the -v0 scenarios the
    tables before 2026-12-04 were measured on)."""
    safelibero_root: str | None = None
    """The safelibero/libero/libero folder of a THU-RCSCT/vlsa-aegis checkout (default: $SAFELIBERO_ROOT)."""
    cells: Literal["all", "feasible"] = "all"
    """all, or feasible: leave out what the DetAug authors omit as infeasible (Spatial task 0, Long task 0 at L1)."""
    step_limits: Literal["suite", "aegis"] = "suite"
    """suite (220/280/300/520 steps: LIBERO-PRO's, the DetAug authors') or aegis (AEGIS's 300/300/300/550)."""
    settle: Literal["steps", "still"] = "steps"
    """steps (SafeLIBERO's 10 no-op steps) or still (then on until the obstacle is still)."""

    def __post_init__(self) -> None:
        for name in ("episodes", "workers", "threads", "envs_per_worker"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name} must be >= 1, got {getattr(self, name)}")
        if self.video < 0:
            raise ValueError(f"--video must be >= 0, got {self.video}")
        if self.scenarios == "official" and self.episodes > NUM_INIT_STATES:
            raise ValueError(f"--episodes counts episodes per task with --scenarios official; SafeLIBERO has "
                             f"{NUM_INIT_STATES} per task and level, got {self.episodes}")
        check_device(self.device)
        if self.address is not None and self.backend != "ray":
            raise ValueError("--address is read by --backend ray only")
        if self.safelibero_root is not None and self.scenarios != "official":
            raise ValueError("--safelibero-root is read by --scenarios official only")
        if self.scenario_version is not None:
            from detaug_gym.envs.obstacles import SCENARIO_VERSIONS

            if self.scenarios == "official":
                raise ValueError("--scenario-version chooses procedural scenarios; --scenarios official has one")
            if self.scenario_version not in SCENARIO_VERSIONS:
                raise ValueError(f"unknown --scenario-version {self.scenario_version}; valid: "
                                 f"{', '.join(map(str, SCENARIO_VERSIONS))}")
        for name in ("methods", "suites", "levels", "seeds"):
            if not getattr(self, name):
                raise ValueError(f"--{name} needs at least one value")
            setattr(self, name, list(dict.fromkeys(getattr(self, name))))  # a duplicate would count twice

    @property
    def renders(self) -> bool:
        return self.video > 0 or self.video_failures

    def cell_env_kwargs(self, suite: str) -> dict:
        """gym.make kwargs of ``suite``'s cells: --env-kwargs plus the scenario, settle and step-limit choices."""
        kwargs = parse_env_kwargs(self.env_kwargs)
        if self.scenarios == "official":
            kwargs.update(scenarios="official", **({"safelibero_root": self.safelibero_root}
                                                   if self.safelibero_root is not None else {}))
        if self.settle != "steps":
            kwargs["settle"] = self.settle
        aegis = SUITES[suite].aegis_max_steps
        if self.step_limits == "aegis" and aegis is not None:
            kwargs.setdefault("max_episode_steps", aegis)
        return kwargs

    def notes(self) -> tuple[str, ...]:
        """What the table's caption says about these choices."""
        notes = []
        if self.scenarios == "official":
            notes.append("Scenarios: the official SafeLIBERO episodes (Hu et al. 2025), read from the user's files.")
        if self.scenario_version == 0:
            notes.append("Scenarios: procedural -v0 (before their calibration to the official ones).")
        if self.scenario_version == 1:
            notes.append("Scenarios: procedural -v1 (calibrated spots on LIBERO's layouts, before SafeLIBERO's "
                         "scene edits).")
        if self.cells == "feasible":
            left = "; ".join(f"{s} {lv} task {', '.join(map(str, t))}" for s in SUITES if s in self.suites
                             for lv, t in SUITES[s].infeasible.items() if lv in map(parse_level, self.levels))
            if left:
                notes.append(f"Left out as infeasible (as the DetAug authors do): {left}.")
        if self.step_limits == "aegis":
            notes.append("Step limits: AEGIS's (300 / 300 / 300 / 550).")
        if self.settle == "still":
            notes.append("Settle: until the obstacle is still.")
        return tuple(notes)


@dataclass(frozen=True)
class Job:
    key: EpisodeKey
    suite: str
    level: str
    run_seed: int = 0
    threads: int = 1
    device: str = "cpu"
    env_kwargs: tuple[tuple[str, object], ...] = ()
    video: str | None = None  # mp4 path to write
    video_failures: bool = False  # render, keep the video only if the episode fails (unless ``keep_video``)
    keep_video: bool = False
    reset_options: tuple[tuple[str, object], ...] = ()  # beyond the task (official: SafeLIBERO's episode index)


def parse_levels(values: list[str]) -> list[str]:
    try:
        return list(dict.fromkeys(parse_level(v) for v in values))
    except ValueError as exc:
        raise SystemExit(f"{exc}") from None


def parse_suites(values: list[str]) -> list[str]:
    try:
        return list(dict.fromkeys(get_suite(v).name for v in values))
    except ValueError as exc:
        raise SystemExit(f"{exc}") from None


def _literal(value: str):
    try:
        return ast.literal_eval(value.strip())
    except (ValueError, SyntaxError):
        return value.strip()


def split_method(spec: str) -> tuple[str, dict[str, str]]:
    """``"detaug:k=8,labels=zero"`` -> ``("detaug", {"k": "8", "labels": "zero"})``: the name and the raw
    option strings (:func:`parse_method` converts them)."""
    name, _, options = spec.partition(":")
    raw = {}
    for item in filter(None, options.split(",")):
        key, eq, value = item.partition("=")
        if not eq or not key.strip().isidentifier():
            raise SystemExit(f"bad method option {item!r} in {spec!r}; write name:key=value[,key=value]")
        raw[key.strip()] = value.strip()
    return name.lower(), raw


def parse_method(spec: str) -> tuple[str, dict]:
    """``"detaug:k=8,latch=false"`` -> ``("detaug", {"k": 8, "latch": False})``: options converted and checked
    against the policy's declared option types and ranges (:func:`detaug_gym.policies.parse_policy_options`),
    without building the policy. ``ValueError`` / ``KeyError`` say what is wrong and what is valid."""
    from detaug_gym.policies import parse_policy_options

    name, raw = split_method(spec)
    return name, parse_policy_options(name, raw)


def parse_env_kwargs(items: list[str]) -> dict:
    """``["max_episode_steps=100", "controller=stock"]`` -> ``{"max_episode_steps": 100, "controller": "stock"}``."""
    out = {}
    for item in items:
        key, eq, value = item.partition("=")
        if not eq or not key.strip().isidentifier():
            raise SystemExit(f"bad --env-kwargs item {item!r}; write key=value (max_episode_steps=100)")
        out[key.strip()] = _literal(value)
    return out


def check_methods(methods: list[str], suites: list[str]) -> None:
    """Fail before any episode runs, with one line per problem: an unknown method, options its policy rejects,
    or a checkpoint missing for one of the suites."""
    from detaug_gym.policies import available_policies

    problems = []
    for spec in methods:
        name, _ = split_method(spec)
        if name not in available_policies():
            problems.append(f"unknown method {spec!r}; registered policies: {', '.join(available_policies())} "
                            "(options go after a colon: detaug:k=8)")
            continue
        try:
            name, options = parse_method(spec)
        except (ValueError, KeyError) as exc:
            problems.append(f"method {spec!r}: {exc.args[0] if exc.args else exc}")
            continue
        for suite in suites:
            try:
                missing = [p for p in method_checkpoints(name, options, suite) if not (p / "config.json").exists()]
            except (TypeError, ValueError) as exc:
                problems.append(f"method {spec!r}: {exc}")
                break
            if missing:
                problems.append(f"method {spec!r} on suite {suite!r}: no checkpoint at {missing[0]} (the zoo has "
                                f"it only for the suites whose cards are in policies/; train it with "
                                f"python -m detaug_gym.train --out {missing[0]})")
                continue
            for path in method_checkpoints(name, options, suite):
                problems += [f"method {spec!r} on suite {suite!r}: {p}" for p in _checkpoint_problem(path)]
    if problems:
        raise SystemExit("cannot run:\n  " + "\n  ".join(problems))


def _checkpoint_problem(path: Path) -> list[str]:
    """[] when the checkpoint at ``path`` loads, else its error (loading checks it against itself)."""
    from detaug_gym.models.checkpoint import CheckpointError, load_checkpoint

    try:
        load_checkpoint(path)
    except CheckpointError as exc:
        return [str(exc).splitlines()[0]]
    return []


def check_env_kwargs(cells: list[tuple[str, str]], cfg: BenchConfig) -> None:
    """Fail before any episode runs when the envs reject the cells' kwargs (making an env builds no scene;
    official scenarios check their files here)."""
    import gymnasium as gym

    import detaug_gym  # noqa: F401

    problems = []
    for suite, level in cells:
        kwargs = cfg.cell_env_kwargs(suite)
        if not kwargs:
            continue
        env_id = SUITES[suite].env_id(level, cfg.scenario_version)
        try:
            gym.make(env_id, **kwargs).close()
        except (TypeError, ValueError, FileNotFoundError) as exc:
            problems.append(f"{env_id} rejected the env options {kwargs}: {exc}")
    if problems:
        raise SystemExit("cannot run:\n  " + "\n  ".join(problems))


def plan_cells(suites: list[str], levels: list[str]) -> list[tuple[str, str]]:
    """The (suite, level) cells to run: each suite at the asked levels it has (Newton has no L1)."""
    return [(s, lv) for s in suites for lv in levels if lv in SUITES[s].levels]


def plan_jobs(methods, suites, levels, episodes, seeds, cfg: BenchConfig | None = None) -> list[Job]:
    """Every (method, cell, run seed, episode) job; ``seeds`` is one run seed or a list of them.

    Procedural: ``episodes`` per cell, episode ``i`` is task ``i mod #tasks``. Official (``cfg.scenarios``):
    ``episodes`` per task, episode ``i`` is task ``i mod #tasks`` at SafeLIBERO's episode ``i // #tasks``.
    ``cfg.cells == "feasible"`` drops the episodes of the infeasible tasks."""
    jobs = []
    official = cfg is not None and cfg.scenarios == "official"
    for run_seed in ([seeds] if isinstance(seeds, int) else seeds):
        for suite, level in plan_cells(suites, levels):
            spec = SUITES[suite]
            n_tasks = len(spec.tasks_for(level))
            kwargs = tuple(sorted(({} if cfg is None else cfg.cell_env_kwargs(suite)).items()))
            skip = spec.infeasible.get(level, ()) if cfg is not None and cfg.cells == "feasible" else ()
            for method in methods:
                for ep in range(episodes * n_tasks if official else episodes):
                    if ep % n_tasks in skip:
                        continue
                    version = OFFICIAL_ID_VERSION if official else None if cfg is None else cfg.scenario_version
                    key = EpisodeKey(method, spec.env_id(level, version), ep % n_tasks, ep,
                                     bench_episode_seed(run_seed, suite, level, ep))
                    options = (("episode", ep // n_tasks),) if official else ()
                    jobs.append(Job(key, suite, level, run_seed, env_kwargs=kwargs, reset_options=options))
    # Group by env so a worker reuses its compiled scenes, and by method so policies load once.
    return sorted(jobs, key=lambda j: (j.key.env_id, j.key.method, j.run_seed, j.key.episode))


def video_path(out: Path, job: Job) -> Path:
    method = re.sub(r"[^A-Za-z0-9_.-]+", "_", job.key.method)
    return out / "videos" / method / job.key.env_id / f"seed{job.run_seed}_ep{job.key.episode}.mp4"


_CACHE: dict = {}


def group_jobs(jobs: list[Job], size: int) -> list[tuple[Job, ...]]:
    """Consecutive jobs of one (method, cell, seed, env options, rendering) in groups of up to ``size``: the
    episodes a worker steps together (``--envs-per-worker``)."""
    def kind(job: Job) -> tuple:
        return job.key.method, job.key.env_id, job.run_seed, job.env_kwargs, job.video is not None

    groups: list[list[Job]] = []
    for job in jobs:
        if groups and len(groups[-1]) < size and kind(groups[-1][0]) == kind(job):
            groups[-1].append(job)
        else:
            groups.append([job])
    return [tuple(g) for g in groups]


def _run_group(group: tuple[Job, ...]) -> list[dict]:
    """Worker entry: run a group of episodes of one method and cell in lockstep, one cached env and policy per
    slot; with several, flow policies share a plan batcher (their replans at one step are one network call)."""
    import gymnasium as gym
    import torch

    import detaug_gym  # noqa: F401
    from detaug_gym.models.batching import PlanBatcher
    from detaug_gym.policies import make_policy, option_names, share_planner

    first = group[0]
    torch.set_num_threads(first.threads)  # torch's worker threads stall when several processes share the cores
    render = first.video is not None
    env_keys = [("env", first.key.env_id, first.env_kwargs, render, slot) for slot in range(len(group))]
    pol_keys = [("policy", first.key.method, first.suite, first.device, slot) for slot in range(len(group))]
    try:
        for env_key, pol_key in zip(env_keys, pol_keys):
            if env_key not in _CACHE:
                _CACHE[env_key] = gym.make(first.key.env_id, **dict(first.env_kwargs),
                                           **({"render_mode": "rgb_array"} if render else {}))
            if pol_key not in _CACHE:
                name, options = parse_method(first.key.method)
                if "device" in option_names(name, options):
                    options.setdefault("device", first.device)
                _CACHE[pol_key] = make_policy(name, suite=first.suite, **options)
    except Exception as exc:  # construction errors are recorded like episode errors
        return [error_record(job, f"{type(exc).__name__}: {exc}") for job in group]
    policies = [_CACHE[k] for k in pol_keys]
    batcher = PlanBatcher() if len(group) > 1 else None
    for policy in policies:
        share_planner(policy, batcher)
    hooks = [[] for _ in group]
    if render:
        from detaug_gym.video import VideoRecorder

        hooks = [[VideoRecorder(job.video, label=job.key.method)] for job in group]
    records = run_episodes([_CACHE[k] for k in env_keys], policies, [job.key for job in group], first.suite,
                           first.level, hooks, first.run_seed, [dict(job.reset_options) for job in group], batcher)
    for policy in policies:
        share_planner(policy, None)
    for job, record, hook, env_key in zip(group, records, hooks, env_keys):
        if render and hook[0].frames and (job.keep_video or not record.success):
            record.video = str(hook[0].save())
        if record.termination == "error":
            _CACHE.pop(env_key).close()  # a broken simulator is rebuilt for the next episode
    return [record.to_json() for record in records]


def _group_error(group: tuple[Job, ...], error: str) -> list[dict]:
    return [error_record(job, error) for job in group]


def error_record(job: Job, error: str) -> dict:
    """The JSON record of an episode that could not run (counted as an error, retried by a rerun)."""
    return EpisodeRecord(job.key.method, job.key.env_id, job.suite, job.level, job.key.task, job.key.episode,
                         job.key.seed, run_seed=job.run_seed, error=error).to_json()


def close_cached() -> None:
    """Close the envs this process cached (their renderers and simulators)."""
    for key in [k for k in _CACHE if k[0] == "env"]:
        _CACHE.pop(key).close()


def prepare_out(out: Path) -> Path:
    """Create ``out`` (a clear error when it is a file or cannot be created); returns the JSONL path."""
    if out.exists() and not out.is_dir():
        raise SystemExit(f"--out {out} is a file; give a folder (rerun the same command to resume)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SystemExit(f"--out {out}: cannot create the folder ({exc.strerror})") from None
    return out / LOG


def run(cfg: BenchConfig) -> str:
    """Run the episodes of ``cfg`` not yet in ``<out>/episodes.jsonl``, then rewrite the tables; returns the
    Markdown table."""
    methods = list(dict.fromkeys(m if ":" in m else m.lower() for m in cfg.methods))
    suites, levels = parse_suites(cfg.suites), parse_levels(cfg.levels)
    cells = plan_cells(suites, levels)
    if not cells:
        raise SystemExit(f"no cell to run: suites {', '.join(suites)} have none of the levels "
                         f"{', '.join(levels)} (their levels: "
                         + "; ".join(f"{s}: {', '.join(SUITES[s].levels)}" for s in suites) + ")")
    if cfg.scenarios == "official":
        lacking = [s for s in suites if not SUITES[s].official]
        if lacking:
            raise SystemExit(f"--scenarios official: {', '.join(lacking)} has no official SafeLIBERO scenarios "
                             f"(suites with them: {', '.join(n for n, s in SUITES.items() if s.official)})")
        if "Free" in levels:
            raise SystemExit("--scenarios official: SafeLIBERO has L1 and L2 only; drop --levels free")
    check_methods(methods, suites)
    check_env_kwargs(cells, cfg)
    if cfg.device != "cpu":  # fail here, not in every episode (imports torch only then)
        from detaug_gym.models.checkpoint import resolve_device

        try:
            resolve_device(cfg.device)
        except ValueError as err:
            raise SystemExit(f"--device: {err}") from None
    out = Path(cfg.out)
    log = prepare_out(out)
    check_manifest(out, cfg, methods, suites)
    dropped = repair_log(log)
    if dropped:
        print(f"repaired {log}: dropped {dropped} torn line(s) (a run was killed mid-write); those episodes rerun")
    records = read_records(log)
    done = {record_key(r) for r in records if r.get("termination") != "error"}
    retried = sum(r.get("termination") == "error" for r in records)
    planned = plan_jobs(methods, suites, levels, cfg.episodes, cfg.seeds, cfg=cfg)
    if not planned:
        raise SystemExit("no episode to run: --cells feasible leaves out every task of the asked cells")
    jobs = []
    for job in planned:
        if job.key.as_tuple() in done:
            continue
        first = job.key.episode < cfg.video
        if first or cfg.video_failures:
            job = replace(job, video=str(video_path(out, job)), keep_video=first, video_failures=cfg.video_failures)
        jobs.append(replace(job, threads=cfg.threads, device=cfg.device))
    write_manifest(out, cfg, methods, suites)
    print(f"{len(planned) - len(jobs)} of {len(planned)} episodes already in {log}; {len(jobs)} to run"
          + (f" (errored ones are retried: {retried} in the log)" if retried else ""))
    with open(log, "a") as f, tqdm(total=len(jobs), desc="episodes", unit="ep") as bar:

        def record(result: dict) -> None:
            if result.get("video"):
                result["video"] = os.path.relpath(result["video"], out)  # the folder stays movable
            f.write(json.dumps(result) + "\n")
            f.flush()
            os.fsync(f.fileno())
            bar.set_postfix_str(f"{result['method']} {result['env_id']} {result['termination']}")
            bar.update()

        env_vars = {"MUJOCO_GL": os.environ["MUJOCO_GL"]} if "MUJOCO_GL" in os.environ else {}
        try:
            for results in run_jobs(group_jobs(jobs, cfg.envs_per_worker), _run_group, _group_error, cfg.backend,
                                    cfg.workers, cfg.threads, cfg.address, env_vars):
                for result in results:
                    record(result)
        finally:
            close_cached()  # this process's envs (--workers 1 runs here)
    wanted = {j.key.as_tuple()[1:] for j in planned}  # any method's lines of the planned episodes
    text = write_report([r for r in read_records(log) if record_key(r)[1:] in wanted], out, notes=cfg.notes(),
                        beside_paper=cfg.scenarios == "official")
    print(text)
    print(f"wrote {out}/table.md, table.csv, levels.csv, tasks.csv, paired.csv, eval_info.json, results.png")
    return text


def build_parser():
    return config_parser(BenchConfig, prog="python -m detaug_gym.bench", description=__doc__)


def parse_config(argv: list[str] | None = None) -> BenchConfig:
    """The :class:`BenchConfig` of a command line; a bad value exits with the parser's message."""
    parser = build_parser()
    try:
        return config_from_namespace(BenchConfig, parser.parse_args(argv))
    except ValueError as exc:
        parser.error(str(exc))


def main(argv: list[str] | None = None) -> None:
    cfg = parse_config(argv)
    if cfg.renders:  # headless rendering; must be chosen before MuJoCo is imported (here and in workers)
        os.environ.setdefault("MUJOCO_GL", "egl")
    run(cfg)


if __name__ == "__main__":
    main()
