"""Official SafeLIBERO scenarios beside our procedural ones, per (suite, level) (run by hand; needs SAFELIBERO_ROOT).

    python benchmarks/placement_fidelity.py                # every official episode + 200 procedural per cell
    python benchmarks/placement_fidelity.py --suites spatial --episodes 20 --official-episodes 20
    python benchmarks/placement_fidelity.py --version 0                  # the -v0 scenarios instead of -v2
    python benchmarks/placement_fidelity.py --anchors                    # the official spots per task (calibration)
    python benchmarks/placement_fidelity.py --calibrate                  # write version 2's calibration file

For every settled episode (after the reset's settle, before any action) it measures, as the issue's comparison
did: the gap between the obstacle's and the pick object's xy footprints (0 when they overlap), the obstacle's
top above the table under what it stands on (under its base's centre when raised: a book on its edge overhangs its
base), whether it stands raised on a base or pedestal, whether its footprint crosses the straight pick -> place
segment, and the obstacle types. Official episodes are SafeLIBERO's (episode ``i // 4`` of task ``i mod 4``; all 50
per task by default, so the official side is its whole population); procedural ones are the bench's seeds for the
same cells. An episode whose object to pick is not on the table (more than :data:`OFF_TABLE` from its centre) is
broken: it is counted and left out of the means (one official episode is).
Gap and path are measured to the task's first pick-place step. The goal (issue #22, part 2): per cell within 2 cm
on mean gap and 3 cm on mean top height, the same type set, path-crossing share within 15 points.

``--anchors`` prints, per (suite, level, task), what :mod:`detaug_gym.envs.calibration` holds: the official
obstacle types and base, and where the obstacle's centre stands relative to the first pick-place step: along the
pick -> place path as a fraction of its length, and beside it in metres (medians over all 50 official episodes).

``--calibrate`` measures what version 2 (the ``-v2`` ids) holds and writes it to
``detaug_gym/envs/calibration_v2.json``: per (suite, level, task) one anchor per official obstacle type (its number
of episodes, base, and median spot as above), and SafeLIBERO's scene edits, read from the init states of both
kinds (official and LIBERO's, loaded without settling): every object whose median xy differs by more than
:data:`EDIT_MIN` (moved by that difference), every object SafeLIBERO parks off the table in most episodes or
does not declare (removed), and every fixture whose compiled xy differs by more than :data:`EDIT_MIN` (moved).
"""

from __future__ import annotations

import argparse
import datetime
import json
from collections import Counter
from pathlib import Path

import gymnasium as gym
import mujoco
import numpy as np
from tqdm import tqdm

import detaug_gym  # noqa: F401
from detaug_gym.envs.official import is_obstacle_category
from detaug_gym.envs.suites import SUITES
from detaug_gym.seeds import bench_episode_seed

COLLISION_GROUP = np.array([1, 0, 0, 0, 0, 0], np.uint8)  # robosuite/LIBERO collision geoms are group 0
OFF_TABLE = 1.0  # m: an object to pick farther than this from the table's centre (x or y) is not on the table
EDIT_MIN = 0.01  # m: smaller differences between SafeLIBERO's and LIBERO's layouts are not edits
CALIBRATION = Path(__file__).resolve().parents[1] / "detaug_gym" / "envs" / "calibration_v2.json"


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


def _table_below(scene, xy: np.ndarray, skip: set[int]) -> float:
    """Height of the first surface under ``xy`` that is not one of the ``skip`` bodies (the obstacle and what
    it stands on) nor the robot: a downward ray."""
    m = scene.model
    geom = np.zeros(1, np.int32)
    down = np.array([0.0, 0.0, -1.0])
    z, exclude = 3.0, -1
    for _ in range(50):
        dist = mujoco.mj_ray(m, scene.data, np.array([xy[0], xy[1], z]), down, COLLISION_GROUP, 1, exclude, geom)
        if dist < 0:
            return 0.0  # nothing below: the floor plane
        body = int(m.geom_bodyid[geom[0]])
        if body not in skip and not scene.robot_geom[geom[0]]:
            return float(z - dist)
        z, exclude = z - dist - 1e-4, body  # on from just below the hit
    raise RuntimeError(f"no surface below {xy}")


def measure(env, info: dict) -> dict:
    """The statistics of the episode ``env`` was just reset to."""
    base = env.unwrapped
    scene = base.scene
    body = scene.obstacles[info["obstacle"]].body_id
    o_lo, o_hi = scene.world_aabb(scene.subtree_bodies(body))
    # The table is measured under what the obstacle stands on: its base or pedestal when raised (an obstacle
    # that overhangs its base, like a book on its edge, has no base under its own centre).
    supports = sorted({int(scene.model.geom_bodyid[g]) for g in base._support_geoms})
    skip = {int(b) for s in (body, *supports) for b in scene.subtree_bodies(s)}
    under = scene.data.xpos[supports[0]][:2] if supports else 0.5 * (o_lo[:2] + o_hi[:2])
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
        "top": float(o_hi[2] - _table_below(scene, under, skip)),
        "raised": bool(info["obstacle_raised"]),
        "crosses": _crosses(o_lo[:2], o_hi[:2], problem.pick.center, problem.place.center),
        "type": info["obstacle"],
        # A broken episode: the object to pick is not on the table (SafeLIBERO's Goal L1 drawer task has one, 5 m out).
        "broken": bool(np.any(np.abs(problem.pick.center) > OFF_TABLE)),
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
    """Means over the cell's episodes, leaving out (and counting) the broken ones."""
    every = cell_rows(suite, level, episodes, official, version)
    rows = [r for r in every if not r["broken"]]
    return {
        "n": len(every),
        "broken": len(every) - len(rows),
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


def _layout(env, task: int) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """xyz of every free object in each of the task's init states (``name -> (50, 3)``), loaded without settling,
    and the xy of every fixture (``name -> (2,)``)."""
    base = env.unwrapped
    states = base.init_states(task)
    scene = base.scene_for(task)
    sim = scene.sim_env
    names = [n for n, o in sim.objects_dict.items()
             if not (n.startswith("obstacle_") or is_obstacle_category(o.category_name))]
    xyz = {n: [] for n in names}
    for state in states:
        scene.set_state(state)
        mujoco.mj_forward(scene.model, scene.data)
        for n in names:
            xyz[n].append(scene.data.xpos[scene.body_id(n)].copy())
    fixtures = {n: scene.data.xpos[scene.body_id(n)][:2].copy() for n in sim.fixtures_dict}
    return {n: np.array(v) for n, v in xyz.items()}, fixtures


def scene_edits(suite: str, level: str, task: int) -> dict:
    """SafeLIBERO's edits of the task's LIBERO scene (see ``--calibrate``)."""
    spec = SUITES[suite]
    official = gym.make(spec.env_id(level), task=task, scenarios="official")
    libero = gym.make(spec.env_id(level, version=1), task=task)  # LIBERO's layout, unedited
    (off, off_fix), (ours, our_fix) = _layout(official, task), _layout(libero, task)
    official.close()
    libero.close()
    moved, removed = {}, []
    for name, xyz in ours.items():
        if name not in off:
            removed.append(name)
            continue
        parked = (np.abs(off[name][:, 0]) > 0.5) | (np.abs(off[name][:, 1]) > 0.5) | (off[name][:, 2] < 0)
        if parked.mean() > 0.5:
            removed.append(name)
            continue
        shift = np.median(off[name][~parked, :2], axis=0) - np.median(xyz[:, :2], axis=0)
        if np.linalg.norm(shift) > EDIT_MIN:
            moved[name] = [round(float(v), 3) for v in shift]
    fixtures = {n: [round(float(v), 3) for v in off_fix[n] - xy] for n, xy in our_fix.items()
                if n in off_fix and np.linalg.norm(off_fix[n] - xy) > EDIT_MIN}
    return {"moved": moved, "fixtures": fixtures, "removed": sorted(removed)}


def calibrate(cells: list[tuple[str, str]]) -> dict:
    """Version 2's calibration of ``cells`` (see ``--calibrate``)."""
    out = {}
    for suite, level in tqdm(cells, desc="cells"):
        n_tasks = len(SUITES[suite].tasks_for(level))
        rows = [r for r in cell_rows(suite, level, 50 * n_tasks, official=True) if not r["broken"]]
        tasks = []
        for task in range(n_tasks):
            mine = [r for r in rows if r["task"] == task]
            anchors = []
            for kind, count in Counter(r["type"] for r in mine).items():
                of_kind = [r for r in mine if r["type"] == kind]
                anchors.append({"type": kind, "weight": count,
                                "base": Counter(r["base"] for r in of_kind).most_common(1)[0][0],
                                "along": round(float(np.median([r["along"] for r in of_kind])), 3),
                                "lateral": round(float(np.median([r["lateral"] for r in of_kind])), 3)})
            tasks.append({"anchors": anchors, **scene_edits(suite, level, task)})
        out[f"{suite} {level}"] = tasks
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suites", nargs="+", default=["spatial", "object", "goal", "long"])
    parser.add_argument("--levels", nargs="+", default=["L1", "L2"])
    parser.add_argument("--episodes", type=int, default=200, help="procedural episodes per cell")
    parser.add_argument("--official-episodes", type=int, default=None,
                        help="official episodes per cell (default: all, 50 per task)")
    parser.add_argument("--version", type=int, default=None, help="procedural scenario version (default current)")
    parser.add_argument("--anchors", action="store_true", help="print the official spots per task and stop")
    parser.add_argument("--calibrate", action="store_true", help=f"write version 2's calibration to {CALIBRATION}")
    args = parser.parse_args()
    cells = [(s, lv) for s in args.suites for lv in args.levels]
    if args.anchors:
        print_anchors(cells)
        return
    if args.calibrate:
        old = json.loads(CALIBRATION.read_text())["cells"] if CALIBRATION.exists() else {}
        data = {"measured": datetime.date.today().isoformat(),
                "command": "SAFELIBERO_ROOT=... python benchmarks/placement_fidelity.py --calibrate",
                "cells": old | calibrate(cells)}
        CALIBRATION.write_text(json.dumps(data, indent=1) + "\n")
        print(f"wrote {CALIBRATION}")
        return
    results = {}
    for suite, level in tqdm(cells, desc="cells"):
        n_official = args.official_episodes or 50 * len(SUITES[suite].tasks_for(level))
        results[(suite, level)] = [cell_stats(suite, level, n_official if official else args.episodes, official,
                                              None if official else args.version) for official in (True, False)]
    print("\n| cell | episodes official / ours (broken, left out) | gap official / ours (m) | top official / ours (m) "
          "| raised official / ours | crosses path official / ours | types official | types ours | goal met |")
    print("|---|---|---|---|---|---|---|---|---|")
    met = 0
    for (suite, level), (off, ours) in results.items():
        ok = (abs(off["gap"] - ours["gap"]) <= 0.02 and abs(off["top"] - ours["top"]) <= 0.03
              and set(off["types"]) == set(ours["types"]) and abs(off["crosses"] - ours["crosses"]) <= 0.15)
        met += ok
        print(f"| {suite} {level} | {off['n']} ({off['broken']}) / {ours['n']} ({ours['broken']}) | "
              f"{off['gap']:.3f} / {ours['gap']:.3f} | {off['top']:.3f} / {ours['top']:.3f} | "
              f"{off['raised']:.0%} / {ours['raised']:.0%} | {off['crosses']:.0%} / {ours['crosses']:.0%} | "
              f"{', '.join(sorted(off['types']))} | {', '.join(sorted(ours['types']))} | {'yes' if ok else 'no'} |")
    print(f"{met} of {len(results)} cells meet the goal (gap within 2 cm, top within 3 cm, same types, "
          "path crossing within 15 points)")


if __name__ == "__main__":
    main()
