"""CAPE: receding-horizon re-noising of the frozen ``base`` flow policy with collision guidance.

Each episode starts with a plan sampled from noise (flow time 0 -> 1, guidance in the late steps). Then,
every ``prefix_steps`` (2) env steps:

1. the unexecuted remainder of the previous plan is shifted to start now (:func:`shift_plan`: drop the
   executed prefix, pad the end like the training windows);
2. it is re-noised to flow time ``t_start = 1 - delta`` (default 0.5; CAPE's delta = 0.08 is 0.92 in our
   convention, where the flow runs from t = 0 noise to t = 1 data), with the current robot state inpainted;
3. the remaining Euler steps are integrated (``refine_steps``; default the steps a ``flow_steps``
   schedule has left after ``t_start``: 5 of 10) with guidance ``x <- x - lambda grad cost`` at every step
   with ``t >= chi`` (``guidance_t_min`` 0.8: every refine step, and the last two of a fresh plan);
4. the first ``prefix_steps`` actions of the result are executed.

Cost: hinge ``sum max(0, r + margin - sdf(centre))`` over the end-effector spheres
(:class:`~detaug_gym.geometry.RobotSpheres`: three spheres of radius ``sphere_radius`` over the palm and the
fingers) and the plan steps, with the shared FK and obstacle SDF (``detaug_gym.geometry``; the state term
equals ``plan_collision_cost(..., kind="spheres")``). A plan here holds joint states *and* OSC actions,
and only the actions are executed, so the cost is evaluated twice (``guide="both"``):

- ``states``: spheres placed by FK of the plan's joint states; its gradient moves the states, which
  reaches the actions only through later network evaluations (none after the last Euler step);
- ``actions``: the same spheres carried along the end-effector path the plan's actions command,
  ``p_{t+1} = p_t + gain * POS_SCALE * a_t[:3]`` (``action_gain`` 0.25: the fraction of the commanded 5 cm a
  step that the OSC controller achieves at steady state, measured on the Spatial env), with the hand's
  orientation from FK; its gradient moves the executed actions away from the obstacle.

Without an obstacle (mask 0) there is no guidance; the re-noising still happens.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from detaug_gym.actions import POS_SCALE
from detaug_gym.geometry.costs import DEFAULT_MARGIN, sphere_cost
from detaug_gym.geometry.obstacle_view import has_obstacle
from detaug_gym.geometry.robot_points import EEF_SPHERE_RADIUS, RobotGeometry, RobotSpheres
from detaug_gym.geometry.sdf import ObstacleSDF, obstacle_sdf
from detaug_gym.models.flow import Guidance
from detaug_gym.models.policy import FlowPolicy, load_checkpoint, shift_plan, zoo_dir
from detaug_gym.policies.options import CapeOptions


@dataclass(frozen=True)
class CapeStep:
    """One replan: ``fresh`` (sampled from noise) or re-noised, whether guidance acted, and the cost of
    the result (NaN unless ``track_cost``)."""

    fresh: bool
    guided: bool
    cost: float


class CapePolicy(FlowPolicy):
    """CAPE on a flow checkpoint (default ``policies/base/<suite>/``).

    Args:
        suite: zoo suite folder of the ``base`` policy.
        checkpoint: a checkpoint folder instead of the zoo's.
        prefix_steps: actions executed from each plan before re-noising the rest (CAPE: ~2).
        t_start: flow time the remainder is re-noised to (1 - delta). Default 0.5: with the zoo's base, trained
            on recovery demos, the paper's 0.92 never lets a plan change course (0 of 80 Spatial L1/L2 episodes
            solved, the hand wanders above the bowl); 0.5 solved 14 of 80 (``docs/methods.md``).
        refine_steps: Euler steps from ``t_start`` to 1 (default: what ``flow_steps`` leaves, at least 1).
        guidance_scale: lambda, the gradient step (in normalised plan coordinates).
        guidance_t_min: chi, guidance acts at flow times ``t >= chi``.
        sphere_radius: radius (m) of the end-effector spheres (CAPE: 0.06-0.08).
        margin: hinge margin (m) added to the radius.
        guide: ``"both"``, ``"states"`` or ``"actions"``: which part of the plan the cost sees (module doc).
        action_gain: achieved fraction of the commanded displacement per step (``actions`` term).
        track_cost: record the cost of every executed plan in ``diagnostics`` (one more FK pass per replan).
        support: also guide away from what the obstacle stands on (a pedestal or base; off by default, as
            measured best for CAPE: :class:`~detaug_gym.policies.options.CapeOptions`).
        **options: :class:`~detaug_gym.models.policy.FlowPolicy` options (``flow_steps``, ``seed``, ...).

    Every option, its type and its range are :class:`~detaug_gym.policies.options.CapeOptions`.
    """

    zoo_method = "base"

    def __init__(self, suite: str = "spatial", checkpoint: str | None = None, prefix_steps: int = 2,
                 t_start: float = 0.5, refine_steps: int | None = None, guidance_scale: float = 3.0,
                 guidance_t_min: float = 0.8, sphere_radius: float = EEF_SPHERE_RADIUS,
                 margin: float = DEFAULT_MARGIN["spheres"], guide: str = "both", action_gain: float = 0.25,
                 track_cost: bool = False, support: bool = False, **options) -> None:
        if "action_steps" in options:
            raise ValueError("CAPE executes prefix_steps actions per plan; pass prefix_steps, not action_steps")
        opts = CapeOptions.from_kwargs(
            suite=suite, checkpoint=checkpoint, prefix_steps=prefix_steps, t_start=t_start, refine_steps=refine_steps,
            guidance_scale=guidance_scale, guidance_t_min=guidance_t_min, sphere_radius=sphere_radius, margin=margin,
            guide=guide, action_gain=action_gain, track_cost=track_cost, support=support, **options)
        ckpt = load_checkpoint(opts.checkpoint or zoo_dir("base", opts.suite))
        if not opts.prefix_steps < ckpt.network.config.dit.horizon:
            raise ValueError(f"prefix_steps must lie in [1, horizon), got {opts.prefix_steps}")
        super().__init__(ckpt, action_steps=opts.prefix_steps, **opts.flow_policy_kwargs())
        self.t_start, self.refine_steps = opts.t_start, opts.refine_steps
        self.guidance_scale, self.guidance_t_min = opts.guidance_scale, opts.guidance_t_min
        self.margin, self.guide, self.action_gain = opts.margin, opts.guide, opts.action_gain
        panda = RobotGeometry.panda()
        spheres = RobotSpheres.end_effector(panda.kinematics, radius=opts.sphere_radius)
        self.robot = RobotGeometry(panda.kinematics, panda.points, spheres)
        self.track_cost, self.support = opts.track_cost, opts.support
        self.diagnostics: list[CapeStep] = []
        self._previous: torch.Tensor | None = None

    @property
    def prefix_steps(self) -> int:
        return self.action_steps

    def reset(self, seed: int | None = None, context=None) -> None:
        super().reset(seed, context)
        self._previous = None
        self.diagnostics = []

    def episode_summary(self) -> dict:
        """Replans, and how many of them were guided (an obstacle in view) or sampled fresh from noise."""
        return {"replans": len(self.diagnostics), "guided_replans": sum(d.guided for d in self.diagnostics),
                "fresh_plans": sum(d.fresh for d in self.diagnostics)}

    def belief(self, obs: Mapping[str, np.ndarray] | None = None) -> dict:
        """:meth:`FlowPolicy.belief` plus whether the replan was guided and, with ``track_cost``, the
        guided plan's sphere cost (``plan_cost``)."""
        belief = super().belief(obs)
        if self.diagnostics:
            last = self.diagnostics[-1]
            belief["guided"] = last.guided
            if np.isfinite(last.cost):
                belief["plan_cost"] = last.cost
        return belief

    def next_plan(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        cost = self.cost_function(obs)
        guidance = None if cost is None else Guidance(cost, self.guidance_scale, self.guidance_t_min)
        fresh = self._previous is None
        if fresh:
            plans = self.plan(obs, None, num_samples=1, guidance=guidance)
        else:
            remainder = shift_plan(self._previous[None], executed=self.action_steps)
            plans = self.plan(obs, None, init_plan=remainder, t_start=self.t_start, steps=self.refine_steps,
                              guidance=guidance)
        self._previous = plans[0]
        final = float("nan")
        if self.track_cost:
            with torch.no_grad():
                final = 0.0 if cost is None else float(cost(plans, 1.0)[0])
        self.diagnostics.append(CapeStep(fresh, cost is not None, final))
        return plans[0].numpy()

    # ------------------------------------------------------------------ cost
    def cost_function(self, obs: Mapping[str, np.ndarray]):
        """``cost(plans (K, H, D) physical, t) -> (K,)`` for this observation, or ``None`` without an obstacle."""
        if not has_obstacle(obs):
            return None
        observation = dict(obs)
        sdf, robot = obstacle_sdf(observation, support=self.support), self.robot.aligned_to(observation)
        fingers = torch.as_tensor(np.asarray(obs["gripper_qpos"], np.float64))

        def cost(plans: torch.Tensor, t: float) -> torch.Tensor:
            return self.collision_cost(plans, robot, sdf, fingers)

        return cost

    def collision_cost(self, plans: torch.Tensor, robot: RobotGeometry, sdf: ObstacleSDF,
                       fingers: torch.Tensor | None = None) -> torch.Tensor:
        """(K,) sphere hinge cost of physical plans (K, H, D) on the states, the actions or both (``guide``)."""
        joints = plans[..., self.layout.key_slice("robot_joint_pos")]
        fk = robot.kinematics(joints, None if fingers is None else fingers.to(joints.dtype))
        centres = robot.spheres.world(fk)  # (K, H, S, 3)
        radii = robot.spheres.radii_tensor(centres)
        total = torch.zeros(plans.shape[:-2], dtype=plans.dtype)
        if self.guide in ("both", "states"):
            total = total + sphere_cost(centres, radii, sdf, self.margin)
        if self.guide in ("both", "actions"):
            moves = self.action_gain * POS_SCALE * plans[..., self.layout.action_slice][..., :-1, :3]
            start = fk.eef_position[..., :1, :].detach()  # the current grip site (inpainted state)
            path = torch.cat([start, start + torch.cumsum(moves, dim=-2)], dim=-2)  # (K, H, 3)
            hand = (centres - fk.eef_position[..., None, :]).detach()  # sphere layout from the FK orientation
            total = total + sphere_cost(hand + path[..., None, :], radii, sdf, self.margin)
        return total
