"""How far a policy gets through a task's goal: per goal predicate, when it first held (run by hand).

    python benchmarks/goal_progress.py --suite long --method base --episodes 40
    python benchmarks/goal_progress.py --suite goal --task 3 --max-steps 600 --method base:checkpoint=PATH
    python benchmarks/goal_progress.py --suite spatial --level L1 --task 3 --method detaug --episodes 20

A task of LIBERO's is solved when every predicate of its BDDL goal holds (Long's have two: one per pick-place).
A bench record says only solved or not; this runs ``--episodes`` Free episodes (``--level L1`` or ``L2``: obstacle
episodes; ``--layout``: a Free env's object layout) (tasks in turn, episode ``i`` on
task ``i % tasks``, or every one on ``--task``, with reset seed ``seed + i``) and reads every goal predicate after
each step, so a failure is placed: no predicate ever held (the first pick-place failed), some but not all (a later
one failed), or all.

Prints one row per task: episodes, how many reached all / some / none of the goal, the mean step each predicate
first held, how many episodes held the whole goal at the end (a placed object can be knocked out again), and of
the episodes where no predicate ever held, how many lifted the first object (tracked object 0) by more than
``LIFTED`` (a grasp that worked, so the place failed) and how many never did (the grasp failed).
``--max-steps`` replaces the suite's step limit: a task that the policy solves late, past the limit, is slow;
one it does not solve with twice the limit is stuck. ``--out``'s lines also hold each tracked object's highest
rise (``lift``) and largest horizontal displacement (``moved``; Goal's drawer region moves as the drawer opens),
whether the obstacle was hit (``collision``; false on Free) and the least robot-obstacle distance (``clearance``, m).
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from contextlib import nullcontext

import gymnasium as gym
import numpy as np
from tqdm import tqdm

import detaug_gym  # noqa: F401  (registers the envs)
from detaug_gym.bench import check_methods, parse_method
from detaug_gym.envs.safe_libero import LAYOUTS
from detaug_gym.envs.suites import SUITES
from detaug_gym.policies.base import make_policy
from detaug_gym.report import markdown
from detaug_gym.rollout import Hook, ObstacleMetrics, Step, rollout

LIFTED = 0.05  # m: an object risen this far was grasped and carried


class GoalPredicates(Hook):
    """Records, per goal predicate of the episode's LIBERO task, the first step after which it held."""

    def on_start(self, env, obs: dict[str, np.ndarray], info: dict) -> None:
        self._scene = env.unwrapped.scene
        self.goals = [f"{g.relation} {g.obj} {g.target}" for g in self._scene.pick_places]
        self.first: list[int | None] = [None] * len(self.goals)
        self.final = [False] * len(self.goals)
        self._start = np.asarray(obs["object_poses"])[:, :3].copy()  # (N, 3) tracked objects' positions
        self.lift = np.zeros(len(self._start))  # (N,) highest rise of each tracked object (m)
        self.moved = np.zeros(len(self._start))  # (N,) largest horizontal displacement (m): a drawer pulled open

    def on_step(self, step: Step) -> None:
        position = np.asarray(step.next_obs["object_poses"])[:, :3]
        self.lift = np.maximum(self.lift, position[:, 2] - self._start[:, 2])
        self.moved = np.maximum(self.moved, np.linalg.norm(position[:, :2] - self._start[:, :2], axis=1))
        self.final = list(self._scene.goals_fn())  # the env's own sub-goal flags (its info["goals_met"] counts them)
        for i, held in enumerate(self.final):
            if held and self.first[i] is None:
                self.first[i] = step.index


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    libero = [name for name in SUITES if name != "newton"]
    parser.add_argument("--suite", default="long", help=f"a LIBERO suite: {', '.join(libero)}")
    parser.add_argument("--method", default="base",
                        help="a method as the bench spells it, e.g. base, detaug:labels=zero, base:checkpoint=PATH")
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--task", type=int, help="run every episode on this task index (default: tasks in turn)")
    parser.add_argument("--max-steps", type=int, help="step limit (default: the suite's)")
    parser.add_argument("--level", default="Free", help="Free (default), L1 or L2 (current scenarios)")
    parser.add_argument("--layout", choices=LAYOUTS, help="the Free env's object layout (default: the env's, LIBERO's)")
    parser.add_argument("--out", help="also write one JSON line per episode here")
    args = parser.parse_args()
    if args.suite not in libero:
        parser.error(f"--suite {args.suite!r}: valid are {', '.join(libero)}")
    tasks = len(SUITES[args.suite].tasks)
    if args.task is not None and not 0 <= args.task < tasks:
        parser.error(f"--task {args.task}: {args.suite} has tasks 0..{tasks - 1}")
    if args.max_steps is not None and args.max_steps < 1:
        parser.error(f"--max-steps {args.max_steps}: give a positive step count")
    try:
        env_id = SUITES[args.suite].env_id(args.level)
    except ValueError as err:
        parser.error(f"--level {args.level!r}: {err}")
    if args.layout is not None and env_id != SUITES[args.suite].env_id("Free"):
        parser.error(f"--layout is a Free env's option (got --level {args.level}); the obstacle levels use "
                     "SafeLIBERO's layouts")
    check_methods([args.method], [args.suite])  # the bench's own errors for an unknown method or bad options
    kwargs = {} if args.max_steps is None else {"max_episode_steps": args.max_steps}
    if args.layout is not None:
        kwargs["layout"] = args.layout
    env = gym.make(env_id, **kwargs)
    name, options = parse_method(args.method)
    policy = make_policy(name, suite=args.suite, **options)
    rows: dict[int, list[GoalPredicates]] = defaultdict(list)
    with open(args.out, "w") if args.out else nullcontext() as out:
        for episode in tqdm(range(args.episodes), desc=f"{args.method} {args.suite}", unit="ep"):
            task = episode % tasks if args.task is None else args.task
            hook, obstacle = GoalPredicates(), ObstacleMetrics()
            result = rollout(env, policy, seed=args.seed + episode, options={"task": task}, hooks=[hook, obstacle])
            rows[task].append(hook)
            if out:  # one line per episode as it ends
                clearance = None if np.isinf(obstacle.clearance) else round(obstacle.clearance, 4)
                out.write(json.dumps({"task": task, "seed": args.seed + episode, "goals": hook.goals,
                                      "first": hook.first, "final": hook.final, "steps": result.steps,
                                      "lift": hook.lift.round(4).tolist(),
                                      "moved": hook.moved.round(4).tolist(),
                                      "collision": obstacle.collision,
                                      "clearance": clearance}) + "\n")
                out.flush()
    layout = f" ({args.layout} layout)" if args.layout else ""
    print(f"\n{args.method} on {env_id}{layout}, {args.episodes} episodes "
          f"(reset seeds {args.seed}..)\n")
    header = ["task", "goal", "episodes", "all held", "some", "none (first object lifted / not)",
              "mean first step per predicate", "held at the end"]
    print(markdown(header, [_task_row(task, rows[task]) for task in sorted(rows)]))


def _task_row(task: int, hooks: list[GoalPredicates]) -> list[str]:
    """One table row from the episodes of one task."""
    n_goals = len(hooks[0].goals)
    reached = [sum(f is not None for f in h.first) for h in hooks]
    firsts = []
    for i in range(n_goals):
        steps = [h.first[i] for h in hooks if h.first[i] is not None]
        firsts.append(f"{np.mean(steps):.0f} ({len(steps)})" if steps else "- (0)")
    stuck = [h for h, r in zip(hooks, reached) if r == 0]
    lifted = sum(h.lift[0] > LIFTED for h in stuck)
    return [str(task), "; ".join(hooks[0].goals), str(len(hooks)), str(reached.count(n_goals)),
            str(sum(0 < r < n_goals for r in reached)), f"{len(stuck)} ({lifted} / {len(stuck) - lifted})",
            " / ".join(firsts), str(sum(all(h.final) for h in hooks))]

if __name__ == "__main__":
    main()
