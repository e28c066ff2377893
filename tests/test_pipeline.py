"""The pipeline scheduler: tasks take the cores they declare, the highest priority first, shorter ones backfilling
cores a waiting task could not use."""

from __future__ import annotations

import time

from detaug_gym.pipeline import Task, ready_tasks, run_tasks
from detaug_gym.zoo import STAGES, Paths, Recipe, build_stages, plan, wall_estimate


def _task(name: str, priority: float, cores: int = 1, needs: tuple[str, ...] = (), estimate: float = 0.0) -> Task:
    return Task(name, None, [], needs, priority, cores=cores, estimate_s=estimate)


def _running(*left: float) -> list[tuple[Task, float]]:
    """One-core tasks running, with these estimated seconds left (a task of unknown length: None)."""
    return [(_task(f"run{i}", 0.0, estimate=0.0 if s is None else 100.0), 0.0 if s is None else s)
            for i, s in enumerate(left)]


def test_one_core_tasks_fill_the_free_cores_in_priority_order():
    todo = [_task("low", 1.0), _task("high", 3.0), _task("mid", 2.0)]
    assert [t.name for t in ready_tasks(todo, set(), [], 2)] == ["high", "mid"]
    assert [t.name for t in ready_tasks(todo, set(), _running(9.0), 2)] == ["high"]
    assert ready_tasks(todo, set(), _running(9.0, 9.0), 2) == []


def test_a_two_core_task_waits_for_both_cores_and_nothing_lower_jumps_ahead():
    todo = [_task("train", 5.0, cores=2), _task("augment", 1.0)]
    assert ready_tasks(todo, set(), _running(None), 2) == []  # the one-core task would delay the training
    assert [t.name for t in ready_tasks(todo, set(), [], 2)] == ["train"]
    assert [t.name for t in ready_tasks(todo, set(), [], 1)] == ["train"]  # more cores than jobs: runs alone


def test_a_shorter_task_backfills_the_core_a_waiting_two_core_task_cannot_use_yet():
    todo = [_task("train", 5.0, cores=2, estimate=1500.0), _task("short", 1.0, estimate=1000.0),
            _task("long", 2.0, estimate=2000.0), _task("unknown", 3.0)]
    # the training waits ~1500 s for the running augmentation's core: only the task estimated to end first fills it
    assert [t.name for t in ready_tasks(todo, set(), _running(1500.0), 2)] == ["short"]
    assert [t.name for t in ready_tasks(todo, set(), _running(2500.0), 2)] == ["long"]  # the higher one first
    assert ready_tasks(todo, set(), _running(500.0), 2) == []  # none ends before the training could start
    assert ready_tasks(todo, set(), _running(None), 2) == []  # nothing known about when the core frees


def test_a_task_whose_needs_are_not_done_does_not_start():
    todo = [_task("train", 5.0, needs=("collect",)), _task("augment", 1.0)]
    assert [t.name for t in ready_tasks(todo, set(), [], 2)] == ["augment"]
    assert [t.name for t in ready_tasks(todo, {"collect"}, [], 2)] == ["train", "augment"]


def test_run_tasks_never_runs_a_two_core_command_beside_another(tmp_path):
    sleep = ["-n", "1", "-r", "1", "import time; time.sleep(0.6)"]  # python -m timeit: a real subprocess
    tasks = [Task("a", "timeit", sleep, (), 3.0), Task("b", "timeit", sleep, (), 2.0),
             Task("train", "timeit", sleep, ("a",), 10.0, cores=2), Task("c", "timeit", sleep, (), 1.0)]
    spans: dict[str, list[float]] = {}
    run_tasks(tasks, 2, tmp_path / "logs", "test", on_start=lambda t: spans.setdefault(t.name, [time.time()]),
              on_finish=lambda t, s: spans[t.name].append(time.time()))
    assert set(spans) == {"a", "b", "train", "c"}
    start, end = spans["train"]
    for name in ("a", "b", "c"):
        other_start, other_end = spans[name]
        assert other_end <= start + 0.05 or other_start >= end - 0.05, f"{name} overlapped the two-core task"


def test_the_zoo_gives_a_two_thread_training_both_cores():
    stages = build_stages(Recipe.load("long"), Paths.default("long"))
    assert stages["train_base"].cores == 2  # long.toml trains its base with threads = 2
    assert stages["evaluate"].cores == 2 and stages["collect"].cores == 1
    steps = plan(stages, list(STAGES), list(STAGES))
    shared = wall_estimate(steps, 2)
    stages["train_base"].cores = 1
    assert wall_estimate(steps, 2) < shared  # one core each: the augmentations would run beside the base
