"""Why a method's episodes collided: the candidate causes of issue #23, counted from bench records (run by hand).

    python -m detaug_gym.bench --methods detaug --suites spatial --levels 2 --episodes 80 --seed 23 --out runs/diag
    python benchmarks/collision_causes.py runs/diag/episodes.jsonl --method detaug

Every collided episode's ``collision_cause`` (written by the bench, :class:`detaug_gym.rollout.CollisionAttribution`)
says who moved the obstacle, in which phase, what the selected plan was predicted to cost, and how the
policy's scorer judged the configuration actually reached. Each collision gets the first cause that fits:

1. ``window``: it happened where the augmentation never bends a demo (an interaction window or its margin).
2. ``no_free_candidate``: the selected plan already had a cost > 0, i.e. none of the K candidates was clear.
3. ``scorer_blind_robot``: the robot touched the obstacle while the scorer put the reached configuration clear
   of it (``executed_clearance > 0``): the geometry model misses the contact however well the plan is tracked.
4. ``execution_divergence``: the robot touched it, the chosen plan was free, and the scorer sees the reached
   configuration penetrate: execution went where the plan did not.
5. ``scorer_blind_object``: the held (or a pushed) object moved it and the scorer's held-object model saw no
   penetration in the reached state (``executed_cost == 0``).
6. ``object_divergence``: as 5, but the scorer does see the reached state penetrate.
7. ``unattributed``: no body was seen touching the obstacle, or the record has no plan facts.

Beside the causes it prints how far execution had drifted from the plan (``plan_deviation``), the gap between
the scorer's and the env's robot clearance, and how often the label had just switched (``label_change``).
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np

CAUSES = ("window", "no_free_candidate", "scorer_blind_robot", "execution_divergence", "scorer_blind_object",
          "object_divergence", "unattributed")


def classify(cause: dict) -> str:
    """The first of :data:`CAUSES` that fits one ``collision_cause``."""
    if not cause.get("bent", True):
        return "window"
    if "plan_cost" not in cause or cause["body"] == "none":
        return "unattributed"
    if cause["plan_cost"] > 0.0:
        return "no_free_candidate"
    kinds = set(cause["body"].split("+"))
    if kinds & {"link", "gripper"}:
        return "scorer_blind_robot" if cause.get("executed_clearance", 0.0) > 0.0 else "execution_divergence"
    return "scorer_blind_object" if cause.get("executed_cost", 0.0) <= 0.0 else "object_divergence"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("records", type=Path, nargs="+", help="bench episodes.jsonl file(s)")
    parser.add_argument("--method", default="detaug")
    args = parser.parse_args()
    rows = [json.loads(line) for path in args.records for line in path.read_text().splitlines() if line.strip()]
    rows = [r for r in rows if r["method"] == args.method and r.get("termination") != "error"]
    hits = [r for r in rows if r["collision"]]
    if not hits:
        raise SystemExit(f"no collided {args.method} episode in {len(rows)}")
    causes = [r["collision_cause"] or {} for r in hits]
    counts = Counter(classify(c) for c in causes)
    print(f"{args.method}: {len(hits)} collisions in {len(rows)} episodes\n")
    print("| cause | collisions | share |\n|---|---|---|")
    for name in CAUSES:
        print(f"| {name} | {counts[name]} | {100 * counts[name] / len(hits):.0f} % |")
    print("\n| body | collisions |\n|---|---|")
    for body, n in Counter(c.get("body", "unattributed") for c in causes).most_common():
        print(f"| {body} | {n} |")
    print("\n| phase | collisions |\n|---|---|")
    for phase, n in Counter(c.get("phase", "unattributed") for c in causes).most_common():
        print(f"| {phase} | {n} |")
    per_task = Counter((r["task"], r["collision"]) for r in rows)
    tasks = sorted({r["task"] for r in rows})
    print("\ncollisions per task: " + ", ".join(
        f"task {t}: {per_task[(t, True)]}/{per_task[(t, True)] + per_task[(t, False)]}" for t in tasks))

    def stat(key: str, pick=lambda c: True) -> str:
        values = np.array([c[key] for c in causes if c.get(key) is not None and pick(c)], float)
        return "n/a" if not values.size else f"median {np.median(values):.3f}, max {values.max():.3f} (n={values.size})"

    def robot(c):
        return bool(set(c.get("body", "").split("+")) & {"link", "gripper"})

    print(f"plan_deviation (rad): {stat('plan_deviation')}")
    gaps = [c["executed_clearance"] - c["robot_clearance"] for c in causes
            if robot(c) and c.get("executed_clearance") is not None]
    if gaps:
        print(f"robot contacts: scorer clearance minus env clearance (m): median {np.median(gaps):.4f}, "
              f"max {np.max(gaps):.4f} (n={len(gaps)})")
    print(f"zero_cost_share at the collision's replan: {stat('zero_cost_share')}")
    print(f"label_change at the collision's replan: {stat('label_change')}")


if __name__ == "__main__":
    main()
