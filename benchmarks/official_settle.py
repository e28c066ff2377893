"""How the official SafeLIBERO episodes settle on this MuJoCo (run by hand; needs ``SAFELIBERO_ROOT``).

    python benchmarks/official_settle.py                         # all 1,600 episodes, both settle modes
    python benchmarks/official_settle.py --suites spatial --episodes 10 --settle steps

Per (suite, level): for every episode, reset (the official state, then the settle), record how far the active
obstacle ended from where the state put it (xy, m), then hold the robot still for ``--hold`` no-op steps and
count the episodes the collision rule flags although nothing moved the obstacle (a spurious collision), and
how many episodes had an obstacle or base lifted out of its support before the settle.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
from tqdm import tqdm

import detaug_gym  # noqa: F401
from detaug_gym.envs.scene import SETTLE_ACTION
from detaug_gym.envs.suites import SUITES


def scan(suite: str, level: str, episodes: int, settle: str, hold: int) -> dict:
    spec = SUITES[suite]
    drift, spurious, moved_1cm = [], 0, 0
    for task in range(len(spec.tasks_for(level))):
        env = gym.make(spec.env_id(level), scenarios="official", task=task, settle=settle)
        base = env.unwrapped
        states = base.init_states(task)
        for episode in range(episodes):
            _, info = env.reset(options={"episode": episode})
            scene = base.scene
            body = scene.obstacles[info["obstacle"]].body_id
            qpos = 1 + scene.model.jnt_qposadr[scene.model.body_jntadr[body]]  # the free joint in the flat state
            official_xy = states[episode][qpos:qpos + 2]
            d = float(np.linalg.norm(scene.data.xpos[body][:2] - official_xy))
            drift.append(d)
            moved_1cm += d > 0.01
            for _ in range(hold):
                _, _, _, _, info = base.step(SETTLE_ACTION)
            spurious += bool(info["collision"])
        env.close()
    return {"episodes": len(drift), "mean_xy_drift": float(np.mean(drift)), "max_xy_drift": float(np.max(drift)),
            "moved_over_1cm": int(moved_1cm), "spurious_collisions": int(spurious)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suites", nargs="+", default=["spatial", "object", "goal", "long"])
    parser.add_argument("--levels", nargs="+", default=["L1", "L2"])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--settle", nargs="+", default=["steps", "still"])
    parser.add_argument("--hold", type=int, default=50, help="no-op steps after the settle")
    args = parser.parse_args()
    rows = []
    cells = [(s, lv, m) for m in args.settle for s in args.suites for lv in args.levels]
    for suite, level, settle in tqdm(cells, desc="cells"):
        rows.append((suite, level, settle, scan(suite, level, args.episodes, settle, args.hold)))
    print(f"\n| suite | level | settle | episodes | mean xy drift (mm) | max (mm) | > 1 cm | spurious collisions "
          f"in {args.hold} no-op steps |")
    print("|---|---|---|---|---|---|---|---|")
    for suite, level, settle, r in rows:
        print(f"| {suite} | {level} | {settle} | {r['episodes']} | {1000 * r['mean_xy_drift']:.1f} | "
              f"{1000 * r['max_xy_drift']:.1f} | {r['moved_over_1cm']} | {r['spurious_collisions']} |")
    for settle in args.settle:
        total = sum(r["spurious_collisions"] for _, _, m, r in rows if m == settle)
        moved = sum(r["moved_over_1cm"] for _, _, m, r in rows if m == settle)
        n = sum(r["episodes"] for _, _, m, r in rows if m == settle)
        print(f"settle={settle}: {total} / {n} spurious collisions, {moved} / {n} obstacles more than 1 cm from "
              "the official xy")


if __name__ == "__main__":
    main()
