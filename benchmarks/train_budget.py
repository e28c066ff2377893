"""Training budget on this CPU: parameters, step time and projected wall time for a few model sizes.

Run by hand (takes a few minutes; the paper-size row alone needs ~1 min)::

    python benchmarks/train_budget.py                       # default grid, 1 and 2 threads
    python benchmarks/train_budget.py --threads 2 --batch 256 --planned-steps 8000 --skip-paper

Each row times the real training step of ``detaug_gym.train`` (batch sampling, flow loss, backward, clip,
AdamW, EMA) on a synthetic Spatial-shaped dataset (obs dim 49, label dim 4, H = 50). Step times are the
median of ``--repeats`` steps after two warm-up steps, as wall time and as CPU time of this process. The
machine's load average is printed with the table: other processes on the same cores slow training down
(with two threads much more so, as OpenMP threads wait for each other); with one thread the CPU time is
close to the wall time the step takes on an otherwise idle machine.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import torch

from detaug_gym.models.dataset import PlanLayout, WindowDataset, read_demos
from detaug_gym.models.synthetic import write_synthetic_demos
from detaug_gym.train import EMA, TrainConfig, build_network, train_step

# (name, d_model, layers, heads, steps_per_token)
GRID = [
    ("paper (d256 L8, 1 step/token)", 256, 8, 4, 1),
    ("d256 L8, 5 steps/token", 256, 8, 4, 5),
    ("d192 L6, 5 steps/token", 192, 6, 4, 5),
    ("d128 L4, 5 steps/token", 128, 4, 4, 5),
    ("d128 L4, 10 steps/token", 128, 4, 4, 10),
    ("d96 L4, 5 steps/token", 96, 4, 4, 5),
]


def time_config(data: WindowDataset, d_model: int, layers: int, heads: int, steps_per_token: int, batch: int,
                repeats: int) -> tuple[int, float, float]:
    cfg = TrainConfig(method="detaug", batch_size=batch, d_model=d_model, layers=layers, heads=heads,
                      steps_per_token=steps_per_token)
    network = build_network(cfg, data)
    optimizer = torch.optim.AdamW(network.parameters(), lr=cfg.lr)
    ema = EMA(network, cfg.ema_decay)
    known = torch.zeros(1, cfg.horizon, data.layout.plan_dim, dtype=torch.bool)
    known[:, 0, data.layout.state_slice] = True
    generator = torch.Generator().manual_seed(0)
    wall, cpu = [], []
    for i in range(repeats + 2):
        tic, cpu_tic = time.perf_counter(), time.process_time()
        train_step(network, data, optimizer, cfg, known, generator)
        ema.update(network)
        if i >= 2:
            wall.append(time.perf_counter() - tic)
            cpu.append(time.process_time() - cpu_tic)
    return network.num_parameters(), statistics.median(wall), statistics.median(cpu)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch thread counts to time")
    parser.add_argument("--batch", type=int, default=256, help="batch size")
    parser.add_argument("--planned-steps", type=int, default=8000, help="steps used for the wall-time projection")
    parser.add_argument("--repeats", type=int, default=6, help="timed steps per row")
    parser.add_argument("--skip-paper", action="store_true", help="skip the slow paper-size rows")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = write_synthetic_demos(Path(tmp) / "demos.hdf5", n_demos=16, length=150, n_tasks=4, n_slots=2,
                                     label_dim=4)
        data = WindowDataset(read_demos(path), horizon=50, layout=PlanLayout(), use_labels=True)
    print(f"obs dim {data.obs_dim}, plan dim {data.layout.plan_dim}, batch {args.batch}, "
          f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores, torch {torch.__version__}")
    print(f"| model | params | threads | step wall (s) | step CPU (s) | {args.planned_steps} steps (min) |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, d_model, layers, heads, per_token in GRID:
        if args.skip_paper and d_model == 256:
            continue
        for threads in args.threads:
            torch.set_num_threads(threads)
            repeats = 2 if d_model == 256 else args.repeats
            params, step, cpu = time_config(data, d_model, layers, heads, per_token, args.batch, repeats)
            print(f"| {name} | {params / 1e6:.2f}M | {threads} | {step:.3f} | {cpu:.3f} | "
                  f"{step * args.planned_steps / 60:.1f} |", flush=True)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
