"""The one rollout loop: every episode in the project (bench, collection, demo replay, augmentation replay)
steps its env here, and what differs between them is a hook on this loop.

    result = rollout(env, policy, seed=3, options={"task": 1}, hooks=[recorder])

The loop: start the episode (``env.reset(seed, options)``, or ``start(env)`` for a restored frame), reset the
policy with the seed and the :class:`EpisodeContext`, then per step ``action = policy.act(obs)``, each hook's
:meth:`Hook.transform` in turn (action noise), ``env.step``, each hook's :meth:`Hook.on_step` (recording,
metrics), until ``stop(step)`` (default: terminated or truncated). Only this module and ``detaug_gym/envs/``
call ``env.step``.

:func:`run_episode` is the bench's episode: a metrics hook, a collision attribution, the policy's per-episode
summary and an :class:`EpisodeRecord` (one JSON line); it never raises.
"""

from __future__ import annotations

import inspect
import math
import time
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from detaug_gym.policies.base import Policy


@dataclass(frozen=True)
class EpisodeContext:
    """What a policy may know about its episode beyond the observation (a policy may ignore it).

    Attributes:
        env_id: the registered id (``"SafeLibero-Spatial-L2-v0"``).
        suite: suite name (``"spatial"``); level: ``"L1" | "L2" | "Free"``.
        task: task index into the level's task list; task_key: its short name; instruction: its language.
        seed: the episode's seed (None when unseeded).
    """

    env_id: str
    suite: str
    level: str
    task: int
    task_key: str
    instruction: str
    seed: int | None = None


def episode_context(env, seed: int | None = None) -> EpisodeContext | None:
    """The context of the episode ``env`` is in (after a reset); None for envs that are not ours."""
    base = env.unwrapped
    suite = getattr(base, "suite", None)
    if suite is None or getattr(base, "episode", None) is None:
        return None
    spec = base.task_spec
    return EpisodeContext(suite.env_id(base.level, base.version), suite.name, base.level, int(base.episode.task),
                          spec.key, spec.language, seed)


@dataclass
class Step:
    """One transition. ``action`` is the policy's, ``sent`` what the env received (after the hooks'
    transforms); ``state`` the flattened simulator state before the step (only when a hook asks for it)."""

    index: int
    obs: dict[str, np.ndarray]
    action: np.ndarray
    sent: np.ndarray
    next_obs: dict[str, np.ndarray]
    reward: float
    terminated: bool
    truncated: bool
    info: dict
    state: np.ndarray | None = None


class Hook:
    """An observer of the rollout loop; override what you need. ``needs_states = True`` makes the loop read
    the simulator state before every step into :attr:`Step.state`."""

    needs_states = False

    def on_start(self, env, obs: dict[str, np.ndarray], info: dict) -> None:
        """Called once the episode has started, before the first action."""

    def transform(self, action: np.ndarray) -> np.ndarray:
        """The action to send instead of ``action`` (7,) (default: unchanged)."""
        return action

    def on_step(self, step: Step) -> None:
        """Called after every env step."""


@dataclass
class RolloutResult:
    """How a rollout ended: ``steps`` taken, the last ``obs`` / ``info``, and the start's ``info``."""

    steps: int
    obs: dict[str, np.ndarray]
    info: dict
    start_info: dict
    context: EpisodeContext | None = None


def until_done(tail_steps: int = 0, truncation: bool = True) -> Callable[[Step], bool]:
    """Stop rule: the episode's end (terminated, or truncated unless ``truncation=False``), or with
    ``tail_steps`` that many steps past the first success (the step limit no longer applies in the tail)."""
    solved_at: list[int] = []

    def stop(step: Step) -> bool:
        if not solved_at and step.terminated:
            solved_at.append(step.index)
        if not solved_at:
            return truncation and step.truncated
        return step.index - solved_at[0] >= tail_steps

    return stop


class Rollout:
    """One episode, stepped from outside: :meth:`begin`, then :meth:`advance` with the policy's action until
    :attr:`done`. :func:`rollout` drives one; :func:`run_episodes` drives several in lockstep. Arguments as in
    :func:`rollout`."""

    def __init__(self, env, policy: Policy, *, seed: int | None = None, options: Mapping | None = None,
                 start: Callable[[object], tuple[dict, dict]] | None = None, hooks: Iterable[Hook] = (),
                 stop: Callable[[Step], bool] | None = None, max_steps: int | None = None,
                 dtype: type | None = np.float32) -> None:
        self.env, self.policy, self.seed, self.options, self._start = env, policy, seed, options, start
        self.hooks, self.stop, self.max_steps, self.dtype = list(hooks), stop or until_done(), max_steps, dtype
        self.steps, self.done = 0, False
        self.obs: dict[str, np.ndarray] = {}
        self.info: dict = {}
        self.start_info: dict = {}
        self.context: EpisodeContext | None = None

    def begin(self) -> dict[str, np.ndarray]:
        """Start the episode (env, policy, hooks); returns the first observation."""
        env = self.env
        obs, info = self._start(env) if self._start is not None else env.reset(seed=self.seed,
                                                                               options=dict(self.options or {}))
        self.context = episode_context(env, self.seed)
        reset_policy(self.policy, self.seed, self.context)
        for hook in self.hooks:
            hook.on_start(env, obs, info)
        self.obs, self.info, self.start_info = obs, info, info
        self._states = any(h.needs_states for h in self.hooks)
        self.done = self.max_steps is not None and self.max_steps <= 0
        return obs

    def advance(self, action: np.ndarray) -> bool:
        """Send the policy's ``action`` through the hooks to the env; returns :attr:`done`."""
        action = np.asarray(action, dtype=self.dtype)
        sent = action
        for hook in self.hooks:
            sent = hook.transform(sent)
        state = self.env.unwrapped.get_state() if self._states else None
        next_obs, reward, terminated, truncated, info = self.env.step(sent)
        step = Step(self.steps, self.obs, action, sent, next_obs, float(reward), bool(terminated), bool(truncated),
                    info, state)
        self.steps += 1
        for hook in self.hooks:
            hook.on_step(step)
        self.obs, self.info = next_obs, info
        self.done = self.stop(step) or (self.max_steps is not None and self.steps >= self.max_steps)
        return self.done

    def result(self) -> RolloutResult:
        return RolloutResult(self.steps, self.obs, self.info, self.start_info, self.context)


def rollout(env, policy: Policy, *, seed: int | None = None, options: Mapping | None = None,
            start: Callable[[object], tuple[dict, dict]] | None = None, hooks: Iterable[Hook] = (),
            stop: Callable[[Step], bool] | None = None, max_steps: int | None = None,
            dtype: type | None = np.float32) -> RolloutResult:
    """Run one episode of ``policy`` in ``env`` through ``hooks`` (see the module docstring).

    Args:
        env: a gymnasium env (wrapped or not); the loop steps exactly this object.
        policy: anything with ``reset(seed=...)`` and ``act(obs)``; ``reset`` also gets ``context=`` when it
            accepts it.
        seed, options: passed to ``env.reset`` (ignored with ``start``).
        start: ``env -> (obs, info)`` that starts the episode instead of ``env.reset`` (e.g. ``env.restore``).
        stop: ``Step -> bool``, called after the hooks; default :func:`until_done`.
        max_steps: hard cap on the steps of this rollout, whatever ``stop`` says.
        dtype: the policy's actions are cast to it (float32, the action space's); None sends them as they
            are (the augmentation replay's float64 tracking actions).
    """
    run = Rollout(env, policy, seed=seed, options=options, start=start, hooks=hooks, stop=stop,
                  max_steps=max_steps, dtype=dtype)
    run.begin()
    while not run.done:
        run.advance(policy.act(run.obs))
    return run.result()


def step_limit(env) -> int | None:
    """The step limit an episode of ``env`` runs under: gymnasium's ``TimeLimit`` (``gym.make``), else the
    env's own ``max_episode_steps``, else its suite's."""
    spec = getattr(env, "spec", None)
    if spec is not None and spec.max_episode_steps is not None:
        return int(spec.max_episode_steps)
    base = env.unwrapped
    own = getattr(base, "max_steps", None)
    if own is not None:
        return int(own)
    suite = getattr(base, "suite", None)
    return None if suite is None else int(suite.max_steps)


_ACCEPTS_CONTEXT: dict[type, bool] = {}


def reset_policy(policy: Policy, seed: int | None, context: EpisodeContext | None) -> None:
    """``policy.reset(seed=seed, context=context)``, or without ``context`` for policies written to the
    older one-argument protocol."""
    cls = type(policy)
    if cls not in _ACCEPTS_CONTEXT:
        params = inspect.signature(policy.reset).parameters
        _ACCEPTS_CONTEXT[cls] = "context" in params or any(p.kind is p.VAR_KEYWORD for p in params.values())
    if _ACCEPTS_CONTEXT[cls]:
        policy.reset(seed=seed, context=context)
    else:
        policy.reset(seed=seed)


# ---------------------------------------------------------------------------------------------- the bench's episode
@dataclass(frozen=True)
class EpisodeKey:
    """Identifies an episode; every method sees the same (env_id, task, episode, seed) rollout."""

    method: str
    env_id: str
    task: int
    episode: int
    seed: int

    def as_tuple(self) -> tuple:
        return (self.method, self.env_id, self.task, self.episode, self.seed)


@dataclass
class EpisodeRecord:
    """One JSON line of the bench: what happened in one episode.

    ``summary`` is the policy's own account of the episode (``policy.episode_summary()``, when it has one:
    DetAug's selected costs, AEGIS's interventions, CAPE's guided replans). ``obstacle_pose`` is the settled
    pose (position, xyzw quaternion) the collision rule measures from; ``first_collision_step`` the step
    (1-based) at which the obstacle first moved; ``steps`` the episode's length (ETS); ``run_seed`` the bench
    seed the episode seed derives from; ``video`` the mp4 of the episode when one was rendered; ``goals`` the
    task's number of sub-goals (goal predicates) and ``goals_met`` the most of them that held at one step (a Long
    episode that placed one of its two objects and timed out has 1 of 2).
    """

    method: str
    env_id: str
    suite: str
    level: str
    task: int
    episode: int
    seed: int
    init_state: int | None = None
    obstacle: str | None = None
    success: bool = False
    collision: bool = False
    contact: bool = False
    steps: int = 0
    min_clearance: float | None = None
    wall_time: float = 0.0
    termination: str = "error"  # "success" | "timeout" | "error"
    error: str | None = None
    task_key: str | None = None
    summary: dict = field(default_factory=dict)
    run_seed: int = 0
    obstacle_pose: list[float] | None = None
    first_collision_step: int | None = None
    video: str | None = None
    collision_cause: dict | None = None
    goals: int | None = None
    goals_met: int | None = None

    def to_json(self) -> dict:
        return asdict(self)


class ObstacleMetrics(Hook):
    """The episode's start (init state, obstacle) and, over its steps, collision (latched), robot contact and
    the smallest clearance; kept even when the episode later fails."""

    def __init__(self) -> None:
        self.collision = self.contact = False
        self.clearance = math.inf
        self.start_info: dict = {}
        self.obstacle_pose: list[float] | None = None
        self.first_collision: int | None = None
        self.steps = 0

    def on_start(self, env, obs: dict[str, np.ndarray], info: dict) -> None:
        self.start_info = info
        if float(np.asarray(obs.get("obstacle_mask", [0.0])).ravel()[0]) >= 0.5:
            self.obstacle_pose = [round(float(v), 6) for v in obs["obstacle_pose"]]

    def on_step(self, step: Step) -> None:
        self.steps += 1
        if step.info["collision"] and self.first_collision is None:
            self.first_collision = self.steps
        self.collision |= bool(step.info["collision"])
        self.contact |= bool(step.info["robot_obstacle_contact"])
        self.clearance = min(self.clearance, float(step.info["min_clearance"]))


class GoalProgress(Hook):
    """The task's number of sub-goals and the most of them that held at one step."""

    def __init__(self) -> None:
        self.goals: int | None = None
        self.best = 0

    def on_start(self, env, obs: dict[str, np.ndarray], info: dict) -> None:
        self.goals, self.best = int(info["goals"]), int(info["goals_met"])

    def on_step(self, step: Step) -> None:
        self.best = max(self.best, int(step.info["goals_met"]))


RECENT_TOUCH = 5  # steps: a touch this recent before the obstacle moved is taken as the hit
BODY_KINDS = {"link": "link", "gripper": "gripper", "held": "held_object", "object": "object"}


class CollisionAttribution(Hook):
    """Who moved the obstacle, when, and what the policy believed then.

    At the first collision step (the obstacle's displacement passes SafeLIBERO's threshold) it keeps who
    touched the obstacle: the env's ``obstacle_contacts`` of that step, or of the last step that touched it
    when that was at most :data:`RECENT_TOUCH` steps before, or else the env's ``collision_bodies`` (what was
    within a few cm when the hit left no contact at the step's end); and the policy's ``belief()``, when it
    has one. At the end of the
    episode the executed gripper commands are cut into phases the way the augmentation cuts demos
    (:meth:`~detaug_gym.augment.segment.Segmentation.phase`), which places the collision step in one.

    :meth:`cause` gives the record's ``collision_cause``: ``step`` (1-based, as ``first_collision_step``),
    ``contact_step`` (the step of the contacts used), ``first_touch_step`` (the first step anything touched
    the obstacle), ``bodies`` (the contact labels), ``body`` (their kinds joined by ``+``: ``link``,
    ``gripper``, ``held_object``, ``object``; ``none`` when nothing was seen touching it), ``phase``,
    ``bent`` (whether DetAug's augmentation bends that part of a demo: a transit, not a window or margin),
    ``robot_clearance`` (m, the env's exact robot-to-obstacle distance after that step),
    and from the belief ``plan_deviation`` (rad, largest joint difference between the planned and the
    executed arm configuration after that step) with everything else the policy reported (``plan_cost``,
    ``zero_cost_share``, ...).
    """

    def __init__(self, policy: Policy | None = None) -> None:
        self.policy = policy
        self.commands: list[float] = []
        self.step: int | None = None
        self.first_touch: int | None = None
        self._last_touch: tuple[int, tuple[str, ...]] | None = None
        self._cause: dict = {}

    def on_step(self, step: Step) -> None:
        self.commands.append(float(step.sent[-1]))
        contacts = tuple(step.info.get("obstacle_contacts", ()))
        if contacts:
            self._last_touch = (step.index + 1, contacts)
            self.first_touch = self.first_touch or step.index + 1
        if self.step is not None or not step.info["collision"]:
            return
        self.step = step.index + 1
        contact_step, bodies = self._last_touch or (None, ())
        if contact_step is None or self.step - contact_step > RECENT_TOUCH:
            near = tuple(step.info.get("collision_bodies", ()))
            contact_step, bodies = (self.step, near) if near else (None, ())
        if contact_step is not None and (self.first_touch is None or contact_step < self.first_touch):
            self.first_touch = contact_step  # a hit between two steps' contact lists
        kinds = sorted({BODY_KINDS[b.split(":", 1)[0]] for b in bodies})
        self._cause = {"step": self.step, "contact_step": contact_step, "bodies": list(bodies),
                       "body": "+".join(kinds) or "none", "robot_clearance": float(step.info["min_clearance"])}
        belief = getattr(self.policy, "belief", None)
        belief = dict(belief(step.next_obs)) if callable(belief) else {}
        planned = belief.pop("planned_joint_pos", None)
        if planned is not None:
            executed = np.asarray(step.next_obs["robot_joint_pos"], np.float64)
            belief["plan_deviation"] = float(np.abs(np.asarray(planned) - executed).max())
        self._cause.update(belief)

    def cause(self) -> dict | None:
        """The collision's attribution (see the class docstring), or None when the obstacle never moved."""
        if self.step is None:
            return None
        from detaug_gym.augment.segment import segment_gripper  # here: its import loads MuJoCo (see bench.main)

        seg = segment_gripper(np.asarray(self.commands))
        frame = self.step - 1
        return {**self._cause, "first_touch_step": self.first_touch, "phase": seg.phase(frame),
                "bent": not bool(seg.frozen_mask()[frame])}


class BenchEpisode:
    """The bench's episode as a :class:`Rollout` with its metrics, collision attribution and record."""

    def __init__(self, env, policy: Policy, key: EpisodeKey, suite: str, level: str, hooks: Iterable[Hook] = (),
                 run_seed: int = 0, options: dict | None = None) -> None:
        self.policy = policy
        self.record = EpisodeRecord(key.method, key.env_id, suite, level, key.task, key.episode, key.seed,
                                    run_seed=run_seed)
        self.metrics, self.attribution, self.progress = ObstacleMetrics(), CollisionAttribution(policy), GoalProgress()
        self.run = Rollout(env, policy, seed=key.seed, options={**(options or {}), "task": key.task},
                           hooks=[self.metrics, self.attribution, self.progress, *hooks])
        self.finished = False
        self._start = time.perf_counter()

    def begin(self) -> None:
        self._guard(self.run.begin)

    def advance(self, action: np.ndarray | BaseException) -> None:
        """Step with the policy's action (or record the exception the policy raised instead of acting)."""
        if isinstance(action, BaseException):
            self.fail(action)
        else:
            self._guard(self.run.advance, action)

    def _guard(self, fn, *args) -> None:
        try:
            fn(*args)
        except Exception as exc:  # one broken episode (policy bug, simulator instability) must not stop a run
            self.fail(exc)
            return
        if self.run.done:
            self._finish()

    def fail(self, exc: BaseException) -> None:
        self.record.error = f"{type(exc).__name__}: {exc}\n" + "".join(traceback.format_exception(exc, limit=3))
        self.record.termination = "error"
        self.finished = True

    def _finish(self) -> None:
        rec, result = self.record, self.run.result()
        try:
            rec.task_key = result.context.task_key if result.context else None
            rec.success = bool(result.info["is_success"])
            rec.termination = "success" if rec.success else "timeout"
            summary = getattr(self.policy, "episode_summary", None)
            rec.summary = dict(summary()) if callable(summary) else {}
        except Exception as exc:
            self.fail(exc)
        self.finished = True

    def result(self) -> EpisodeRecord:
        """The finished episode's record (metrics kept even when it failed)."""
        rec, metrics = self.record, self.metrics
        rec.init_state, rec.obstacle = metrics.start_info.get("init_state"), metrics.start_info.get("obstacle")
        rec.collision, rec.contact, rec.steps = metrics.collision, metrics.contact, metrics.steps
        rec.obstacle_pose, rec.first_collision_step = metrics.obstacle_pose, metrics.first_collision
        rec.collision_cause = self.attribution.cause()
        if self.progress.goals is not None:  # None when the episode failed before it started
            rec.goals, rec.goals_met = self.progress.goals, self.progress.best
        rec.min_clearance = None if math.isinf(metrics.clearance) else metrics.clearance
        rec.wall_time = time.perf_counter() - self._start
        return rec


def run_episode(env, policy: Policy, key: EpisodeKey, suite: str, level: str, hooks: Iterable[Hook] = (),
                run_seed: int = 0, options: dict | None = None) -> EpisodeRecord:
    """Roll ``policy`` out in ``env`` for one episode (with extra ``hooks``, e.g. a video; reset ``options``
    beyond the task, e.g. an official ``episode``); never raises (errors are recorded)."""
    return run_episodes([env], [policy], [key], suite, level, [list(hooks)], run_seed, [options])[0]


def run_episodes(envs: Sequence, policies: Sequence[Policy], keys: Sequence[EpisodeKey], suite: str, level: str,
                 hooks: Sequence[Iterable[Hook]] | None = None, run_seed: int = 0,
                 options: Sequence[dict | None] | None = None, batcher=None) -> list[EpisodeRecord]:
    """Episodes ``keys[i]`` of ``policies[i]`` in ``envs[i]``, stepped in lockstep; the actions of each step come
    from :func:`~detaug_gym.policies.act_batch` (with a shared ``batcher``, flow policies that replan at the
    same step share one network call). An episode ends on its own; one that errors is recorded and the others
    go on. Never raises."""
    from detaug_gym.policies.base import act_batch

    n = len(envs)
    episodes = [BenchEpisode(envs[i], policies[i], keys[i], suite, level, (hooks or [()] * n)[i], run_seed,
                             (options or [None] * n)[i]) for i in range(n)]
    for episode in episodes:
        episode.begin()
    while active := [e for e in episodes if not e.finished]:
        actions = act_batch([e.policy for e in active], [e.run.obs for e in active], batcher)
        for episode, action in zip(active, actions):
            episode.advance(action)
    return [e.result() for e in episodes]
