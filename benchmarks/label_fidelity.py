"""How much of a labelled arc a DetAug checkpoint reproduces (run by hand).

    python benchmarks/label_fidelity.py --data data/spatial_detaug.hdf5
    python benchmarks/label_fidelity.py --data data/spatial_detaug.hdf5 --checkpoint /tmp/ckpt/detaug_new --demos 60

DetAug only avoids what its K candidates avoid, so a checkpoint that draws every label as nearly the unbent
path gives the selector nothing to choose from. For each augmented demo in ``--data`` and each of its bent
transits (approach, carry), at the transit's first frame the checkpoint plans ``--samples`` chunks with the
demo's own label, and the script compares the planned end-effector path with the demo's over the chunk
(``H`` steps): the mean distance from each demo point to the nearest planned point. The unbent source demo's
path gives the scale: ``reproduced = 1 - d(plan, demo) / d(source, demo)`` is 1 when the plan follows the arc,
0 when it is as far from it as the unbent path (and negative when farther). Transits are split into
sideways arcs (|cos theta| > 0.7) and the others (mostly up), whose fidelity can differ. At z = 0 the
unbent plan's distance to the source demo is the floor every label adds its error to.
"""

from __future__ import annotations

import argparse
import json

import h5py
import numpy as np
import torch
from tqdm import tqdm

import detaug_gym  # noqa: F401
from detaug_gym.augment.arcs import label_to_arc
from detaug_gym.policies import make_policy


def path_distance(demo: np.ndarray, plan: np.ndarray) -> float:
    """Mean over the demo's points (N, 3) of the distance to the nearest point of the plan's path (H, 3)."""
    return float(np.linalg.norm(demo[:, None] - plan[None], axis=-1).min(axis=1).mean())


def _obs(group: h5py.Group, frame: int) -> dict[str, np.ndarray]:
    return {key: group["obs"][key][frame] for key in group["obs"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, help="an augmented file (python -m detaug_gym.augment)")
    parser.add_argument("--checkpoint", default=None, help="a DetAug checkpoint folder (default: the zoo's)")
    parser.add_argument("--suite", default="spatial")
    parser.add_argument("--demos", type=int, default=80, help="augmented demos to use (spread over the file)")
    parser.add_argument("--samples", type=int, default=4, help="plans per transit")
    parser.add_argument("--flow-steps", type=int, default=10, help="Euler steps per plan (the policy default: 10)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    policy = make_policy("detaug", suite=args.suite, checkpoint=args.checkpoint, flow_steps=args.flow_steps)
    eef, horizon = policy.layout.key_slice("eef_pos"), policy.horizon
    rows: list[tuple[str, float, float]] = []  # (kind, d(plan, demo), d(source, demo))
    floor: list[float] = []
    with h5py.File(args.data, "r") as f:
        data = f["data"]
        augmented = sorted((k for k in data if data[k].attrs.get("augmented", False)), key=lambda k: int(k[5:]))
        if not augmented:
            raise SystemExit(f"error: {args.data} has no augmented demos (python -m detaug_gym.augment writes them)")
        pick = [augmented[i] for i in np.linspace(0, len(augmented) - 1, min(args.demos, len(augmented))).astype(int)]
        for key in tqdm(pick, desc="demos"):
            demo, label = data[key], np.asarray(data[key]["label"], np.float32).reshape(-1)
            source = data[demo.attrs["source_demo"]]
            for slot, transit in enumerate(json.loads(demo.attrs["transits"])):
                phi, theta = label_to_arc(label[2 * slot:2 * slot + 2])
                if phi == 0.0:
                    continue
                start, src_start = transit["start"], transit["source_start"]
                target = demo["obs"]["eef_pos"][start:start + horizon]
                policy.reset(seed=0)
                plans = policy.plan(_obs(demo, start), np.repeat(label[None], args.samples, 0)).numpy()[..., eef]
                unbent = source["obs"]["eef_pos"][src_start:src_start + horizon]
                kind = "sideways" if abs(np.cos(theta)) > 0.7 else "up"
                rows.append((kind, float(np.mean([path_distance(target, p) for p in plans])),
                             path_distance(target, unbent)))
            policy.reset(seed=0)
            zero = policy.plan(_obs(source, 0), np.zeros((args.samples, policy.label_dim), np.float32)).numpy()
            floor.append(float(np.mean([path_distance(source["obs"]["eef_pos"][:horizon], p[:, eef]) for p in zero])))
    print(f"checkpoint: {policy.checkpoint.path}  data: {args.data}  ({len(pick)} demos, {len(rows)} bent transits)")
    print("| transits | n | d(plan, demo) cm | d(unbent, demo) cm | reproduced (median) |")
    print("|---|---|---|---|---|")
    for kind in ("sideways", "up", "all"):
        sel = [r for r in rows if kind == "all" or r[0] == kind]
        if not sel:
            continue
        d_plan, d_src = np.array([r[1] for r in sel]), np.array([r[2] for r in sel])
        reproduced = 1.0 - d_plan / np.maximum(d_src, 1e-6)
        print(f"| {kind} | {len(sel)} | {100 * d_plan.mean():.1f} | {100 * d_src.mean():.1f} | "
              f"{np.median(reproduced):.2f} |")
    print(f"z = 0: d(plan, source demo) {100 * np.mean(floor):.1f} cm (the floor)")


if __name__ == "__main__":
    main()
