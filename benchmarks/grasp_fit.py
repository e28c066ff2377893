"""How precisely a flow checkpoint grasps: in its own training demos (open loop) and in rollouts (run by hand).

    python benchmarks/grasp_fit.py --suite long
    python benchmarks/grasp_fit.py --suite object --checkpoint policies/base/object

A pick fails when the fingers close beside the object. This puts a number on how far beside, per task, two ways:

- **open loop** (``--demos`` per task of ``--data``, default the suite's clean demo file): from the demo's
  observation ``--lead`` steps before its first gripper close, sample ``--samples`` plans and measure the
  horizontal distance (cm) between each plan's end effector at the close step and the demo's. This is how well
  the network fits the data it was trained on, with no compounding error.
- **closed loop** (``--episodes`` Free episodes per task, reset seeds ``seed + i``): the policy and the scripted
  expert each run the same episode; at each one's first gripper close, the first tracked object's position relative
  to the end effector is read, and the horizontal distance (cm) between the policy's and the expert's is the grasp
  error. (Relative to the expert's offset, because some grasps are off-centre by design: a mug by its rim.)

Prints one row per task: medians and 90th percentiles of both errors, and how many policy rollouts closed at all.
"""

from __future__ import annotations

import argparse
from collections import defaultdict

import gymnasium as gym
import numpy as np
from tqdm import tqdm

import detaug_gym  # noqa: F401  (registers the envs)
from detaug_gym.augment.segment import SegmentConfig, closed_runs
from detaug_gym.envs.suites import SUITES
from detaug_gym.models.dataset import read_demos
from detaug_gym.models.policy import FlowPolicy, zoo_dir
from detaug_gym.policies.base import load, make_policy
from detaug_gym.report import markdown
from detaug_gym.rollout import Hook, Step, rollout


def first_close(gripper: np.ndarray) -> int | None:
    """Index of the first close of gripper commands (T,) (a grasp as the augmentation segments it), or None."""
    runs = closed_runs(gripper, SegmentConfig().min_closed)
    return runs[0][0] if runs else None


class FirstClose(Hook):
    """The first tracked object's position relative to the end effector (3,) at the first close command."""

    def on_start(self, env, obs: dict[str, np.ndarray], info: dict) -> None:
        self.offset: np.ndarray | None = None
        self._closed = False

    def on_step(self, step: Step) -> None:
        closed = bool(step.action[-1] > 0)
        if closed and not self._closed and self.offset is None:
            self.offset = np.asarray(step.obs["object_poses"])[0, :3] - np.asarray(step.obs["eef_pos"])
        self._closed = closed


def open_loop(policy: FlowPolicy, data: str, demos: int, lead: int, samples: int) -> dict[int, list[float]]:
    """Per task, the median (over ``samples`` plans) xy error (cm) of the planned grasp position per demo."""
    errors: dict[int, list[float]] = defaultdict(list)
    eef = policy.layout.key_slice("eef_pos")
    for demo in read_demos(data):
        task = int(demo.attrs["task"])
        close = first_close(demo.actions[:, -1])
        if len(errors[task]) >= demos or close is None or close < lead:
            continue
        obs = {key: value[close - lead] for key, value in demo.obs.items()}
        plans = policy.plan(obs, num_samples=samples).numpy()  # (K, H, D)
        planned = plans[:, lead, eef][:, :2]  # (K, 2)
        errors[task].append(float(np.median(np.linalg.norm(planned - demo.obs["eef_pos"][close, :2], axis=1))) * 100)
    return errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suite", default="long", help=f"a suite: {', '.join(SUITES)}")
    parser.add_argument("--checkpoint", help="a flow checkpoint folder (default the zoo's base of --suite)")
    parser.add_argument("--data", help="demos to fit (default data/<suite>.hdf5, the zoo's clean demos)")
    parser.add_argument("--demos", type=int, default=20, help="demos per task for the open-loop error")
    parser.add_argument("--lead", type=int, default=15, help="plan from this many steps before the close")
    parser.add_argument("--samples", type=int, default=8, help="plans per demo")
    parser.add_argument("--episodes", type=int, default=5, help="Free episodes per task (0: open loop only)")
    parser.add_argument("--seed", type=int, default=1000)
    args = parser.parse_args()
    if args.suite not in SUITES:
        parser.error(f"--suite {args.suite!r}: valid are {', '.join(SUITES)}")
    if args.lead < 1 or args.samples < 1 or args.demos < 1 or args.episodes < 0:
        parser.error("--lead, --samples and --demos must be >= 1, --episodes >= 0")
    spec = SUITES[args.suite]
    checkpoint = args.checkpoint or str(zoo_dir("base", args.suite))
    policy = load(checkpoint, seed=0)
    if args.lead >= policy.horizon:
        parser.error(f"--lead must be below the plan horizon {policy.horizon}")
    fit = open_loop(policy, args.data or f"data/{args.suite}.hdf5", args.demos, args.lead, args.samples)

    closed: dict[int, list[float]] = defaultdict(list)
    missed: dict[int, int] = defaultdict(int)
    if args.episodes:
        env = gym.make(spec.env_id("Free"))
        expert = make_policy("scripted")
        tasks = range(len(spec.tasks_for("Free")))
        runs = [(task, args.seed + i * len(tasks) + task) for i in range(args.episodes) for task in tasks]
        for task, seed in tqdm(runs, desc=f"grasps on {args.suite} Free", unit="ep"):
            hooks = {}
            for name, actor in (("expert", expert), ("policy", policy)):
                hooks[name] = FirstClose()
                rollout(env, actor, seed=seed, options={"task": task}, hooks=[hooks[name]])
            if hooks["policy"].offset is None or hooks["expert"].offset is None:
                missed[task] += 1
                continue
            closed[task].append(float(np.linalg.norm((hooks["policy"].offset - hooks["expert"].offset)[:2])) * 100)

    def stats(values: list[float]) -> str:
        return f"{np.median(values):.2f} / {np.percentile(values, 90):.2f}" if values else "-"

    print(f"\n{checkpoint} on {args.suite}: grasp xy error, cm (median / 90th percentile)\n")
    header = ["task", f"open loop ({args.lead} steps ahead, demos)", "demos",
              "closed loop (vs expert, same episode)", "episodes", "no close by one of the two"]
    rows = [[str(t), stats(fit[t]), str(len(fit[t])), stats(closed[t]), str(len(closed[t])), str(missed[t])]
            for t in sorted(set(fit) | set(closed) | set(missed))]
    print(markdown(header, rows))


if __name__ == "__main__":
    main()
