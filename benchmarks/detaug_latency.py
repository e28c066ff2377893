"""DetAug replan latency for K = 1, 8, 32, 64, split into generation and scoring, with the generation's flop
count against this CPU's measured matmul peak (run by hand).

    python benchmarks/detaug_latency.py                       # policies/detaug/spatial, one torch thread
    python benchmarks/detaug_latency.py --checkpoint DIR --repeats 10

Uses a real SafeLibero-Spatial-L2 observation (obstacle present), times ``plan`` (K plans in one batched
call) and ``score`` (penetration cost of the K joint trajectories) separately, and prints the medians and
their ratios to K = 1, as wall-clock latency and as CPU time (the sum over threads; it is what a
loaded machine has to give). Target (issue #25): K = 32 within 3x of K = 1. The flops are counted by
``torch.utils.flop_counter`` on one ``plan`` call (the matmuls; attention and the elementwise work are
not counted, they are a few percent); GFLOP/s is that count over the generation time, against a
2048 x 2048 float32 matmul on the same threads (the peak this CPU gives torch). With ``--threads 2`` the
batched call of K = 32 spreads over both cores while K = 1 is dispatch-bound and does not; compare the runs.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

import detaug_gym  # noqa: F401
from detaug_gym.models.policy import zoo_dir
from detaug_gym.policies.detaug import DetAugPolicy

KS = (1, 8, 32, 64)


def matmul_peak(size: int = 2048, repeats: int = 5) -> float:
    """GFLOP/s of a float32 ``size x size`` matmul on torch's current threads (best of ``repeats``)."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    a @ b
    best = min(_timed(lambda: a @ b) for _ in range(repeats))
    return 2 * size ** 3 / best / 1e9


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def measure(checkpoint: str, repeats: int = 7, ks=KS) -> list[dict]:
    """Per K: median generation / scoring wall ms, total CPU ms, and the generation's GFLOP."""
    env = gym.make("SafeLibero-Spatial-L2-v0", task=0)
    obs, _ = env.reset(seed=0)
    rows = []
    for k in ks:
        policy = DetAugPolicy(checkpoint=checkpoint, k=k, seed=0)
        policy.reset(seed=0)
        policy.score(policy.plan(obs, policy.sample_labels(obs, k)), obs)  # warm-up: SDF bake, FK build
        with FlopCounterMode(display=False) as counter:
            policy.plan(obs, policy.sample_labels(obs, k))
        times = []  # (gen wall, score wall, total cpu) per repeat
        for _ in range(repeats):
            labels = policy.sample_labels(obs, k)
            c0, t0 = time.process_time(), time.perf_counter()
            plans = policy.plan(obs, labels)
            t1 = time.perf_counter()
            policy.score(plans, obs)
            t2, c2 = time.perf_counter(), time.process_time()
            times.append((t1 - t0, t2 - t1, c2 - c0))
        gen, score, cpu = 1e3 * np.median(np.array(times), axis=0)
        rows.append({"k": k, "generation_ms": gen, "scoring_ms": score, "cpu_ms": cpu,
                     "gflop": counter.get_total_flops() / 1e9})
    env.close()
    return rows


def print_table(rows: list[dict], peak: float, threads: int, repeats: int) -> None:
    wall1 = rows[0]["generation_ms"] + rows[0]["scoring_ms"]
    cpu1 = rows[0]["cpu_ms"]
    print(f"DetAug replan latency per replan (median of {repeats}), {threads} torch thread(s); "
          f"float32 matmul peak {peak:.1f} GFLOP/s")
    print("| K | generation ms | scoring ms | total ms | total / K=1 | CPU ms | CPU / K=1 | GFLOP | GFLOP/s "
          "| of peak |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        total = r["generation_ms"] + r["scoring_ms"]
        rate = r["gflop"] / (r["generation_ms"] / 1e3)
        print(f"| {r['k']} | {r['generation_ms']:.1f} | {r['scoring_ms']:.1f} | {total:.1f} | {total / wall1:.2f} | "
              f"{r['cpu_ms']:.1f} | {r['cpu_ms'] / cpu1:.2f} | {r['gflop']:.2f} | {rate:.1f} | {rate / peak:.0%} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default=str(zoo_dir("detaug", "spatial")))
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = measure(args.checkpoint, args.repeats)
    print_table(rows, matmul_peak(), args.threads, args.repeats)


if __name__ == "__main__":
    main()
