"""Per-step cost of AEGIS and CAPE (and DetAug when its checkpoint exists) relative to the base flow policy.

    python benchmarks/method_overhead.py                        # Spatial L2 task 0, 120 steps, 5 repeats
    python benchmarks/method_overhead.py --level L1 --clock wall   # wall time (noisy on a shared machine)

The observations are real: one episode of the (obstacle-blind) scripted expert in the env, recorded once,
which passes close to the obstacle, so AEGIS's QP and CAPE's guidance have work to do. Every policy is
then fed the same recorded observations (open loop) and ``act`` is timed step by step; the mean per env
step includes the replans (base and DetAug at their checkpoints' replan period, every 5 steps for the
zoo's; CAPE every 2). The network is the real ``policies/base/spatial`` checkpoint when it exists,
otherwise a default-size one trained for a few steps on synthetic demos (same cost per step, meaningless
actions). One warm-up pass per policy is excluded
(AEGIS's obstacle ellipsoid fit and the SDF bake are cached per obstacle shape after it); the first-step
cost with an empty cache is printed separately. One torch thread, like the bench workers.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from detaug_gym.models.policy import zoo_dir

CLOCK = time.perf_counter


def record_observations(level: str, task: int, steps: int, seed: int) -> list[dict[str, np.ndarray]]:
    """``steps`` observations of one scripted-expert episode (continued with no-ops after it ends)."""
    import gymnasium as gym

    from detaug_gym.policies import make_policy

    env = gym.make(f"SafeLibero-Spatial-{level}-v0", task=task)
    expert = make_policy("scripted")
    obs, _ = env.reset(seed=seed)
    expert.reset(seed=seed)
    observations, done = [], False
    for _ in range(steps):
        observations.append({key: np.array(value) for key, value in obs.items()})
        action = np.zeros(7, np.float32) if done else expert.act(obs)
        obs, _, terminated, truncated, _ = env.step(action)
        done = done or terminated or truncated
    env.close()
    return observations


def base_checkpoint(obs: dict[str, np.ndarray], workdir: Path) -> tuple[str, str]:
    """The zoo's ``base/spatial`` checkpoint, or a default-size stand-in trained on synthetic demos."""
    real = zoo_dir("base", "spatial")
    if (real / "model.pt").exists():
        return str(real), "real policies/base/spatial"
    from detaug_gym.models.synthetic import write_synthetic_demos
    from detaug_gym.train import TrainConfig, train

    data = write_synthetic_demos(workdir / "demos.hdf5", n_demos=8, length=60, n_tasks=len(obs["task_id"]),
                                 n_slots=len(obs["object_mask"]))
    cfg = TrainConfig(method="base", data=str(data), out=str(workdir / "base"), steps=5, warmup_steps=1,
                      progress=False, threads=1)
    train(cfg)
    return cfg.out, "synthetic stand-in (default size, untrained)"


def time_policies(policies: dict, observations: list[dict], repeats: int) -> dict[str, np.ndarray]:
    """``{name: (repeats, steps)}`` seconds per ``act`` call, after one warm-up pass; the methods take
    turns within each repeat, so a change in machine load hits all of them alike."""
    times = {name: np.zeros((repeats, len(observations))) for name in policies}
    for r in range(-1, repeats):
        for name, policy in policies.items():
            policy.reset(seed=r + 1)
            for i, obs in enumerate(observations):
                start = CLOCK()
                policy.act(obs)
                if r >= 0:
                    times[name][r, i] = CLOCK() - start
    return times


def filter_split(aegis, observations: list[dict]) -> tuple[float, float, float]:
    """Fraction of steps the filter changed the action; mean filter ms on passive and on active steps."""
    aegis.reset(seed=1)
    active, passive = [], []
    for obs in observations:
        action = aegis.policy.act(obs)
        start = CLOCK()
        _, step = aegis.filter(action, obs)
        (active if step.active else passive).append(CLOCK() - start)
    n = len(active) + len(passive)
    mean = lambda xs: 1e3 * float(np.mean(xs)) if xs else float("nan")  # noqa: E731
    return len(active) / n, mean(passive), mean(active)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--level", default="L2", choices=["L1", "L2"])
    parser.add_argument("--task", type=int, default=0)
    parser.add_argument("--steps", type=int, default=120, help="recorded env steps fed to every policy")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--clock", choices=["wall", "cpu"], default="cpu",
                        help="cpu (default): this process's CPU time, steadier on a shared machine")
    args = parser.parse_args()
    global CLOCK
    CLOCK = time.process_time if args.clock == "cpu" else time.perf_counter
    torch.set_num_threads(1)
    from detaug_gym.policies import make_policy

    observations = record_observations(args.level, args.task, args.steps, args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        checkpoint, source = base_checkpoint(observations[0], Path(tmp))
        methods = {"base": make_policy("base", checkpoint=checkpoint),
                   "aegis": make_policy("aegis", checkpoint=checkpoint),
                   "cape": make_policy("cape", checkpoint=checkpoint)}
        if (zoo_dir("detaug", "spatial") / "model.pt").exists():
            methods["detaug"] = make_policy("detaug", suite="spatial")
        first = {}
        for name in ("aegis", "cape"):  # cold caches: a fresh process would pay this once per obstacle shape
            from detaug_gym.geometry import SHAPES

            SHAPES.clear()  # hulls, SDF grids and ellipsoid fits of every shape
            fresh = make_policy(name, checkpoint=checkpoint)
            fresh.reset(seed=0)
            start = CLOCK()
            fresh.act(observations[0])
            first[name] = 1e3 * (CLOCK() - start)
        results = time_policies(methods, observations, args.repeats)
        share, passive_ms, active_ms = filter_split(methods["aegis"], observations)
    base_ms = 1e3 * float(np.median(results["base"].mean(axis=1)))
    print(f"Spatial {args.level} task {args.task}, {args.steps} recorded steps x {args.repeats} repeats, "
          f"{args.clock} clock, torch threads {torch.get_num_threads()}, network: {source}")
    print("\n| method | ms / env step | p95 ms | overhead vs base (ms) | ratio to base |")
    print("|---|---:|---:|---:|---:|")
    for name, times in results.items():
        ms = 1e3 * float(np.median(times.mean(axis=1)))
        p95 = 1e3 * float(np.percentile(times, 95))
        print(f"| {name} | {ms:.2f} | {p95:.2f} | {ms - base_ms:+.2f} | {ms / base_ms:.2f} |")
    print(f"\nAEGIS filter alone: active on {100 * share:.0f}% of steps; {passive_ms:.3f} ms when it passes the "
          f"action, {active_ms:.3f} ms when it solves the QP.")
    print(f"First step with empty caches: aegis {first['aegis']:.0f} ms (MVEE fit), cape {first['cape']:.0f} ms "
          "(SDF bake + plan).")


if __name__ == "__main__":
    main()
