"""Measure where obstacles land in every SafeLibero suite and write the suite cards (run by hand).

    python benchmarks/placement_stats.py --seeds 10            # all suites, 10 resets per task and level
    python benchmarks/placement_stats.py --suites spatial --seeds 25

For each (suite, level, task) it resets the env over ``--seeds`` seeds and records the obstacle's gap to
the pick object's footprint, its centre distance to the pick object, its distance to the motion-path
segment it was put on, the pedestal, the relaxation round and the robot's clearance to it at the start.
Writes ``envs/<suite>/README.md`` (task list, step limit, placement rules, measured table).
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import gymnasium as gym
import numpy as np

import detaug_gym  # noqa: F401
from detaug_gym.envs.placement import L1_GAP, L2_LATERAL, TRANSIT_HEIGHT, distance_to_segment, footprint_gap
from detaug_gym.envs.suites import SUITES

ROOT = Path(__file__).resolve().parents[1]


def measure(suite: str, level: str, seeds: int) -> list[dict]:
    env = gym.make(SUITES[suite].env_id(level, version=0))
    rows = []
    for task in range(len(env.unwrapped.tasks)):
        for seed in range(seeds):
            _, info = env.reset(seed=seed, options={"task": task})
            u = env.unwrapped
            placement = u.episode.placement
            problem = placement.problem
            segments = {name: (a, b) for name, a, b in problem.path_segments()}
            a, b = segments.get(placement.segment, (problem.pick.center, problem.place.center))
            rows.append({
                "task": task, "obstacle": info["obstacle"], "pedestal": placement.pedestal or "none",
                "gap_to_pick": footprint_gap(placement.footprint, problem.pick),
                "centre_to_pick": float(np.linalg.norm(placement.xy - problem.pick.center)),
                "to_path": distance_to_segment(placement.xy, a, b), "segment": placement.segment or "-",
                "relaxed": placement.relaxed, "clearance": info["min_clearance"],
            })
    env.close()
    return rows


def _q(values) -> str:
    v = np.asarray(values, dtype=float)
    return f"{v.min():.3f} / {np.median(v):.3f} / {v.max():.3f}"


def card(suite: str, stats: dict[str, list[dict]], seeds: int) -> str:
    spec = SUITES[suite]
    lines = [f"# SafeLibero-{suite.capitalize()}", "",
             f"Ids: `SafeLibero-{suite.capitalize()}-L1-v1`, `-L2-v1` (drawn around SafeLIBERO's own obstacle "
             "spots, `docs/scenarios.md`), `-Free-v0`, and the older `-L1-v0`, `-L2-v0` (below). "
             f"Step limit: {spec.max_steps} control steps (20 Hz). Object slots in `object_poses`: "
             f"{spec.object_slots}.", "", "| # | task (LIBERO) | L1 | L2 | Free |", "|---|---|---|---|---|"]
    for i, t in enumerate(spec.tasks):
        marks = ["x" if i in spec.level_tasks.get(lv, range(len(spec.tasks))) else "" for lv in ("L1", "L2")]
        lines.append(f"| {i} | {t.language} (`{t.libero_suite}` #{t.libero_index}) | {marks[0]} | {marks[1]} | x |")
    lines += ["", "Task indices of a level are positions in its own list (`env.unwrapped.tasks`).", "",
              "## Obstacle placement of the -v0 ids", "",
              f"- One of SafeLIBERO's six obstacles per episode, drawn from the seed. Level 1: footprint gap "
              f"{L1_GAP[0]:.2f}-{L1_GAP[1]:.2f} m from the object to pick, any direction, no overlap with "
              "other objects. Level 2: on the straight motion path, carry segment (pick -> place) when it "
              "has room, else the approach segment (hand start -> pick), centre within "
              f"{L2_LATERAL:.2f} m of it (relaxation widens this, and its last two rounds may put it up to "
              "10 cm beside the path in cluttered scenes), raised on a "
              f"pedestal when shorter than the carry height ({TRANSIT_HEIGHT:.2f} m above the support minus "
              "the held object).",
              "- `relaxed` counts placements that needed relaxed constraints (see `place_obstacle`); a "
              "negative gap means footprint boxes overlap (round objects' boxes overlap before the objects do).",
              "- SafeLIBERO for comparison (anchors): Level I close to the target; Level II further away on "
              "the path, often on a storage-box base; position jitter within a scenario 0-2 cm.", "",
              f"## Measured ({seeds} seeds per task and level; min / median / max, metres)", "",
              "| level | gap to pick | centre to pick | centre to path | segments | pedestals | relaxed | "
              "robot clearance at start |", "|---|---|---|---|---|---|---|---|"]
    for level, rows in stats.items():
        seg = Counter(r["segment"] for r in rows)
        ped = Counter(r["pedestal"] for r in rows)
        relaxed = sum(r["relaxed"] > 0 for r in rows)
        lines.append(f"| {level} | {_q([r['gap_to_pick'] for r in rows])} | "
                     f"{_q([r['centre_to_pick'] for r in rows])} | {_q([r['to_path'] for r in rows])} | "
                     f"{dict(seg)} | {dict(ped)} | {relaxed}/{len(rows)} | {_q([r['clearance'] for r in rows])} |")
    lines += ["", "Regenerate: `python benchmarks/placement_stats.py --suites " + suite + f" --seeds {seeds}`.", ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--suites", nargs="+", default=[s for s in SUITES if SUITES[s].shape_source_level])
    parser.add_argument("--seeds", type=int, default=10)
    args = parser.parse_args()
    for suite in args.suites:
        stats = {level: measure(suite, level, args.seeds) for level in ("L1", "L2")}
        text = card(suite, stats, args.seeds)
        path = ROOT / "envs" / suite / "README.md"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        print(text)


if __name__ == "__main__":
    main()
