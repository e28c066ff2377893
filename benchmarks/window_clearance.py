"""How close the scripted expert's unbent parts come to the obstacle, per cell (run by hand).

    python benchmarks/window_clearance.py --suite spatial --levels L1 L2 --episodes 12
    python benchmarks/window_clearance.py --suite goal --levels L1 --episodes 10 --out runs/window_clearance.jsonl
    SAFELIBERO_ROOT=... python benchmarks/window_clearance.py --scenarios official --episodes 12

DetAug bends a demo's transits (approach, carry) into arcs and keeps its interaction windows (grasp, release) and
their margins as they were. Where those frozen frames themselves come near the obstacle, no arc label makes the
demo clear: its data holds no clean way through that cell, whatever the selection picks. This measures it on the
obstacle episodes, with the obstacle-blind scripted expert (the source of every demo) standing in for a demo of
that geometry.

Each episode (task ``i % tasks`` of the level, reset seed ``seed + i``; ``--scenarios official``: SafeLIBERO's
episode ``i // tasks`` of that task) runs the expert to its end; the obstacle
is taken as it stood at the reset (the expert may knock it later), and every frame's robot is scored against it
with DetAug's own geometry: :func:`~detaug_gym.geometry.robot_clearance` for the arm and fingers and, while the
fingers hold an object, the held object's observed surface points (:func:`~detaug_gym.geometry.held_object`).
The expert's executed gripper commands are cut the way the augmentation cuts demos
(:func:`~detaug_gym.augment.segment.segment_gripper`), so every frame is in a phase and is frozen (a window, its
margin, anything outside a transit) or bent (inside a transit).

Prints one row per cell: episodes, expert success, and how many episodes had their frozen / bent frames
penetrate the obstacle (clearance <= 0) or come within ``--margin`` of it (DetAug's ``inflate``, 1.5 cm: where
its score already counts a plan as colliding), and the phases where the frozen frames came closest.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter, defaultdict
from contextlib import nullcontext

import gymnasium as gym
import numpy as np
import torch
from tqdm import tqdm

import detaug_gym  # noqa: F401  (registers the envs)
from detaug_gym.augment.segment import segment_gripper
from detaug_gym.envs.suites import NUM_INIT_STATES, OFFICIAL_ID_VERSION, SUITES
from detaug_gym.geometry import held_object, obstacle_sdf, robot_clearance
from detaug_gym.policies.base import make_policy
from detaug_gym.report import markdown
from detaug_gym.rollout import Hook, Step, rollout


class FrameClearance(Hook):
    """Per frame, the robot's and the held object's clearance (m) to the obstacle as it stood at the reset,
    and the executed gripper command."""

    def on_start(self, env, obs: dict[str, np.ndarray], info: dict) -> None:
        self._sdf = obstacle_sdf(obs)
        self.robot: list[float] = []
        self.held: list[float] = []  # inf while nothing is held
        self.commands: list[float] = []
        self._frame(obs)

    def on_step(self, step: Step) -> None:
        self.commands.append(float(step.sent[-1]))
        self._frame(step.next_obs)

    def _frame(self, obs: dict[str, np.ndarray]) -> None:
        with torch.no_grad():
            self.robot.append(float(robot_clearance(np.asarray(obs["robot_joint_pos"], np.float64), obs, self._sdf)))
            points = held_object(obs)
            self.held.append(np.inf if points is None else float(
                self._sdf(torch.as_tensor(points + np.asarray(obs["eef_pos"], np.float64))).min()))

    def summary(self) -> dict:
        """Least clearance (robot and held object together) of the frozen and of the bent frames, and of each
        phase's frozen frames (a margin counts in the transit it ends or starts: approach, carry)."""
        clearance = np.minimum(self.robot, self.held)[1:]  # frame t + 1: after command t
        seg = segment_gripper(np.asarray(self.commands))
        frozen = seg.frozen_mask()
        frozen_phases: dict[str, float] = defaultdict(lambda: np.inf)  # least clearance of a phase's frozen frames
        for t in np.flatnonzero(frozen):
            phase = seg.phase(int(t))
            frozen_phases[phase] = min(frozen_phases[phase], float(clearance[t]))
        least = {name: float(clearance[mask].min()) if mask.any() else np.inf
                 for name, mask in (("frozen", frozen), ("bent", ~frozen))}
        return {"frozen": least["frozen"], "bent": least["bent"], "frozen_phases": dict(frozen_phases)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    libero = [name for name in SUITES if name != "newton"]
    parser.add_argument("--suite", default="spatial", help=f"a LIBERO suite: {', '.join(libero)}")
    parser.add_argument("--levels", nargs="+", default=["L1", "L2"], help="obstacle levels: L1 and/or L2")
    parser.add_argument("--episodes", type=int, default=12, help="episodes per task and level")
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--scenarios", choices=("procedural", "official"), default="procedural",
                        help="procedural (default) or SafeLIBERO's official episodes (needs $SAFELIBERO_ROOT)")
    parser.add_argument("--margin", type=float, default=0.015, help="m; DetAug's inflate (default 0.015)")
    parser.add_argument("--out", help="also write one JSON line per episode here")
    args = parser.parse_args()
    if args.suite not in libero:
        parser.error(f"--suite {args.suite!r}: valid are {', '.join(libero)}")
    if args.episodes < 1:
        parser.error(f"--episodes {args.episodes}: give a positive count")
    if args.scenarios == "official" and args.episodes > NUM_INIT_STATES:
        parser.error(f"--episodes {args.episodes}: SafeLIBERO has {NUM_INIT_STATES} episodes per task and level")
    bad = [level for level in args.levels if level not in ("L1", "L2")]
    if bad:
        parser.error(f"--levels {' '.join(bad)}: valid are L1 and L2 (the obstacle levels)")
    suite = SUITES[args.suite]
    policy = make_policy("scripted", suite=args.suite)  # rollout resets it with each episode's seed
    rows = []
    with open(args.out, "w") if args.out else nullcontext() as out:
        for level in args.levels:
            tasks, official = len(suite.tasks_for(level)), args.scenarios == "official"
            env = (gym.make(suite.env_id(level, OFFICIAL_ID_VERSION), scenarios="official") if official
                   else gym.make(suite.env_id(level)))
            cells: dict[int, list[dict]] = defaultdict(list)
            for i in tqdm(range(args.episodes * tasks), desc=f"expert {args.suite} {level}", unit="ep"):
                task, hook = i % tasks, FrameClearance()
                options = {"task": task, **({"episode": i // tasks} if official else {})}
                result = rollout(env, policy, seed=args.seed + i, options=options, hooks=[hook])
                record = {"level": level, "task": task, "seed": args.seed + i,
                          "success": bool(result.info["is_success"]), **hook.summary()}
                cells[task].append(record)
                if out:
                    out.write(json.dumps(record, default=lambda v: None) + "\n")
                    out.flush()
            env.close()
            rows += [_row(level, task, cells[task], args.margin) for task in sorted(cells)]
    episodes = (f"SafeLIBERO's episodes 0-{args.episodes - 1}" if args.scenarios == "official"
                else f"reset seeds {args.seed}..")
    print(f"\nscripted expert on {args.suite} {' '.join(args.levels)} ({args.scenarios}), {args.episodes} episodes "
          f"per cell ({episodes}); clearance to the obstacle as it stood at the reset, DetAug's geometry\n")
    header = ["level", "task", "episodes", "expert success", f"frozen <= 0 / < {args.margin * 100:g} cm",
              f"bent <= 0 / < {args.margin * 100:g} cm", "frozen frames' closest phase"]
    print(markdown(header, rows))


def _row(level: str, task: int, records: list[dict], margin: float) -> list[str]:
    """One table row from one cell's episodes."""
    def counts(key: str) -> str:
        return f"{sum(r[key] <= 0 for r in records)} / {sum(r[key] < margin for r in records)}"

    closest = Counter(min(r["frozen_phases"], key=r["frozen_phases"].get) for r in records if r["frozen"] < margin)
    return [level, str(task), str(len(records)), str(sum(r["success"] for r in records)), counts("frozen"),
            counts("bent"), ", ".join(f"{p} {n}" for p, n in closest.most_common()) or "-"]


if __name__ == "__main__":
    main()
