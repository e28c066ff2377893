"""How far DetAug's scorer geometry is from the simulator's, near the obstacle (run by hand).

    python benchmarks/scorer_fidelity.py                 # 40 Spatial L2 episodes of the obstacle-blind expert
    python benchmarks/scorer_fidelity.py --episodes 10 --points 300 1000

The scripted expert ignores the obstacle, so on L2 it passes close to it. At every step before the first
collision it compares

- the robot: the env's exact robot-to-obstacle distance (``info["min_clearance"]``, MuJoCo's narrow phase on the
  collision geoms) with the scorer's (:func:`detaug_gym.geometry.robot_clearance`: the obstacle SDF at the robot's
  surface points), for each robot point count, at steps where the exact distance is below 4 cm;
- the held object: the exact distance from the object in the hand to the obstacle with the scorer's (the SDF at
  the object's observed surface points, :func:`detaug_gym.geometry.held_object`), below 6 cm.

Positive errors mean the scorer sees more room than there is: a plan that grazes the obstacle by less than that
scores zero. DetAug's ``inflate`` option is set from these numbers.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import mujoco
import numpy as np
import torch
from tqdm import tqdm

import detaug_gym  # noqa: F401
from detaug_gym.geometry import RobotGeometry, held_object, obstacle_sdf, robot_clearance
from detaug_gym.policies import make_policy


def _report(name: str, errors: list[float]) -> None:
    e = np.asarray(errors)
    if not e.size:
        print(f"{name}: no samples")
        return
    print(f"{name}: scorer - exact (cm): median {100 * np.median(e):+.2f}, p90 {100 * np.percentile(e, 90):+.2f}, "
          f"max {100 * e.max():+.2f}, min {100 * e.min():+.2f} (n={e.size})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--points", type=int, nargs="+", default=[300, 1000, 3000])
    parser.add_argument("--env", default="SafeLibero-Spatial-L2-v2", help="a registered SafeLibero L1/L2 id")
    args = parser.parse_args()
    env = gym.make(args.env)
    expert = make_policy("scripted", suite="spatial")
    robots = {n: RobotGeometry.panda(num_points=n) for n in args.points}
    robot_err: dict[int, list[float]] = {n: [] for n in args.points}
    held_err: list[float] = []
    fromto = np.zeros(6)
    for episode in tqdm(range(args.episodes), desc="episodes"):
        obs, info = env.reset(seed=episode, options={"task": episode % 4})
        expert.reset(seed=episode)
        scene = env.unwrapped.scene
        obstacle = scene.obstacles[info["obstacle"]].geom_ids
        pick = int(scene.model.body_rootid[scene.body_id(scene.pick_places[0].obj)])
        pick_geoms = scene.collision_geoms(pick)
        for _ in range(300):
            obs, _, terminated, truncated, info = env.step(expert.act(obs))
            if terminated or truncated or info["collision"]:
                break
            sdf = None
            if info["min_clearance"] < 0.04:
                sdf = obstacle_sdf(obs)
                q = torch.as_tensor(obs["robot_joint_pos"], dtype=torch.float64)
                for n, robot in robots.items():
                    model = float(robot_clearance(q, obs, sdf, robot.aligned_to(obs)))
                    robot_err[n].append(model - info["min_clearance"])
            held = held_object(obs)
            if held is None:
                continue
            exact = min(mujoco.mj_geomDistance(scene.model, scene.data, int(a), int(b), 0.2, fromto)
                        for a in pick_geoms for b in obstacle)
            if exact < 0.06:
                sdf = sdf or obstacle_sdf(obs)
                points = torch.as_tensor(held + obs["eef_pos"], dtype=torch.float64)
                held_err.append(float(sdf(points).min()) - exact)
    for n in args.points:
        _report(f"robot, {n} surface points", robot_err[n])
    _report("held object, its observed surface points", held_err)


if __name__ == "__main__":
    main()
