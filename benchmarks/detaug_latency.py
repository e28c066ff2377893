"""DetAug replan latency for K = 1, 8, 32, 64, split into generation and scoring (run by hand).

    python benchmarks/detaug_latency.py                       # policies/detaug/spatial, one torch thread
    python benchmarks/detaug_latency.py --checkpoint DIR --repeats 10

Uses a real SafeLibero-Spatial-L2 observation (obstacle present), times ``plan`` (K plans in one batched
call) and ``score`` (penetration cost of the K joint trajectories) separately, and prints the medians and
their ratios to K = 1, as wall-clock latency and as CPU time (the sum over threads; it is what a
loaded machine has to give). Target (issue): K = 32 within 3x of K = 1. With ``--threads 2`` the batched
call of K = 32 spreads over both cores while K = 1 is dispatch-bound and does not; compare the two runs.
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
        times = []  # (gen wall, score wall, total cpu) per repeat
        for _ in range(args.repeats):
            labels = policy.sample_labels(obs, k)
            c0, t0 = time.process_time(), time.perf_counter()
            plans = policy.plan(obs, labels)
            t1 = time.perf_counter()
            policy.score(plans, obs)
            t2, c2 = time.perf_counter(), time.process_time()
            times.append((t1 - t0, t2 - t1, c2 - c0))
        rows.append((k, *(1e3 * np.median(np.array(times), axis=0))))
    wall1, cpu1 = rows[0][1] + rows[0][2], rows[0][3]
    print(f"DetAug replan latency per replan (median of {args.repeats}), {args.threads} torch thread(s)")
    print("| K | generation ms | scoring ms | total ms | total / K=1 | CPU ms | CPU / K=1 |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for k, g, s, c in rows:
        print(f"| {k} | {g:.1f} | {s:.1f} | {g + s:.1f} | {(g + s) / wall1:.2f} | {c:.1f} | {c / cpu1:.2f} |")
    env.close()


if __name__ == "__main__":
    main()
