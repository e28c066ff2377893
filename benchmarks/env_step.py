"""How fast our envs step, next to stock LIBERO and to the bare physics, measured in one run.

    python benchmarks/env_step.py                 # full table (about 2 minutes: builds 4 LIBERO scenes)
    python benchmarks/env_step.py --no-vec        # skip the make_vec workers
    python benchmarks/env_step.py --steps 100 --reps 5

Rows:
- stock: ``libero.libero.envs.env_wrapper.ControlEnv`` (state only, soft reset) on libero_spatial task 0,
  robosuite's own OSC_POSE controller and observables, ``env.step`` per 20 Hz control step.
- ours: ``gym.make("SafeLibero-Spatial-Free-v0", task=0)`` (fast controller), the whole ``env.step``
  including our observation and info (success check, contacts).
- physics: 25 x ``mj_step`` on the same scene, the floor for any controller.
- reset: ours = ``env.reset(seed)`` (state load + 10 settle steps); stock = ``reset()`` + ``set_init_state``,
  alone and followed by the same 10 settle steps.
- RSS added: resident memory added by building each env; the stock env is built first, so its figure also
  holds the LIBERO/robosuite imports that ours then reuses.
- make_vec: ``gym.make_vec(..., vectorization_mode="async")`` with 1 and 2 workers, env-steps per second
  (both built first, then timed in alternating blocks).
Stock and ours alternate in the same process on the same random actions; each figure is the median over
``--reps`` blocks. On a shared machine compare the ratios, not the absolute times; the load average is
printed so that a busy machine shows.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import resource
import time
from dataclasses import dataclass

import gymnasium as gym
import mujoco
import numpy as np

import detaug_gym  # noqa: F401  (registers the ids)
from detaug_gym.envs.base import SETTLE_STEPS
from detaug_gym.envs.scene import SETTLE_ACTION

ENV_ID = "SafeLibero-Spatial-Free-v0"


@dataclass
class Args:
    steps: int = 60
    """control steps per timed block"""
    reps: int = 5
    """timed blocks per variant (the median is reported)"""
    vec_steps: int = 150
    """vector steps timed per make_vec configuration, in --reps blocks (below the 220-step limit: no auto-reset)"""
    no_vec: bool = False
    """skip the make_vec measurements"""


def parse_args() -> Args:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=Args.steps)
    parser.add_argument("--reps", type=int, default=Args.reps)
    parser.add_argument("--vec-steps", type=int, default=Args.vec_steps)
    parser.add_argument("--no-vec", action="store_true")
    return Args(**vars(parser.parse_args()))


def rss_mb() -> float:
    """Current resident set size of this process (MB)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def build_stock():
    """LIBERO's state-only ControlEnv on libero_spatial task 0, at its first official init state."""
    with contextlib.redirect_stdout(io.StringIO()):
        from libero.libero import benchmark, get_libero_path
        from libero.libero.envs.env_wrapper import ControlEnv

        suite = benchmark.get_benchmark("libero_spatial")(task_order_index=0)
        task = suite.get_task(0)
        init_states = suite.get_task_init_states(0)
        env = ControlEnv(bddl_file_name=f"{get_libero_path('bddl_files')}/{task.problem_folder}/{task.bddl_file}",
                         has_renderer=False, has_offscreen_renderer=False, use_camera_obs=False,
                         hard_reset=False, ignore_done=True)
        env.seed(0)
        env.reset()
    env.set_init_state(init_states[0])
    return env, init_states


def timed(fn, n: int) -> float:
    """Seconds per call of ``fn`` over ``n`` calls."""
    start = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - start) / n


def time_steps(stock, ours, args: Args) -> dict[str, float]:
    """ms per control step for stock, ours and physics only, interleaved block by block."""
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (args.steps, 7)).astype(np.float32)
    scene = ours.unwrapped.scene
    m, d = scene.model, scene.data
    blocks = {"stock": [], "ours": [], "physics": []}
    for _ in range(args.reps):
        start = time.perf_counter()
        for a in actions:
            stock.step(a)
        blocks["stock"].append(time.perf_counter() - start)
        start = time.perf_counter()
        for a in actions:
            ours.step(a)
        blocks["ours"].append(time.perf_counter() - start)
        state = scene.get_state()
        warmstart = d.qacc_warmstart.copy()
        start = time.perf_counter()
        for _ in range(25 * len(actions)):
            mujoco.mj_step(m, d)
        blocks["physics"].append(time.perf_counter() - start)
        scene.set_state(state)  # leave our env where its own steps left it
        d.qacc_warmstart[:] = warmstart
        mujoco.mj_forward(m, d)
    return {k: 1e3 * float(np.median(v)) / args.steps for k, v in blocks.items()}


def time_resets(stock, init_states, ours, reps: int) -> dict[str, float]:
    """ms per reset: ours (seeded, with its settle steps), stock (soft reset + official init state), and stock
    followed by the same 10 no-op settle steps (what a SafeLIBERO-style episode start costs with stock)."""
    def stock_reset(settle_steps: int = 0):
        with contextlib.redirect_stdout(io.StringIO()):
            stock.reset()
        stock.set_init_state(init_states[0])
        for _ in range(settle_steps):
            stock.step(SETTLE_ACTION)

    seeds = iter(range(10**6))
    return {"stock": 1e3 * timed(stock_reset, reps),
            "stock_settled": 1e3 * timed(lambda: stock_reset(SETTLE_STEPS), reps),
            "ours": 1e3 * timed(lambda: ours.reset(seed=next(seeds)), reps)}


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (from /proc)."""
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def vec_throughput(worker_counts: tuple[int, ...], steps: int, reps: int) -> dict[int, dict[str, float]]:
    """Per worker count: env-steps per second, worker CPU ms per env-step, build + reset seconds.

    All vector envs are built first and then timed in alternating blocks (median block), so that a change in
    the machine's load hits every configuration alike. The workers' CPU time per env-step tells contention
    apart from overhead: if it stays flat from 1 to 2 workers, missing scaling is other processes' load.
    """
    venvs, builds = {}, {}
    for n in worker_counts:
        start = time.perf_counter()
        venvs[n] = gym.make_vec(ENV_ID, num_envs=n, vectorization_mode="async", task=0,
                                vector_kwargs={"context": "spawn"})  # fresh workers, not forks of this process
        venvs[n].reset(seed=0)
        builds[n] = time.perf_counter() - start
    rng = np.random.default_rng(1)
    block = max(1, steps // reps)
    rates = {n: [] for n in worker_counts}
    cpu = {n: [] for n in worker_counts}
    for n, venv in venvs.items():  # warm up the pipes and the workers' caches
        for a in rng.uniform(-0.3, 0.3, (5, n, 7)).astype(np.float32):
            venv.step(a)
    for _ in range(reps):
        for n, venv in venvs.items():
            actions = rng.uniform(-0.3, 0.3, (block, n, 7)).astype(np.float32)
            pids = [p.pid for p in venv.processes]
            cpu_start = sum(cpu_seconds(pid) for pid in pids)
            start = time.perf_counter()
            for a in actions:
                venv.step(a)
            rates[n].append(n * block / (time.perf_counter() - start))
            cpu[n].append(1e3 * (sum(cpu_seconds(pid) for pid in pids) - cpu_start) / (n * block))
    for venv in venvs.values():
        venv.close()
    return {n: {"steps_per_s": float(np.median(rates[n])), "cpu_ms": float(np.median(cpu[n])),
                "build_s": builds[n]} for n in worker_counts}


def main() -> None:
    args = parse_args()
    load_start = os.getloadavg()[0]
    rss0 = rss_mb()
    start = time.perf_counter()
    stock, init_states = build_stock()
    stock_build = time.perf_counter() - start
    rss_stock = rss_mb()
    start = time.perf_counter()
    ours = gym.make(ENV_ID, task=0)
    ours.reset(seed=0)
    ours_build = time.perf_counter() - start
    rss_ours = rss_mb()

    ms = time_steps(stock, ours, args)
    resets = time_resets(stock, init_states, ours, reps=5)
    load_steps = os.getloadavg()[0]
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    rows = [
        ("stock ControlEnv step", f"{ms['stock']:.1f} ms", ""),
        ("ours env.step", f"{ms['ours']:.1f} ms", f"{ms['ours'] / ms['stock']:.2f} x stock (goal <= 0.33)"),
        ("physics only (25 x mj_step)", f"{ms['physics']:.1f} ms",
         f"ours = {ms['ours'] / ms['physics']:.2f} x physics (goal <= 2)"),
        ("stock reset + set_init_state", f"{resets['stock']:.0f} ms", ""),
        ("stock reset + set_init_state + 10 settle steps", f"{resets['stock_settled']:.0f} ms", ""),
        ("ours reset (incl. 10 settle steps)", f"{resets['ours']:.0f} ms",
         f"{resets['ours'] / resets['stock']:.2f} x stock reset, "
         f"{resets['ours'] / resets['stock_settled']:.2f} x stock reset + settle"),
        ("first build: stock / ours", f"{stock_build:.1f} s / {ours_build:.1f} s", ""),
        ("RSS added: stock env / our env", f"{rss_stock - rss0:.0f} MB / {rss_ours - rss_stock:.0f} MB",
         f"peak RSS of this process {peak_rss:.0f} MB"),
    ]
    load_vec = None
    if not args.no_vec:
        vec = vec_throughput((1, 2), args.vec_steps, args.reps)
        one, two = vec[1], vec[2]
        sps1, sps2 = one["steps_per_s"], two["steps_per_s"]
        load_vec = os.getloadavg()[0]
        child_rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        rows += [
            ("make_vec async, 1 worker", f"{sps1:.0f} steps/s", f"build + reset {one['build_s']:.1f} s"),
            ("make_vec async, 2 workers", f"{sps2:.0f} steps/s",
             f"{sps2 / sps1:.2f} x one worker (goal >= 1.7); build + reset {two['build_s']:.1f} s"),
            ("worker CPU per env-step: 1 / 2 workers", f"{one['cpu_ms']:.1f} / {two['cpu_ms']:.1f} ms",
             "flat = the workers do not slow each other"),
            ("peak RSS of one worker", f"{child_rss:.0f} MB", "a spawned worker: its own imports and scene"),
        ]
    width = max(len(r[0]) for r in rows)
    print(f"\n{'measure':<{width}} | {'value':<18} | ratio")
    print(f"{'-' * width}-|-{'-' * 18}-|------")
    for name, value, ratio in rows:
        print(f"{name:<{width}} | {value:<18} | {ratio}")
    cores = os.cpu_count()
    loads = f"load average (1 min) at start {load_start:.1f}, after step timing {load_steps:.1f}"
    if load_vec is not None:
        loads += f", after make_vec {load_vec:.1f}"
    print(f"\n{cores} CPU cores; {loads}.")
    if max(load_start, load_steps) > 1.5:
        print("note: other processes were loading the CPU while this ran; absolute times are inflated, "
              "ratios measured side by side are still comparable, make_vec scaling may be understated.")
    ours.close()


if __name__ == "__main__":
    main()
