"""Time the shared collision geometry on CPU: FK, robot points, SDF and plan costs for K plans x H steps.

    python benchmarks/geometry_cost.py                      # K = 1, 8, 32, 64; H = 50; float32
    python benchmarks/geometry_cost.py --threads 1 --dtype float64
    python benchmarks/geometry_cost.py --threads 1 --clock cpu   # steadier on a busy machine

The scene: robosuite's Panda, a 10 x 10 x 16 cm box standing where the hand sweeps through, and K plans
that swing the arm across it (about half of the plan steps near or inside the box), so the culled cost
has real work to do. Prints the median of ``--repeats`` runs in ms.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
import trimesh

from detaug_gym.geometry import RobotGeometry, obstacle_sdf, penetration_cost, plan_collision_cost

HOME = np.array([0.0, -0.17, 0.0, -2.42, 0.0, 2.2, 0.8])


CLOCK = time.perf_counter


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        start = CLOCK()
        fn()
        times.append(CLOCK() - start)
    return 1e3 * float(np.median(times))


def box_observation(robot: RobotGeometry) -> dict[str, np.ndarray]:
    centre = robot.kinematics(torch.tensor(HOME + [0.4, 0, 0, 0, 0, 0, 0])).eef_position.numpy()
    mesh = trimesh.creation.box(extents=[0.1, 0.1, 0.16])
    points, _ = trimesh.sample.sample_surface(mesh, 256, seed=0)
    return {"obstacle_points": points + centre, "obstacle_pose": np.r_[centre, 0.0, 0.0, 0.0, 1.0],
            "obstacle_size": np.array([0.05, 0.05, 0.08]), "obstacle_mask": np.ones(1),
            "gripper_qpos": np.array([0.04, -0.04])}


def sweeping_plans(k: int, horizon: int, dtype: torch.dtype, seed: int = 0) -> torch.Tensor:
    """(k, horizon, 7): joint 1 sweeps 0 -> 0.8 rad through the box, other joints jittered per plan."""
    rng = np.random.default_rng(seed)
    plans = np.tile(HOME, (k, horizon, 1))
    plans[..., 0] += np.linspace(0.0, 0.8, horizon)
    plans[..., 1:] += rng.normal(0.0, 0.1, (k, 1, 6))
    return torch.tensor(plans, dtype=dtype)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ks", type=int, nargs="+", default=[1, 8, 32, 64])
    parser.add_argument("--horizon", type=int, default=50)
    parser.add_argument("--points", type=int, default=300)
    parser.add_argument("--dtype", choices=["float32", "float64"], default="float32")
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: leave torch's default)")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--clock", choices=["wall", "cpu"], default="wall",
                        help="cpu: this process's CPU time, steadier on a shared machine (use with --threads 1)")
    args = parser.parse_args()
    global CLOCK
    CLOCK = time.process_time if args.clock == "cpu" else time.perf_counter
    if args.threads:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    robot = RobotGeometry.panda(num_points=args.points)
    obs = box_observation(robot)
    start = time.perf_counter()
    sdf = obstacle_sdf(obs)
    print(f"bake {1e3 * (time.perf_counter() - start):.0f} ms, grid {sdf.grid.values.shape}, "
          f"torch threads {torch.get_num_threads()}, {args.dtype}, {len(robot.points)} robot points, "
          f"{args.clock} clock")
    print("| K | FK | penetration | clearance | spheres | penetration fwd+bwd | all points (ref) | hit plans |")
    print("|---|---|---|---|---|---|---|---|")
    for k in args.ks:
        row, hits = time_one_batch(robot, obs, sdf, sweeping_plans(k, args.horizon, dtype), args.repeats)
        print(f"| {k} | " + " | ".join(f"{ms:.1f}" for ms in row) + f" | {hits}/{k} |")


def time_one_batch(robot: RobotGeometry, obs: dict[str, np.ndarray], sdf, plans: torch.Tensor,
                   repeats: int) -> tuple[list[float], int]:
    """Median ms of FK, the three plan costs, penetration forward+backward and the all-points reference."""
    fingers = torch.tensor(obs["gripper_qpos"], dtype=plans.dtype)
    grad_plans = plans.clone().requires_grad_(True)
    row = [median_ms(lambda: robot.kinematics(plans, fingers), repeats)]
    for kind in ("penetration", "clearance", "spheres"):
        row.append(median_ms(lambda kind=kind: plan_collision_cost(plans, obs, robot, kind=kind, sdf=sdf), repeats))
    row.append(median_ms(lambda: plan_collision_cost(grad_plans, obs, robot, sdf=sdf).sum().backward(), repeats))
    row.append(median_ms(lambda: penetration_cost(robot.surface_points(plans, fingers), sdf), max(3, repeats // 5)))
    hits = int((plan_collision_cost(plans, obs, robot, sdf=sdf) > 0).sum())
    return row, hits

if __name__ == "__main__":
    main()
