"""Where the bench's episodes run: in this process, in spawned worker processes, or on a Ray cluster.

Every backend takes the same picklable jobs and the same worker function (one episode in, one JSON record
out; the worker caches its env and policy between jobs) and yields the records as episodes finish, in any
order: the bench writes each line at once, so resume, manifest and report do not depend on the backend.

- ``local`` with one worker: in this process, in job order.
- ``local`` with N workers: a pool of N spawned processes (spawned, not forked: a forked MuJoCo/torch parent
  makes its children share one core, docs/performance.md).
- ``ray``: N Ray actors, each a long-lived process that keeps its env and policy cache like a local worker,
  reserving ``threads`` CPUs each. ``address=None`` starts a private local Ray instance with ``N x threads``
  CPUs; ``"auto"`` or ``"HOST:PORT"`` joins a running cluster (``ray start --head`` on one machine,
  ``ray start --address HOST:PORT`` on the others; detaug_gym and its checkpoints installed on every node).
  An actor that dies (a crashed simulator) has its episode recorded as an error, counted in the table and
  retried by a rerun, and is replaced.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any

BACKENDS = ("local", "ray")
RAY_HINT = 'pip install -e ".[ray]"'


def run_jobs(jobs: Sequence[Any], worker: Callable[[Any], dict], on_error: Callable[[Any, str], dict],
             backend: str = "local", workers: int = 1, threads: int = 1, address: str | None = None,
             env_vars: dict[str, str] | None = None) -> Iterator[dict]:
    """Yield ``worker(job)`` for every job as it finishes.

    Args:
        jobs: picklable jobs.
        worker: a module-level function (importable in a fresh process) that runs one job.
        on_error: the record of a job whose worker process died, from the job and the error text.
        backend: ``"local"`` or ``"ray"``.
        workers: parallel workers (processes or actors).
        threads: CPUs each worker uses (Ray reserves that many per actor).
        address: Ray only: ``None`` (a private local instance), ``"auto"`` or ``"HOST:PORT"``.
        env_vars: environment of the Ray workers (e.g. ``MUJOCO_GL``); local workers inherit this process's.
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; valid: {', '.join(BACKENDS)}")
    if backend == "ray":
        yield from _run_ray(jobs, worker, on_error, workers, threads, address, env_vars or {})
    elif address is not None:
        raise ValueError("--address is for --backend ray")
    elif workers <= 1:
        for job in jobs:
            yield worker(job)
    else:
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn")) as pool:
            yield from pool.map(worker, jobs, chunksize=1)


def import_ray():
    """The ``ray`` module, or a clear error saying how to install it."""
    try:
        import ray
    except ImportError:
        raise SystemExit(f"--backend ray needs Ray: {RAY_HINT}") from None
    return ray


def _run_ray(jobs, worker, on_error, workers: int, threads: int, address: str | None,
             env_vars: dict[str, str]) -> Iterator[dict]:
    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        runtime_env = {"env_vars": dict(env_vars)} if env_vars else None
        if address is None:
            ray.init(num_cpus=workers * threads, include_dashboard=False, runtime_env=runtime_env,
                     log_to_driver=False)
        else:
            ray.init(address=address, runtime_env=runtime_env, log_to_driver=False)
    try:
        total = int(ray.cluster_resources().get("CPU", 0))
        if workers * threads > total:
            raise SystemExit(f"--workers {workers} x --threads {threads} needs {workers * threads} CPUs but the Ray "
                             f"cluster has {total}; lower --workers or add nodes")
        yield from _schedule(ray, jobs, worker, on_error, workers, threads)
    finally:
        if started:
            ray.shutdown()


def _schedule(ray, jobs, worker, on_error, workers: int, threads: int) -> Iterator[dict]:
    """Feed the jobs to ``workers`` actors, one job in flight per actor, replacing an actor that dies."""
    Worker = ray.remote(num_cpus=threads, max_restarts=0)(_Actor)
    pending = list(reversed(jobs))
    running: dict = {}  # result ref -> (actor, job)

    def submit(actor) -> None:
        if pending:
            job = pending.pop()
            running[actor.run.remote(worker, job)] = (actor, job)

    for _ in range(min(workers, len(jobs))):
        submit(Worker.remote())
    try:
        while running:
            [ref], _ = ray.wait(list(running), num_returns=1)
            actor, job = running.pop(ref)
            try:
                result = ray.get(ref)
            except (ray.exceptions.RayActorError, ray.exceptions.WorkerCrashedError) as exc:
                result = on_error(job, f"worker died: {type(exc).__name__}: {str(exc).splitlines()[0]}")
                ray.kill(actor)
                actor = Worker.remote()
            yield result
            submit(actor)
    finally:  # the consumer stopped early (or an error): no actor outlives the run
        for actor, _ in running.values():
            ray.kill(actor)


class _Actor:
    """A Ray actor: a long-lived process running jobs with the worker function (whose module caches)."""

    def run(self, worker: Callable[[Any], dict], job: Any) -> dict:
        return worker(job)
