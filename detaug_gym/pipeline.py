"""Run the project's commands as subprocesses, several at once, each when the tasks it needs are done.

The zoo build (:mod:`detaug_gym.zoo`) and the fine-tuning experiment (:mod:`detaug_gym.finetune`) are chains
of the project's own commands (collect, augment, train, bench). :func:`run_tasks` runs such a chain on ``jobs``
cores: a task takes the cores it declares (``cores``: a training's torch threads, a bench's workers; at most
``jobs``, so a task that asks for more runs alone), the ready task with the highest ``priority`` starts first and
no lower one starts before it (a two-core training is not starved by one-core tasks that keep a core busy), except
one that fits the free cores and is estimated to end before the waiting task's cores free up (backfilling: a core
is not left idle for nothing; ``estimate_s`` 0, unknown, never backfills nor frees early), each
command's output appended to ``<logs>/<name>.log`` (progress bars redrawn every 10 s), one tqdm bar over the
tasks. Every command resumes when rerun, so a stopped pipeline loses nothing: a failed task stops the start of
new ones and, once the running ones end, raises ``SystemExit`` with the tail of its log; Ctrl-C stops all.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class Task:
    """One command of a pipeline: ``python -m <module> <argv>`` (or ``call()`` in this process)."""

    name: str
    module: str | None
    argv: list[str]
    needs: tuple[str, ...] = ()
    priority: float = 0.0
    env: dict[str, str] = field(default_factory=dict)
    call: Callable[[], None] | None = None
    cores: int = 1
    """Cores the command keeps busy (its torch threads or bench workers); the scheduler counts them."""
    estimate_s: float = 0.0
    """Its expected run time (0: unknown), for backfilling."""


def cores_taken(task: Task, jobs: int) -> int:
    """The cores ``task`` holds while it runs: its ``cores``, at least 1 and at most ``jobs`` (then it runs alone)."""
    return min(max(1, task.cores), jobs)


def ready_tasks(todo: list[Task], done: set[str], running: list[tuple[Task, float]], jobs: int) -> list[Task]:
    """The tasks of ``todo`` to start now, beside ``running`` (each with its estimated seconds left) on ``jobs``
    cores: those whose needs are ``done``, highest priority first, while their cores (each clipped to ``jobs``)
    fit. The first that does not fit waits for cores and starts next; after it, only a task that fits the free
    cores and whose ``estimate_s`` ends before enough cores for the waiting one are expected to free up."""
    startable = sorted((t for t in todo if all(n in done for n in t.needs)), key=lambda t: -t.priority)
    busy = sum(cores_taken(t, jobs) for t, _ in running)
    chosen: list[Task] = []
    wait: float | None = None  # seconds until the waiting task's cores are expected free
    for task in startable:
        cores = cores_taken(task, jobs)
        if busy + cores > jobs:
            if wait is None:
                wait = _frees_in(running, busy + cores - jobs, jobs)
            continue
        if wait is not None and not 0.0 < task.estimate_s <= wait:
            continue
        chosen.append(task)
        busy += cores
        running = [*running, (task, task.estimate_s)]
    return chosen


def _frees_in(running: list[tuple[Task, float]], cores: int, jobs: int) -> float:
    """Estimated seconds until ``cores`` of the running tasks' cores are free (the soonest-ending first)."""
    freed = 0
    for task, left in sorted(running, key=lambda r: r[1]):
        freed += cores_taken(task, jobs)
        if freed >= cores:
            return max(left, 0.0) if task.estimate_s > 0.0 else 0.0
    return 0.0


def tail(path: Path, lines: int = 15) -> str:
    """The last non-blank lines of a log (progress-bar redraws split into lines)."""
    text = path.read_text(errors="replace").replace("\r", "\n") if path.exists() else ""
    return "\n".join([line for line in text.splitlines() if line.strip()][-lines:])


def run_tasks(tasks: list[Task], jobs: int, logs: Path, desc: str, done: set[str] | None = None,
              on_start: Callable[[Task], None] | None = None,
              on_finish: Callable[[Task, float], None] | None = None) -> None:
    """Run ``tasks`` (their needs outside ``tasks`` must be in ``done``); see the module doc."""
    from tqdm import tqdm

    todo, done = list(tasks), set(done or ())
    logs.mkdir(parents=True, exist_ok=True)
    running: dict[str, tuple[subprocess.Popen, float]] = {}
    failed: list[str] = []
    by_name = {t.name: t for t in tasks}
    bar = tqdm(total=len(todo), desc=desc, unit="task")

    def in_flight() -> list[tuple[Task, float]]:
        now = time.perf_counter()
        return [(by_name[name], by_name[name].estimate_s - (now - tic)) for name, (_, tic) in running.items()]

    def finish(task: Task, seconds: float) -> None:
        if on_finish is not None:
            on_finish(task, seconds)
        done.add(task.name)
        bar.update()
        tqdm.write(f"done  {task.name} in {seconds / 60:.1f} min")

    try:
        while todo or running:
            for task in [] if failed else ready_tasks(todo, done, in_flight(), jobs):
                todo.remove(task)
                if on_start is not None:
                    on_start(task)
                log = logs / f"{task.name}.log"
                if task.module is None:
                    tqdm.write(f"start {task.name}")
                    tic = time.perf_counter()
                    task.call()
                    finish(task, time.perf_counter() - tic)
                    continue
                prefix = "".join(f"{k}={v} " for k, v in task.env.items())
                tqdm.write(f"start {task.name}: {prefix}python -m {task.module} {' '.join(task.argv)}  (log: {log})")
                with open(log, "a") as out:
                    proc = subprocess.Popen([sys.executable, "-m", task.module, *task.argv], stdout=out,
                                            stderr=subprocess.STDOUT,
                                            env={**os.environ, **task.env, "TQDM_MININTERVAL": "10"})
                running[task.name] = (proc, time.perf_counter())
            if not running and todo:
                if failed:
                    break
                raise RuntimeError(f"{desc}: nothing can start; waiting: {', '.join(t.name for t in todo)}")
            time.sleep(0.5)
            for name, (proc, tic) in list(running.items()):
                if proc.poll() is None:
                    continue
                del running[name]
                if proc.returncode == 0:
                    finish(by_name[name], time.perf_counter() - tic)
                else:
                    failed.append(name)
                    tqdm.write(f"FAILED {name} (exit {proc.returncode}); last lines of {logs / name}.log:\n"
                               + tail(logs / f"{name}.log"))
            postfix = ", ".join(running) or "-"
            if bar.postfix != postfix:
                bar.set_postfix_str(postfix)
    except KeyboardInterrupt:
        for proc, _ in running.values():
            proc.send_signal(2)
        for proc, _ in running.values():
            proc.wait()
        raise SystemExit("interrupted; rerun the same command to resume") from None
    finally:
        bar.close()
    if failed:
        raise SystemExit(f"{', '.join(failed)} failed (logs in {logs}); fix it and rerun the same command to resume")
