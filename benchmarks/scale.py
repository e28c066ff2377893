"""The bench's scaling figures in one run (issue #25): DetAug's replan latency per K, episodes per core-hour per
method one env at a time vs batched across envs, and the Ray backend vs local workers on the same episodes.

    python benchmarks/scale.py                          # 8 Spatial L2 episodes per method, 4 envs per worker
    python benchmarks/scale.py --episodes 16 --envs 8   # more episodes, wider batches
    python benchmarks/scale.py --skip latency ray       # only the batched-vs-local table

1. Replan latency: ``benchmarks/detaug_latency.py`` (generation and scoring per K, flops, GFLOP/s against
   this CPU's matmul peak).
2. Episodes per core-hour: every method on the same ``--episodes`` L2 episodes (bench seed ``--seed``),
   ``--workers 1`` in this process, with ``--envs-per-worker 1`` and ``--envs``; core-hours are this process's
   CPU time (all its threads). Beside it how far the two runs' records agree (see docs/performance.md for
   why batching is exact to float32 rounding, not bit for bit, for K = 1 policies).
3. Ray vs local: ``base`` on the same episodes with ``--workers 2`` local and ``--backend ray --workers 2``
   (a private Ray instance started for the run, its start-up timed apart): whether the records are identical,
   and the wall-time overhead per episode.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling benchmark script
import detaug_latency  # noqa: E402

from detaug_gym import bench  # noqa: E402
from detaug_gym.models.policy import zoo_dir  # noqa: E402

METHODS = ("base", "aegis", "cape", "demogen", "detaug")
TIMING = ("wall_time",)


def _bench(out: Path, quiet: bool = True, **kw) -> tuple[float, float]:
    """Run one bench config; returns (wall s, CPU s of this process)."""
    cfg = bench.BenchConfig(out=str(out), **kw)
    c0, t0 = time.process_time(), time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()) if quiet else contextlib.nullcontext():
        bench.run(cfg)
    return time.perf_counter() - t0, time.process_time() - c0


def _records(out: Path) -> dict:
    lines = [json.loads(line) for line in (out / bench.LOG).read_text().splitlines()]
    return {bench.record_key(r): {k: v for k, v in r.items() if k not in TIMING} for r in lines}


def agreement(a: dict, b: dict) -> tuple[int, int, float]:
    """(identical records, same outcome: termination + collision + steps, largest |clearance difference| m)."""
    same = sum(a[k] == b[k] for k in a)
    outcome = sum(all(a[k][f] == b[k][f] for f in ("termination", "collision", "steps")) for k in a)
    gap = max(abs((a[k]["min_clearance"] or 0.0) - (b[k]["min_clearance"] or 0.0)) for k in a)
    return same, outcome, gap


def batched_table(root: Path, episodes: int, envs: int, seed: int) -> None:
    common = dict(suites=["spatial"], levels=["2"], episodes=episodes, seeds=[seed], workers=1)
    print(f"\nEpisodes per core-hour, Spatial L2, {episodes} episodes per method (bench seed {seed}), one process")
    print(f"| method | 1 env: ep / core-h | {envs} envs: ep / core-h | speed-up | CPU ms per env step (1 / {envs}) | "
          f"wall s (1 / {envs}) | identical records | same outcome | max clearance gap (m) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for method in METHODS:
        runs = {}
        for n in (1, envs):
            out = root / f"{method}_n{n}"
            wall, cpu = _bench(out, methods=[method], envs_per_worker=n, **common)
            runs[n] = (wall, cpu, _records(out))
        (w1, c1, r1), (wn, cn, rn) = runs[1], runs[envs]
        same, outcome, gap = agreement(r1, rn)
        steps1, stepsn = (sum(r["steps"] for r in recs.values()) for recs in (r1, rn))
        print(f"| {method} | {episodes / c1 * 3600:.0f} | {episodes / cn * 3600:.0f} | {c1 / cn:.2f} | "
              f"{1e3 * c1 / steps1:.1f} / {1e3 * cn / stepsn:.1f} | {w1:.0f} / {wn:.0f} | {same}/{episodes} | "
              f"{outcome}/{episodes} | {gap:.1e} |")


def ray_table(root: Path, episodes: int, seed: int) -> None:
    import ray

    common = dict(methods=["base"], suites=["spatial"], levels=["2"], episodes=episodes, seeds=[seed], workers=2)
    local_wall, _ = _bench(root / "local", **common)
    t0 = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    startup = time.perf_counter() - t0
    try:
        ray_wall, _ = _bench(root / "ray", backend="ray", **common)
    finally:
        ray.shutdown()
    same, outcome, gap = agreement(_records(root / "local"), _records(root / "ray"))
    print(f"\nRay vs local workers: base, {episodes} Spatial L2 episodes, 2 workers each")
    print("| backend | wall s | per episode s | identical records |")
    print("|---|---:|---:|---:|")
    print(f"| local (spawned processes) | {local_wall:.1f} | {local_wall / episodes:.2f} | |")
    print(f"| ray (private instance, actors) | {ray_wall:.1f} | {ray_wall / episodes:.2f} | {same}/{episodes} |")
    print(f"Ray overhead: {(ray_wall - local_wall) / episodes:+.2f} s per episode (actor start-up included), "
          f"instance start-up {startup:.1f} s apart")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=8)
    parser.add_argument("--envs", type=int, default=4, help="envs per worker of the batched runs")
    parser.add_argument("--seed", type=int, default=31)
    parser.add_argument("--skip", nargs="*", default=[], choices=("latency", "batched", "ray"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    if "latency" not in args.skip:
        rows = detaug_latency.measure(str(zoo_dir("detaug", "spatial")))
        detaug_latency.print_table(rows, detaug_latency.matmul_peak(), 1, 7)
    with tempfile.TemporaryDirectory() as tmp:
        if "batched" not in args.skip:
            batched_table(Path(tmp) / "batched", args.episodes, args.envs, args.seed)
        if "ray" not in args.skip:
            ray_table(Path(tmp) / "ray", args.episodes, args.seed)


if __name__ == "__main__":
    main()
