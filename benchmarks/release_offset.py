"""How far from its target a policy sets each object down (run by hand).

    python benchmarks/release_offset.py --suite goal --task 0 --methods scripted base --episodes 20
    python benchmarks/release_offset.py --suite long --task 0 --methods base base:checkpoint=PATH

Runs ``--episodes`` Free episodes of one task (reset seed ``seed + i``, the same for every method) and, at the
episode's end (success or the step limit), measures for each pick-place step of the task the horizontal offset of
the object from its target's centre (tracked poses; the target is the BDDL goal's region or object). A policy that
grasps well but places a few centimetres off its target's centre fails where the target is small or has a rim
(Goal's plate: the bowl ends on the rim and tips it). Prints per method and pick-place step the median and 90th
percentile offset (cm) and the successes; ``--out`` also writes one JSON line per episode.
"""

from __future__ import annotations

import argparse
import json
from contextlib import nullcontext

import gymnasium as gym
import numpy as np
from tqdm import tqdm

import detaug_gym  # noqa: F401  (registers the envs)
from detaug_gym.bench import check_methods, parse_method
from detaug_gym.envs.suites import SUITES
from detaug_gym.policies.base import make_policy
from detaug_gym.report import markdown
from detaug_gym.rollout import rollout


def final_offsets(env, obs: dict[str, np.ndarray]) -> list[float]:
    """Per pick-place step of the episode's task, the object's horizontal distance from its target (m)."""
    scene = env.unwrapped.scene
    positions = np.asarray(obs["object_poses"])[:, :3]
    out = []
    for step in scene.pick_places:
        obj, target = scene.tracked.index(step.obj), scene.tracked.index(step.target)
        out.append(float(np.linalg.norm(positions[obj, :2] - positions[target, :2])))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    libero = [name for name in SUITES if name != "newton"]
    parser.add_argument("--suite", default="goal", help=f"a LIBERO suite: {', '.join(libero)}")
    parser.add_argument("--task", type=int, default=0, help="task index in the suite")
    parser.add_argument("--methods", nargs="+", default=["scripted", "base"])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--out", help="also write one JSON line per episode here")
    args = parser.parse_args()
    if args.suite not in libero:
        parser.error(f"--suite {args.suite!r}: valid are {', '.join(libero)}")
    tasks = len(SUITES[args.suite].tasks)
    if not 0 <= args.task < tasks:
        parser.error(f"--task {args.task}: {args.suite} has tasks 0..{tasks - 1}")
    if args.episodes < 1:
        parser.error(f"--episodes {args.episodes}: give a positive count")
    check_methods(args.methods, [args.suite])  # the bench's own errors for an unknown method or bad options
    env = gym.make(SUITES[args.suite].env_id("Free"))
    rows = []
    with open(args.out, "w") if args.out else nullcontext() as out:
        for method in args.methods:
            name, options = parse_method(method)
            policy = make_policy(name, suite=args.suite, **options)
            offsets, successes = [], 0
            for episode in tqdm(range(args.episodes), desc=method, unit="ep"):
                result = rollout(env, policy, seed=args.seed + episode, options={"task": args.task})
                offsets.append(final_offsets(env, result.obs))
                successes += bool(result.info.get("is_success", False))
                if out:
                    out.write(json.dumps({"method": method, "seed": args.seed + episode, "steps": result.steps,
                                          "success": bool(result.info.get("is_success", False)),
                                          "offsets": np.round(offsets[-1], 4).tolist()}) + "\n")
                    out.flush()
            cm = 100 * np.asarray(offsets)  # (episodes, pick-places)
            for k, step in enumerate(env.unwrapped.scene.pick_places):
                rows.append([method, f"{step.obj} -> {step.target}", f"{np.median(cm[:, k]):.1f}",
                             f"{np.percentile(cm[:, k], 90):.1f}", f"{successes}/{args.episodes}"])
    last = args.seed + args.episodes - 1
    print(f"\nFree episodes of {args.suite} task {args.task}, reset seeds {args.seed}..{last}\n")
    print(markdown(["method", "pick-place", "median offset (cm)", "90th percentile (cm)", "solved"], rows))


if __name__ == "__main__":
    main()
