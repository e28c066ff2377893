"""Collect scripted-expert demonstrations into a LIBERO-layout HDF5 file (only successful episodes kept).

    python -m detaug_gym.collect --env SafeLibero-Spatial-Free-v0 --task all --demos 50 --out data/spatial.hdf5
    python -m detaug_gym.collect --env SafeLibero-Goal-Free-v0 --task 4 --demos 50 --out data/goal.hdf5
    python -m detaug_gym.collect --env Newton-PickPlace-v0 --demos 50 --out data/newton.hdf5

Demo ``i`` of a task starts from init state ``i % 50`` with seed ``seed + 1000 * task + i`` (env reset and
expert). A failed attempt is not written; attempts continue with the next ``i`` until ``--demos`` demos
are kept or ``--max-attempts`` (default ``2 * demos``) are used. Every kept demo is flushed to disk at once,
so an interrupted run resumes where it stopped when started again with the same arguments.

``--action-noise SIGMA`` collects DART-style demos (Laskey et al., 2017): the env receives the expert's
command plus a temporally correlated disturbance on the position part (an Ornstein-Uhlenbeck process with
stationary std SIGMA in action units, 1 = 5 cm, and correlation time ``--noise-tau`` steps), while
``actions`` records the expert's clean command. The arm wanders off the expert's path and the demo shows
the expert steering back, states a policy trained on clean demos never sees. What was sent is kept as
``executed_actions`` (replay uses it). ``--noise-duty D`` pushes in bursts that cover a share D of the steps
(:class:`ActionNoise`), so the expert also shows its undisturbed pace. Give such a run its own ``--seed``, so
that its demos never share a (task, init state, seed) with the clean file's, and pool the two files when
training:

    python -m detaug_gym.collect --env SafeLibero-Spatial-Free-v0 --task all --demos 50 --seed 500 \\
        --action-noise 0.3 --noise-duty 0.25 --max-attempts 250 --out data/spatial_noisy.hdf5
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

import detaug_gym  # noqa: F401  (registers the env ids)
from detaug_gym.actions import controller_settings
from detaug_gym.config import build_parser, config_from_namespace
from detaug_gym.data.dataset import DatasetWriter, Demo, is_recorded
from detaug_gym.policies import Policy, make_policy
from detaug_gym.rollout import Hook, Step, rollout, until_done
from detaug_gym.seeds import demo_seed


@dataclass
class CollectArgs:
    """Command-line arguments of ``python -m detaug_gym.collect``."""

    env: str
    """Registered env id, e.g. ``SafeLibero-Spatial-Free-v0`` or ``Newton-PickPlace-v0``."""
    out: str
    """Output HDF5 file; demos are appended (resume) if it exists."""
    task: str = "all"
    """Task index or ``all``."""
    demos: int = 50
    """Demos to keep per task."""
    policy: str = "scripted"
    """Registered policy that produces the demos, with options as the bench spells them
    (``scripted:fumble=0.5``)."""
    seed: int = 0
    """Base seed; demo ``i`` of task ``t`` uses ``seed + 1000 t + i``."""
    max_attempts: int | None = None
    """Episodes tried per task before giving up (default ``2 * demos``)."""
    controller: str | None = None
    """Env controller (``fast`` / ``stock``); default: the env's default."""
    layout: str | None = None
    """SafeLIBERO Free envs' object layout: ``libero`` (default), ``safelibero`` (the obstacle levels' scene edits,
    no obstacle) or ``mixed`` (half each); see :class:`~detaug_gym.envs.safe_libero.SafeLiberoEnv`."""
    action_noise: float = 0.0
    """Std of a correlated disturbance on the executed position action, 1 = 5 cm (DART-style recovery demos;
    0: clean)."""
    noise_tau: float = 10.0
    """Correlation time of the disturbance, in env steps."""
    noise_duty: float = 1.0
    """Fraction of the steps the disturbance acts (below 1: in bursts, see :class:`ActionNoise`)."""
    noise_burst: float = 15.0
    """Mean length of a disturbance burst, in env steps (with ``noise_duty < 1``)."""
    tail_steps: int = 0
    """Env steps recorded after the first success (the expert lets go and retreats); 0 ends the demo there."""
    max_steps: int | None = None
    """Step limit of each episode (default: the suite's, which the benchmark keeps). A longer one keeps demos
    that finish late, e.g. recovery demos whose second handle grasp runs past the drawer task's 300 steps."""

    def __post_init__(self) -> None:
        if self.demos < 1:
            raise ValueError(f"--demos must be >= 1, got {self.demos}")
        if self.tail_steps < 0:
            raise ValueError(f"--tail-steps must be >= 0, got {self.tail_steps}")
        try:
            _policy_spec(self.policy)
        except (KeyError, ValueError) as exc:
            raise ValueError(f"--policy {self.policy!r}: {exc.args[0]}") from None
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"--max-steps must be >= 1, got {self.max_steps}")
        if self.max_attempts is not None and self.max_attempts < 1:
            raise ValueError(f"--max-attempts must be >= 1, got {self.max_attempts}")
        if self.layout is not None:
            from detaug_gym.envs.safe_libero import LAYOUTS
            from detaug_gym.envs.suites import suite_of_env

            suite, level = suite_of_env(self.env)
            if self.layout not in LAYOUTS or level != "Free" or not suite.entry_point.endswith(":SafeLiberoEnv"):
                raise ValueError(f"--layout takes {', '.join(LAYOUTS)} on a SafeLIBERO Free env "
                                 f"(SafeLibero-<Suite>-Free-v0); got {self.layout!r} with {self.env}")
        try:  # ActionNoise is the one place that validates the noise options
            ActionNoise(self.action_noise, self.noise_tau, self.noise_duty, self.noise_burst)
        except ValueError as exc:
            raise ValueError(f"--action-noise / --noise-tau / --noise-duty / --noise-burst: {exc}") from None


@dataclass
class ActionNoise:
    """Ornstein-Uhlenbeck disturbance on an action's position part (DART-style collection).

    ``n_{t+1} = rho n_t + sqrt(1 - rho^2) sigma eps`` with ``rho = exp(-1 / tau)``, so every step has std
    ``sigma`` and neighbouring steps push the same way: the arm drifts centimetres off the expert's path
    instead of jittering in place. The gripper and rotation parts are sent unchanged.

    With ``duty < 1`` the disturbance acts in bursts: an on/off switch that turns off with probability
    ``1 / burst`` per step and on again at the rate that keeps it on for a ``duty`` fraction of the steps.
    Between bursts the expert steers back undisturbed, at its own pace; under a constant push it keeps
    fighting it, and those demos teach a policy to dawdle (the grasp came ~50 steps later than in a clean
    demo at ``sigma = 0.3``).
    """

    sigma: float
    tau: float = 10.0
    duty: float = 1.0
    burst: float = 15.0

    def __post_init__(self) -> None:
        if self.sigma < 0 or self.tau <= 0:
            raise ValueError(f"action noise needs sigma >= 0 and tau > 0, got sigma={self.sigma}, tau={self.tau}")
        if not 0.0 < self.duty <= 1.0 or self.burst < 1.0:
            raise ValueError(f"action noise needs 0 < duty <= 1 and burst >= 1 step, got duty={self.duty}, "
                             f"burst={self.burst}")
        self._rng = np.random.default_rng()
        self._state = np.zeros(3)
        self._on = True

    def reset(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)
        self._state = self.sigma * self._rng.standard_normal(self._state.shape)
        self._on = self.duty == 1.0 or bool(self._rng.random() < self.duty)

    @property
    def active(self) -> bool:
        """Whether the last call added a push (always, unless ``duty < 1``)."""
        return self._on

    def __call__(self, action: np.ndarray) -> np.ndarray:
        """The action to execute: ``action`` (7,) with the disturbance added to its position part, clipped."""
        rho = np.exp(-1.0 / self.tau)
        self._state = rho * self._state + np.sqrt(1 - rho**2) * self.sigma * self._rng.standard_normal(
            self._state.shape)
        if self.duty < 1.0:  # (no extra draws at duty 1: the always-on stream stays what it was)
            switch = 1.0 / self.burst if self._on else self.duty / ((1.0 - self.duty) * self.burst)
            self._on ^= bool(self._rng.random() < switch)
        out = np.array(action, dtype=np.float32)
        if self._on:
            out[:3] = np.clip(out[:3] + self._state, -1.0, 1.0)
        return out


@dataclass
class TaskStats:
    task: int
    key: str
    kept: int = 0
    attempts: int = 0
    resumed: int = 0
    steps: int = 0
    seconds: float = 0.0


class NoiseHook(Hook):
    """Adds an :class:`ActionNoise` disturbance to the sent action until the task is first solved (a recorded
    tail is not disturbed)."""

    def __init__(self, noise: ActionNoise, seed: int) -> None:
        self.noise = noise
        noise.reset(seed)
        self.solved = False

    def transform(self, action: np.ndarray) -> np.ndarray:
        return action if self.solved else self.noise(action)

    def on_step(self, step: Step) -> None:
        self.solved |= step.terminated


class ActedOutHook(Hook):
    """Sends the policy's :attr:`sent` action instead of its returned one whenever it sets one: a mistake the
    scripted expert acts out on purpose (``scripted:fumble=P``) while its returned action, the demo's label,
    stays its correct command."""

    def __init__(self, policy: Policy) -> None:
        self.policy = policy

    def transform(self, action: np.ndarray) -> np.ndarray:
        sent = getattr(self.policy, "sent", None)
        return action if sent is None else sent


class DemoRecorder(Hook):
    """Records an episode as a :class:`~detaug_gym.data.Demo`: the non-obstacle observations and the simulator
    state before each action, the policy's actions (the targets) and, with ``keep_sent`` when a hook changed
    any of them, the sent ones."""

    needs_states = True

    def __init__(self, keep_sent: bool = False) -> None:
        self.keep_sent = keep_sent
        self.steps: list[Step] = []

    def on_step(self, step: Step) -> None:
        self.steps.append(step)

    def demo(self, attrs: dict) -> Demo:
        keys = [k for k in self.steps[0].obs if is_recorded(k)]
        actions = np.asarray([s.action for s in self.steps], dtype=np.float32)
        sent = np.asarray([s.sent for s in self.steps], dtype=np.float32)
        dones = np.asarray([float(s.terminated) for s in self.steps], dtype=np.float32)
        return Demo(
            actions=actions,
            states=np.asarray([s.state for s in self.steps], dtype=np.float64),
            obs={k: np.asarray([s.obs[k] for s in self.steps], dtype=np.float32) for k in keys},
            gripper_command=actions[:, -1].copy(),
            attrs=attrs,
            rewards=np.asarray([s.reward for s in self.steps], dtype=np.float32),
            dones=dones,
            executed_actions=sent if self.keep_sent and not np.array_equal(sent, actions) else None,
        )


def record_episode(env, policy, task: int, init_state: int, seed: int, env_id: str,
                   noise: ActionNoise | None = None, tail_steps: int = 0) -> tuple[Demo, bool]:
    """Run one episode and record it; returns the demo and whether it succeeded.

    With ``noise`` the env gets the disturbed action and the demo records the policy's clean one as
    ``actions`` (and the disturbed one as ``executed_actions``); so does a policy that acts out a mistake on
    purpose (the expert's ``fumble``: :class:`ActedOutHook`, applied before the noise). With ``tail_steps`` the
    recording goes on that many steps past the first success (the env's step limit no longer applies then, and
    the tail is not disturbed), and the episode counts as a success only if the task is still solved at its end.
    """
    options = {"init_state": init_state}
    if len(env.unwrapped.tasks) > 1:
        options["task"] = task
    acted = [ActedOutHook(policy)] if getattr(policy, "fumble", 0.0) > 0 else []
    recorder = DemoRecorder(keep_sent=noise is not None or bool(acted))
    hooks = [*acted, *([] if noise is None else [NoiseHook(noise, seed)]), recorder]
    result = rollout(env, policy, seed=seed, options=options, hooks=hooks, stop=until_done(tail_steps))
    base = env.unwrapped
    attrs = {
        "env_id": env_id,
        "task": int(task),
        "task_key": base.task_spec.key,
        "init_state": int(init_state),
        "seed": int(seed),
        "controller": json.dumps(controller_settings(base.controller)),
    }
    if getattr(base, "layout", "libero") != "libero":
        attrs["layout"] = base.episode_layout
    if tail_steps:
        attrs["tail_steps"] = int(tail_steps)
    if acted:
        attrs["fumble"] = float(policy.fumble)
    if noise is not None:
        attrs["action_noise"] = json.dumps({"sigma": noise.sigma, "tau": noise.tau, "duty": noise.duty,
                                            "burst": noise.burst, "dims": "xyz"})
    solved = any(s.terminated for s in recorder.steps)
    return recorder.demo(attrs), solved and bool(result.info.get("is_success", False))


def parse_tasks(spec: str, num_tasks: int) -> list[int]:
    if spec == "all":
        return list(range(num_tasks))
    try:
        task = int(spec)
    except ValueError:
        raise SystemExit(f"--task must be an index in [0, {num_tasks}) or 'all', got {spec!r}") from None
    if not 0 <= task < num_tasks:
        raise SystemExit(f"--task {task} out of range: this env has tasks 0..{num_tasks - 1}")
    return [task]


def _policy_spec(spec: str) -> tuple[str, dict]:
    """``"scripted:fumble=0.5"`` -> ``("scripted", {"fumble": 0.5})``, checked as the bench checks methods."""
    from detaug_gym.bench import parse_method

    return parse_method(spec)


def collect(args: CollectArgs) -> list[TaskStats]:
    """Run the collection described by ``args``; returns per-task statistics."""
    from tqdm import tqdm

    env_kwargs = {key: value for key, value in (("controller", args.controller), ("layout", args.layout),
                                                ("max_episode_steps", args.max_steps)) if value is not None}
    env = gym.make(args.env, **env_kwargs)
    base = env.unwrapped
    tasks = parse_tasks(args.task, len(base.tasks))
    name, options = _policy_spec(args.policy)
    policy = make_policy(name, **options)
    noise = (ActionNoise(args.action_noise, args.noise_tau, args.noise_duty, args.noise_burst)
             if args.action_noise > 0 else None)
    env_args = {"env_name": args.env, "env_version": getattr(detaug_gym, "__version__", "0"),
                "type": "detaug_gym", "env_kwargs": env_kwargs}
    max_attempts = args.max_attempts or 2 * args.demos
    stats = [TaskStats(t, base.tasks[t].key) for t in tasks]
    try:
        with DatasetWriter(args.out, env_args) as writer, \
                tqdm(total=len(tasks) * args.demos, desc=args.env, unit="demo") as bar:
            for st in stats:
                start = time.perf_counter()
                for i in range(max_attempts):
                    if st.kept >= args.demos:
                        break
                    init_state, seed = i % base.suite.num_init_states, demo_seed(args.seed, st.task, i)
                    if writer.has(st.task, init_state, seed):
                        st.kept += 1
                        st.resumed += 1
                        bar.update(1)
                        continue
                    demo, ok = record_episode(env, policy, st.task, init_state, seed, args.env, noise,
                                              args.tail_steps)
                    st.attempts += 1
                    if ok:
                        writer.append(demo)
                        st.kept += 1
                        st.steps += len(demo)
                        bar.update(1)
                    bar.set_postfix(task=st.task, kept=st.kept, tried=st.attempts)
                st.seconds = time.perf_counter() - start
    finally:
        env.close()
    return stats


def format_table(stats: list[TaskStats]) -> str:
    rows = ["| task | key | kept | new attempts | success | mean length | time (s) |",
            "|---:|---|---:|---:|---:|---:|---:|"]
    for st in stats:
        new = st.kept - st.resumed
        rate = f"{100.0 * new / st.attempts:.1f}%" if st.attempts else "-"
        length = f"{st.steps / new:.0f}" if new else "-"
        rows.append(f"| {st.task} | {st.key} | {st.kept} | {st.attempts} | {rate} | {length} | {st.seconds:.0f} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    parser = build_parser(CollectArgs, prog="python -m detaug_gym.collect", description=__doc__)
    try:
        args = config_from_namespace(CollectArgs, parser.parse_args(argv))
    except ValueError as exc:
        parser.error(str(exc))
    start = time.perf_counter()
    stats = collect(args)
    print(format_table(stats))
    print(f"wrote {args.out} in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
