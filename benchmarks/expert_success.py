"""Success (and obstacle-collision) rate of the scripted expert, per task and level (run by hand).

    python benchmarks/expert_success.py --suites spatial --levels Free               # 50 init states / task
    python benchmarks/expert_success.py --suites object goal long newton --levels Free
    python benchmarks/expert_success.py --suites spatial object goal long --levels L1 L2 --episodes 10

Episode ``i`` of a task starts from LIBERO init state ``i % 50`` with seed ``1000 + i`` for both the env
(obstacle type and placement on L1/L2) and the expert, so any episode is reproducible alone. Every
finished episode is appended to ``--out`` (JSONL) and a rerun skips episodes already there, so a long run
can be split or resumed; the table at the end is built from the file. Collision is ``info["collision"]``
at any step (the obstacle moved; Free envs have none). The expert is obstacle-blind by design, so L1/L2
give the unprotected baseline.
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

import gymnasium as gym

import detaug_gym  # noqa: F401
from detaug_gym.envs.suites import SUITES
from detaug_gym.policies import make_policy
from detaug_gym.rollout import ObstacleMetrics, rollout


def env_id(suite: str, level: str) -> str:
    return SUITES[suite].env_id(level)


def run_episode(env: gym.Env, expert, task: int, index: int) -> dict:
    seed = 1000 + index
    metrics = ObstacleMetrics()
    result = rollout(env, expert, seed=seed, options={"task": task, "init_state": index % 50}, hooks=[metrics])
    return {"success": bool(result.info.get("is_success")), "collision": metrics.collision, "steps": result.steps,
            "recipe": expert.recipe.key if expert.recipe else None}


def measure(suite: str, level: str, episodes: int, tasks: list[int] | None, out: Path) -> None:
    done = {(r["env"], r["task"], r["episode"]) for r in read(out)}
    env = gym.make(env_id(suite, level))
    expert = make_policy("scripted")
    name = env_id(suite, level)
    task_ids = tasks if tasks is not None else list(range(len(env.unwrapped.tasks)))
    for task in task_ids:
        start, ran = time.time(), 0
        for index in range(episodes):
            if (name, task, index) in done:
                continue
            row = {"env": name, "suite": suite, "level": level, "task": task, "episode": index}
            row |= run_episode(env, expert, task, index)
            with out.open("a") as f:
                f.write(json.dumps(row) + "\n")
            ran += 1
        print(f"{name} task {task}: {ran} episodes in {time.time() - start:.0f} s", flush=True)
    env.close()


def read(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def table(rows: list[dict]) -> str:
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        groups[(r["suite"], r["level"], r["task"], r["recipe"])].append(r)
    lines = ["| suite | level | task | recipe | episodes | success | collision | mean steps |",
             "|---|---|---|---|---|---|---|---|"]
    for (suite, level, task, recipe), rs in sorted(groups.items(), key=lambda kv: str(kv[0])):
        n = len(rs)
        ok = sum(r["success"] for r in rs)
        coll = sum(r["collision"] for r in rs)
        steps = sum(r["steps"] for r in rs) / n
        lines.append(f"| {suite} | {level} | {task} | {recipe} | {n} | {ok}/{n} ({100 * ok / n:.0f}%) | "
                     f"{coll}/{n} ({100 * coll / n:.0f}%) | {steps:.0f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suites", nargs="+", default=list(SUITES), choices=list(SUITES))
    parser.add_argument("--levels", nargs="+", default=["Free"], choices=["Free", "L1", "L2"])
    parser.add_argument("--episodes", type=int, default=50, help="episodes per task (init state i %% 50)")
    parser.add_argument("--tasks", type=int, nargs="+", default=None, help="task indices (default all)")
    parser.add_argument("--out", type=Path, default=Path("results/expert_success.jsonl"))
    parser.add_argument("--report", action="store_true", help="only print the table from --out")
    args = parser.parse_args()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if not args.report:
        for suite in args.suites:
            for level in [lv for lv in args.levels if lv in SUITES[suite].levels]:
                measure(suite, level, args.episodes, args.tasks, args.out)
    print(table(read(args.out)))


if __name__ == "__main__":
    main()
