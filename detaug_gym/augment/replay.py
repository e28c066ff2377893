"""Execute a :class:`~detaug_gym.augment.plan.Plan` in the env and record what really happened.

Copied steps (interaction windows, margins, the untouched rest) reproduce the source's *commands*: the
gripper command bit for bit, and the arm's OSC goal in the world frame. An OSC_POSE delta action is
relative to the end-effector pose at which it is sent, so once an arc has put the arm in a (slightly)
different state, re-sending the source's raw deltas would re-play the source's goals shifted by that
error, and the error never closes (a 4 mm miss at the window start grew to 1.7 cm at the grasp in our
tests). Instead the copied step sends the delta that puts the controller's goal where the source's was
(:func:`~detaug_gym.actions.action_to_goal` then :func:`~detaug_gym.actions.goal_to_action`, with
``s = POS_SCALE``, ``r = ROT_SCALE`` of :mod:`detaug_gym.actions`):

    goal_src = p_src + s a_src[:3],  R_goal_src = exp(r a_src[3:6]) R_src,
    a[:3] = (goal_src - p) / s,      a[3:6] = rotvec(R_goal_src R^T) / r,   a[6] = a_src[6],

which equals the source's action exactly when the state equals the source's. Steps before the first arc
send the source's actions unchanged (``raw_prefix``), so an unbent demo replays bit for bit.

Transit steps are closed loop: the OSC_POSE delta that moves the controller's goal from the *measured*
end-effector pose to the next arc target,

    a_pos = (p*_{t+1} + lead (p*_{t+1} - p*_t) - p_t) / s,   a_rot = rotvec(R*_{t+1} R_t^T) / r,

clipped to [-1, 1]. The ``lead`` term feeds
the target's own velocity forward: robosuite's OSC is a critically damped spring towards a goal that is
reset every step, so without it the arm lags a moving target. The arc ends with zero speed (min-jerk), so
the arm is on the source's pose when the copied interaction window starts.

The recorded demo is the replay itself (states, observations, actions), so the data are consistent with
the env by construction. Replay stops at the first success (as the source collection does), or after the
plan plus ``extra_steps`` hold steps. A source recorded with ``collect --tail-steps N`` (attribute
``tail_steps``) is replayed N steps past its first success too, so the copies also show the expert letting go.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from detaug_gym.actions import action_to_goal, goal_to_action
from detaug_gym.augment.feasibility import grip_frame_position
from detaug_gym.augment.plan import Plan
from detaug_gym.rollout import Hook, Step, rollout, step_limit, until_done
from detaug_gym.rotations import quat_xyzw_to_mat


@dataclass(frozen=True)
class ReplayConfig:
    """Tracking and acceptance of the replay.

    Attributes:
        lead: velocity feed-forward of the tracker (steps of target motion added to the goal).
        tolerance: largest eef distance (m) from the planned arc during a transit.
        offset_tolerance: drift (m) of the held object in the grip-site frame during a carry allowed on top
            of the drift the source's own carry shows.
        grasp_tolerance: largest distance (m) between where a held object sits in the grip-site frame when its
            carry starts and where it sat in the source: the copied grasp must still take the object the way
            the source's did (a bent approach can nudge a bowl propped on the ramekin by 1-3 cm, and the copied
            grasp then closes elsewhere on it; such copies still succeed, but teach a worse grasp).
        extra_steps: hold steps allowed after the plan for the success check to fire.
        raw_prefix: send the source's raw actions until the first arc starts (bit-identical prefix).
    """

    lead: float = 1.0
    tolerance: float = 0.015
    offset_tolerance: float = 0.01
    grasp_tolerance: float = 0.008
    extra_steps: int = 10
    raw_prefix: bool = True


@dataclass
class Recording:
    """What the replay produced; arrays have one row per executed step."""

    actions: list[np.ndarray] = field(default_factory=list)
    states: list[np.ndarray] = field(default_factory=list)
    obs: list[dict[str, np.ndarray]] = field(default_factory=list)
    success: bool = False
    max_deviation: float = 0.0
    max_offset_drift: float = 0.0

    def stacked_obs(self) -> dict[str, np.ndarray]:
        return {k: np.stack([o[k] for o in self.obs]) for k in self.obs[0]}


def tracking_action(pos: np.ndarray, rot: np.ndarray, target_pos: np.ndarray, target_rot: np.ndarray,
                    prev_target_pos: np.ndarray, grip: float, lead: float) -> np.ndarray:
    """The OSC_POSE delta action (7,) from the pose ``pos`` (3,), ``rot`` (3, 3) towards the next target (see the
    module docstring)."""
    goal = target_pos + lead * (target_pos - prev_target_pos)
    return goal_to_action(pos, rot, goal, target_rot, grip)


def source_goal_action(pos: np.ndarray, rot: np.ndarray, src_pos: np.ndarray, src_rot: np.ndarray,
                       src_action: np.ndarray) -> np.ndarray:
    """The action (7,) whose OSC goal equals the goal the source's ``src_action`` (7,) set from its own pose
    ``src_pos`` (3,), ``src_rot`` (3, 3), sent from the pose ``pos``, ``rot``."""
    goal_pos, goal_rot = action_to_goal(src_pos, src_rot, src_action)
    return goal_to_action(pos, rot, goal_pos, goal_rot, float(np.clip(src_action[6], -1.0, 1.0)))


def distance_to_polyline(point: np.ndarray, poly: np.ndarray) -> float:
    """Euclidean distance from ``point`` (3,) to the polyline ``poly`` (N, 3)."""
    a, b = poly[:-1], poly[1:]
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", point - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-18), 0, 1)
    return float(np.min(np.linalg.norm(a + t[:, None] * ab - point, axis=1)))


def tail_steps(demo) -> int:
    """Steps a source demo recorded past its first success (``collect --tail-steps``; 0 for older files)."""
    return int(demo.attrs.get("tail_steps", 0))


def length_limit(env, demo, max_length: int | None) -> int:
    """Longest acceptable copy of ``demo``: ``max_length``, else the env's episode limit plus the demo's tail."""
    if max_length:
        return int(max_length)
    limit = step_limit(env)
    return (10 ** 9 if limit is None else limit) + tail_steps(demo)


class PlanFollower:
    """The policy that executes a :class:`Plan`: the source's raw actions before the first arc (with
    ``raw_prefix``), the source's goals on copied steps, closed-loop tracking on arcs, then holds
    (see the module docstring). It reads the end-effector pose from the scene in float64."""

    def __init__(self, scene, plan: Plan, source_actions: np.ndarray, config: ReplayConfig) -> None:
        self.scene, self.plan, self.source_actions, self.config = scene, plan, source_actions, config
        self.first_arc = plan.spans[0].start if plan.spans else plan.n_steps
        self.i = 0

    def reset(self, seed: int | None = None) -> None:
        self.i = 0

    def act(self, obs) -> np.ndarray:
        plan, i = self.plan, self.i
        self.i += 1
        if i >= plan.n_steps:
            action = np.zeros(7)
            action[6] = plan.gripper[-1]
            return action
        if plan.source_step[i] >= 0 and (self.config.raw_prefix and i < self.first_arc):
            return np.asarray(self.source_actions[plan.source_step[i]], dtype=np.float64)
        pos, quat = self.scene.eef_pose()
        if plan.source_step[i] >= 0:
            return source_goal_action(pos, quat_xyzw_to_mat(quat), plan.target_pos[i],
                                      quat_xyzw_to_mat(plan.target_quat[i]), self.source_actions[plan.source_step[i]])
        return tracking_action(pos, quat_xyzw_to_mat(quat), plan.target_pos[i + 1],
                               quat_xyzw_to_mat(plan.target_quat[i + 1]), plan.target_pos[i], plan.gripper[i],
                               self.config.lead)


class PlanRecorder(Hook):
    """Records the replay (obs, states, sent actions) and how well it tracked: the eef's largest distance from
    its span's arc and the held object's drift in the grip-site frame (``held_body``: span index -> body)."""

    needs_states = True

    def __init__(self, scene, plan: Plan, held_body: dict[int, int] | None) -> None:
        self.scene, self.plan, self.held_body = scene, plan, held_body or {}
        self.span_of = np.full(plan.n_steps, -1)
        for k, span in enumerate(plan.spans):
            self.span_of[span.start:span.end] = k
        self.offsets: dict[int, np.ndarray] = {}
        self.rec = Recording()
        self.solved = False

    def on_step(self, step: Step) -> None:
        rec, plan = self.rec, self.plan
        self.solved |= bool(step.info["is_success"])
        rec.obs.append(step.obs)
        rec.states.append(step.state)
        rec.actions.append(np.asarray(step.sent, dtype=np.float64))
        k = int(self.span_of[step.index]) if step.index < plan.n_steps else -1
        if k >= 0:
            span = plan.spans[k]
            pos, _ = self.scene.eef_pose()
            arc = plan.target_pos[span.start:span.end + 1]
            rec.max_deviation = max(rec.max_deviation, distance_to_polyline(pos, arc))
            body = self.held_body.get(k)
            if body is not None:
                rec.max_offset_drift = max(rec.max_offset_drift, _offset_drift(self.scene, body, self.offsets, k))


def run_plan(env, obs: dict, plan: Plan, source_actions: np.ndarray, config: ReplayConfig,
             held_body: dict[int, int] | None = None, tail: int = 0) -> Recording:
    """Step ``env`` (already at the source's first frame, ``obs`` its observation) through ``plan``.

    ``held_body`` maps span index -> body id of the object carried in that span (carries only); its pose in
    the grip-site frame is watched for drift. ``tail``: steps recorded past the first success; the replay
    then succeeds only if the task is still solved at the end.
    """
    base = env.unwrapped
    recorder = PlanRecorder(base.scene, plan, held_body)
    result = rollout(base, PlanFollower(base.scene, plan, source_actions, config), start=lambda _: (obs, {}),
                     hooks=[recorder], stop=until_done(tail, truncation=False),
                     max_steps=plan.n_steps + config.extra_steps + tail, dtype=None)
    rec = recorder.rec
    rec.success = recorder.solved and bool(result.info.get("is_success", False))
    return rec


def _offset_drift(scene, body: int, offsets: dict[int, np.ndarray], key: int) -> float:
    """Distance the body moved in the grip-site frame since the span's first step."""
    local = grip_frame_position(scene.data, scene.eef_site, body)
    if key not in offsets:
        offsets[key] = local
    return float(np.linalg.norm(local - offsets[key]))
