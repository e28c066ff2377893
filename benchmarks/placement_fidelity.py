"""Official SafeLIBERO scenarios beside our procedural ones, per (suite, level) (run by hand; needs SAFELIBERO_ROOT).

    python benchmarks/placement_fidelity.py                              # 50 official + 50 procedural per cell
    python benchmarks/placement_fidelity.py --suites spatial --episodes 10
    python benchmarks/placement_fidelity.py --version 0                  # the -v0 scenarios instead of -v1
    python benchmarks/placement_fidelity.py --anchors                    # the official spots per task (calibration)

For every settled episode (after the reset's settle, before any action) it measures, as the issue's comparison
did: the gap between the obstacle's and the pick object's xy footprints (0 when they overlap), the obstacle's
top above the table under it (under its base when raised), whether it stands raised on a base or pedestal, whether
its footprint crosses the straight pick -> place segment, and the obstacle types. Official episodes are
SafeLIBERO's (episode ``i // 4`` of task ``i mod 4``); procedural ones are the bench's seeds for the same cells.
Gap and path are measured to the task's first pick-place step. The goal (issue #22, part 2): per cell within 2 cm
on mean gap and 3 cm on mean top height, the same type set, path-crossing share within 15 points.

``--anchors`` prints, per (suite, level, task), what :mod:`detaug_gym.envs.calibration` holds: the official
obstacle types and base, and where the obstacle's centre stands relative to the first pick-place step: along the
pick -> place path as a fraction of its length, and beside it in metres (medians over all 50 official episodes).
"""

from __future__ import annotations

import argparse
from collections import Counter

import gymnasium as gym
import mujoco
import numpy as np
from tqdm import tqdm

import detaug_gym  # noqa: F401
from detaug_gym.envs.suites import SUITES
from detaug_gym.seeds import bench_episode_seed

COLLISION_GROUP = np.array([1, 0, 0, 0, 0, 0], np.uint8)  # robosuite/LIBERO collision geoms are group 0


def _crosses(lo: np.ndarray, hi: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the segment a -> b (xy) meets the box [lo, hi] (slab test)."""
    t0, t1 = 0.0, 1.0
    d = b - a
    for k in range(2):
        if abs(d[k]) < 1e-12:
            if not lo[k] <= a[k] <= hi[k]:
                return False
            continue
        u, v = sorted(((lo[k] - a[k]) / d[k], (hi[k] - a[k]) / d[k]))
        t0, t1 = max(t0, u), min(t1, v)
    return t0 <= t1


def _gap(lo1, hi1, lo2, hi2) -> float:
    return float(np.linalg.norm(np.maximum(0.0, np.maximum(lo1 - hi2, lo2 - hi1))))


def _table_below(scene, xy: np.ndarray, obstacle: int, raised: bool) -> float:
    """Height of the surface under the obstacle at ``xy``: a downward ray that passes through the obstacle and,
    when it is raised, through the base or pedestal it stands on (the first thing under it)."""
    m = scene.model
    geom = np.zeros(1, np.int32)
    down = np.array([0.0, 0.0, -1.0])
    skip = set(scene.subtree_bodies(obstacle).tolist())
    z, exclude, bases_left = 3.0, -1, int(raised)
    for _ in range(50):
        dist = mujoco.mj_ray(m, scene.data, np.array([xy[0], xy[1], z]), down, COLLISION_GROUP, 1, exclude, geom)
        if dist < 0:
            return 0.0  # nothing below: the floor plane
        body = int(m.geom_bodyid[geom[0]])
        if body not in skip and not scene.robot_geom[geom[0]]:
            if not bases_left:
                return float(z - dist)
            bases_left -= 1
            skip |= set(scene.subtree_bodies(body).tolist())
        z, exclude = z - dist - 1e-4, body  # on from just below the hit
    raise RuntimeError(f"no surface below {xy}")


def measure(env, info: dict) -> dict:
    """The statistics of the episode ``env`` was just reset to."""
    base = env.unwrapped
    scene = base.scene
    body = scene.obstacles[info["obstacle"]].body_id
    o_lo, o_hi = scene.world_aabb(scene.subtree_bodies(body))
    problem = base.placement_problem(step=0)
    centre = 0.5 * (o_lo[:2] + o_hi[:2])
    axis = problem.place.center - problem.pick.center
    rel = centre - problem.pick.center
    length = float(np.linalg.norm(axis))
    unit = axis / length
    return {
        "along": float(rel @ unit / length),
        "lateral": float(rel @ np.array([-unit[1], unit[0]])),
        "base": next((b for b in ("box_small_base", "box_base") if any(
            b in (mujoco.mj_id2name(scene.model, mujoco.mjtObj.mjOBJ_BODY, int(scene.model.geom_bodyid[g])) or "")
            for g in base._support_geoms)), None),
        "gap": _gap(o_lo[:2], o_hi[:2], problem.pick.lo, problem.pick.hi),
        "top": float(o_hi[2] - _table_below(scene, 0.5 * (o_lo[:2] + o_hi[:2]), body, info["obstacle_raised"])),
        "raised": bool(info["obstacle_raised"]),
        "crosses": _crosses(o_lo[:2], o_hi[:2], problem.pick.center, problem.place.center),
        "type": info["obstacle"],
    }


def cell_rows(suite: str, level: str, episodes: int, official: bool, version: int | None = None) -> list[dict]:
    """One :func:`measure` row per episode (with its ``task``)."""
    spec = SUITES[suite]
    n_tasks = len(spec.tasks_for(level))
    kwargs = {"scenarios": "official"} if official else {}
    env = gym.make(spec.env_id(level, version), **kwargs)
    rows = []
    for i in range(episodes):
        options = {"task": i % n_tasks}
        if official:
            options["episode"] = (i // n_tasks) % 50
        _, info = env.reset(seed=bench_episode_seed(0, suite, level, i), options=options)
        rows.append(measure(env, info) | {"task": i % n_tasks})
    env.close()
    return rows


def cell_stats(suite: str, level: str, episodes: int, official: bool, version: int | None = None) -> dict:
    rows = cell_rows(suite, level, episodes, official, version)
    return {
        "gap": float(np.mean([r["gap"] for r in rows])),
        "top": float(np.mean([r["top"] for r in rows])),
        "raised": float(np.mean([r["raised"] for r in rows])),
        "crosses": float(np.mean([r["crosses"] for r in rows])),
        "types": Counter(r["type"] for r in rows),
    }


def print_anchors(cells: list[tuple[str, str]]) -> None:
    """The official obstacle spot of every task: types, base, mean position along the pick -> place path (as a
    fraction of its length) and beside it (m, to the left) over its 50 episodes."""
    print("| cell | task | types | base | along (fraction) | lateral (m) |\n|---|---|---|---|---|---|")
    for suite, level in tqdm(cells, desc="cells"):
        n_tasks = len(SUITES[suite].tasks_for(level))
        rows = cell_rows(suite, level, 50 * n_tasks, official=True)
        for task in range(n_tasks):
            mine = [r for r in rows if r["task"] == task]
            print(f"| {suite} {level} | {task} | {', '.join(Counter(r['type'] for r in mine))} | "
                  f"{Counter(r['base'] for r in mine).most_common(1)[0][0]} | "
                  f"{np.median([r['along'] for r in mine]):.2f} | {np.median([r['lateral'] for r in mine]):.3f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suites", nargs="+", default=["spatial", "object", "goal", "long"])
    parser.add_argument("--levels", nargs="+", default=["L1", "L2"])
    parser.add_argument("--episodes", type=int, default=50, help="episodes per cell and kind")
    parser.add_argument("--version", type=int, default=None, help="procedural scenario version (default current)")
    parser.add_argument("--anchors", action="store_true", help="print the official spots per task and stop")
    args = parser.parse_args()
    cells = [(s, lv) for s in args.suites for lv in args.levels]
    if args.anchors:
        print_anchors(cells)
        return
    results = {}
    for suite, level in tqdm(cells, desc="cells"):
        results[(suite, level)] = [cell_stats(suite, level, args.episodes, official, None if official else args.version)
                                   for official in (True, False)]
    print("\n| cell | gap official / ours (m) | top official / ours (m) | raised official / ours | "
          "crosses path official / ours | types official | types ours | goal met |")
    print("|---|---|---|---|---|---|---|---|")
    met = 0
    for (suite, level), (off, ours) in results.items():
        ok = (abs(off["gap"] - ours["gap"]) <= 0.02 and abs(off["top"] - ours["top"]) <= 0.03
              and set(off["types"]) == set(ours["types"]) and abs(off["crosses"] - ours["crosses"]) <= 0.15)
        met += ok
        print(f"| {suite} {level} | {off['gap']:.3f} / {ours['gap']:.3f} | {off['top']:.3f} / {ours['top']:.3f} | "
              f"{off['raised']:.0%} / {ours['raised']:.0%} | {off['crosses']:.0%} / {ours['crosses']:.0%} | "
              f"{', '.join(sorted(off['types']))} | {', '.join(sorted(ours['types']))} | {'yes' if ok else 'no'} |")
    print(f"{met} of {len(results)} cells meet the goal (gap within 2 cm, top within 3 cm, same types, "
          "path crossing within 15 points)")


if __name__ == "__main__":
    main()
