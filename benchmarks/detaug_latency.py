"""DetAug replan latency for K = 1, 8, 32, 64, split into generation and scoring (run by hand).

    python benchmarks/detaug_latency.py                       # policies/detaug/spatial, one torch thread
    python benchmarks/detaug_latency.py --checkpoint DIR --repeats 10

Uses a real SafeLibero-Spatial-L2 observation (obstacle present), times ``plan`` (K plans in one batched
call) and ``score`` (penetration cost of the K joint trajectories) separately, and prints the medians and
their ratios to K = 1. Target (issue): K = 32 within 3x of K = 1.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch

import detaug_gym  # noqa: F401
from detaug_gym.models.policy import zoo_dir
from detaug_gym.policies.detaug import DetAugPolicy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default=str(zoo_dir("detaug", "spatial")))
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    env = gym.make("SafeLibero-Spatial-L2-v0", task=0)
    obs, _ = env.reset(seed=0)
    rows = []
    for k in (1, 8, 32, 64):
        policy = DetAugPolicy(checkpoint=args.checkpoint, k=k, seed=0)
        policy.reset(seed=0)
        policy.score(policy.plan(obs, policy.sample_labels(obs, k)), obs)  # warm-up: SDF bake, FK build
        gen, score = [], []
        for _ in range(args.repeats):
            labels = policy.sample_labels(obs, k)
            t0 = time.process_time()
            plans = policy.plan(obs, labels)
            t1 = time.process_time()
            policy.score(plans, obs)
            t2 = time.process_time()
            gen.append(t1 - t0)
            score.append(t2 - t1)
        rows.append((k, 1e3 * np.median(gen), 1e3 * np.median(score)))
    base_total = rows[0][1] + rows[0][2]
    print(f"DetAug replan latency, CPU time per replan (median of {args.repeats}), {args.threads} torch thread(s)")
    print("| K | generation ms | scoring ms | total ms | total / K=1 |")
    print("|---:|---:|---:|---:|---:|")
    for k, g, s in rows:
        print(f"| {k} | {g:.1f} | {s:.1f} | {g + s:.1f} | {(g + s) / base_total:.2f} |")
    env.close()


if __name__ == "__main__":
    main()
