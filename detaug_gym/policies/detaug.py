"""DetAug: sample K augmentation labels, generate K plans in one batch, execute the least-colliding one.

At every replan (every ``action_steps`` env steps) a fresh batch of K labels is drawn uniformly from the
training support (the labels of the augmented demos of the current task), the K plans are generated in
one batched call, each plan's joint trajectory is scored by the penetration of the robot's surface points
into the observed obstacle (``detaug_gym.geometry``), and the best plan is executed. Among equally good
plans (e.g. no obstacle in view, all costs zero) the least bent one (smallest label norm) wins, so free
space is crossed the way the unaugmented demos cross it.

The score also covers the object in the hand (``held_object``, default on): its observed surface points,
carried with the grip site while the plan's fingers stay closed. The paper scores the robot only; in the
bench half of the obstacle collisions came without any robot contact, from the carried bowl. The obstacle is
inflated by ``inflate`` (1.5 cm) before penetration is scored, the measured error of the scorer's geometry
(docs/detaug.md). ``held_object=False, inflate=0`` is the paper's score.

When none of the K plans is free, up to ``wider_batches`` (2) more batches are drawn with labels bent up to 2x
and 3x the training support, and the choice is over all of them; a replan with a free plan among the first K
is the paper's. ``wider_batches=0`` is the paper's selection (docs/detaug.md, "Wider batches").

Options reproduce the paper's ablations: ``k``, ``latch`` (keep the first choice for the episode),
``labels="zero"`` (K samples with the unbent label), ``cost="clearance"``, and the selection-vs-guidance
variants ``mode="null_guidance"`` (null token + guidance, no selection), ``"guided_select"`` (guidance and
selection) and ``"null_select"`` (selection over null-token samples).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch

from detaug_gym.geometry.obstacle_view import has_obstacle
from detaug_gym.models.flow import Guidance
from detaug_gym.models.policy import FlowPolicy, load_checkpoint, zoo_dir
from detaug_gym.policies.options import DetAugOptions


@dataclass
class ReplanDiagnostics:
    """What one replan decided."""

    label: np.ndarray
    best_cost: float
    median_cost: float
    k: int
    zero_share: float


class DetAugPolicy(FlowPolicy):
    """DetAug label selection on a checkpoint trained with labels (``python -m detaug_gym.train --method detaug``).

    Args:
        suite: loads ``policies/detaug/<suite>/`` unless ``checkpoint`` is given.
        checkpoint: a checkpoint folder.
        k: candidates per replan (paper: 32).
        latch: keep the first selected label for the whole episode (the paper found this halves clean success).
        labels: ``"support"`` (the paper's draw: uniform within the task's training support, see
            :meth:`sample_labels`), ``"random"`` (rows of the task's training labels) or ``"zero"`` (the unbent
            label for all K candidates).
        cost: ``"penetration"`` (paper) or ``"clearance"``.
        mode: one of :data:`~detaug_gym.policies.options.MODES` (selection vs guidance ablation).
        guidance_scale, guidance_t_min: lambda and chi of the guidance variants.
        held_object: also score the object in the hand (:func:`detaug_gym.geometry.held_object_cost`).
        inflate: metres the obstacle is inflated by for the penetration score (the scorer's model error;
            0 and ``held_object=False`` together are the paper's score).
        tiebreak_margin: metres beyond ``inflate``; among plans of equal (lowest) cost the one penetrating least
            into the obstacle inflated by this much more wins, before the least bent (0: the least bent, as
            the paper's selection).
        support: also score penetration into what the obstacle stands on (a pedestal or base), whose
            displacement moves the obstacle.
        support_scale: ``labels="support"`` draws phi up to this multiple of the largest training phi (1: the
            training support, the paper's).
        wider_batches: when none of the K candidates is free, draw up to this many more batches of K, the
            i-th (from 1) with phi up to ``(1 + i) * support_scale`` times the largest training phi, until one
            holds a free plan; the choice is over every batch drawn (0: one batch, the paper's; default 2).
        commit: from the second replan on, the previous label is a candidate and wins ties of lowest cost
            before the least bent, so a detour is kept while it stays free (false: the paper's fresh draw).
        action_steps, flow_steps, seed: see :class:`~detaug_gym.models.policy.FlowPolicy`.

    Every option, its type and its range are :class:`~detaug_gym.policies.options.DetAugOptions`.
    """

    zoo_method = "detaug"

    def __init__(self, suite: str = "spatial", checkpoint: str | None = None, k: int = 32, latch: bool = False,
                 labels: str = "support", cost: str = "penetration", mode: str = "select",
                 guidance_scale: float = 3.0, guidance_t_min: float = 0.8, held_object: bool = True,
                 inflate: float = 0.015, tiebreak_margin: float = 0.0, support: bool = True,
                 support_scale: float = 1.0, wider_batches: int = 2, commit: bool = False, **options) -> None:
        opts = DetAugOptions.from_kwargs(suite=suite, checkpoint=checkpoint, k=k, latch=latch, labels=labels,
                                         cost=cost, mode=mode, guidance_scale=guidance_scale,
                                         guidance_t_min=guidance_t_min, held_object=held_object, inflate=inflate,
                                         tiebreak_margin=tiebreak_margin, support=support,
                                         support_scale=support_scale, wider_batches=wider_batches, commit=commit,
                                         **options)
        ckpt = load_checkpoint(opts.checkpoint or zoo_dir("detaug", opts.suite))
        if not ckpt.network.config.dit.label_dim:
            raise ValueError(f"{ckpt.path} was trained without labels ({ckpt.method!r}); DetAug needs a "
                             "checkpoint from `python -m detaug_gym.train --method detaug`")
        if opts.labels != "zero" and len(ckpt.labels.bank) == 0:
            raise ValueError(f"{ckpt.path} stores no training labels to sample from")
        super().__init__(ckpt, **opts.flow_policy_kwargs())
        self.k, self.latch, self.label_source, self.cost_kind, self.mode = (opts.k, opts.latch, opts.labels,
                                                                            opts.cost, opts.mode)
        self.guidance_scale, self.guidance_t_min = opts.guidance_scale, opts.guidance_t_min
        self.held_object, self.inflate, self.tiebreak_margin = opts.held_object, opts.inflate, opts.tiebreak_margin
        self.support, self.support_scale, self.wider_batches = opts.support, opts.support_scale, opts.wider_batches
        self.commit = opts.commit
        self.diagnostics: list[ReplanDiagnostics] = []
        self._latched: np.ndarray | None = None
        self._rng = np.random.default_rng()

    def reset(self, seed: int | None = None, context=None) -> None:
        super().reset(seed, context)
        self._rng = np.random.default_rng(seed)
        self._latched = None
        self.diagnostics = []

    def episode_summary(self) -> dict:
        """Replans, and the selected plans' predicted costs (mean, max, replans whose best plan still cost > 0)."""
        best = [d.best_cost for d in self.diagnostics]
        return {"replans": len(best), "selected_cost_mean": float(np.mean(best)) if best else 0.0,
                "selected_cost_max": float(np.max(best)) if best else 0.0,
                "replans_with_cost": int(sum(c > 0.0 for c in best))}

    def belief(self, obs: Mapping[str, np.ndarray] | None = None) -> dict:
        """:meth:`FlowPolicy.belief` plus the replan's choice: the selected plan's predicted ``plan_cost``,
        the ``zero_cost_share`` of the K candidates, ``candidates`` (K), the selected ``label`` and
        ``label_change`` (its distance to the previous replan's label; None at the first replan). Given
        ``obs`` with an obstacle, also how the scorer judges the state reached: ``executed_cost`` (its score
        of that one configuration, robot and held object) and ``executed_clearance`` (m, its robot-to-obstacle
        distance, :func:`~detaug_gym.geometry.robot_clearance`)."""
        belief = super().belief(obs)
        if not self.diagnostics:
            return belief
        last = self.diagnostics[-1]
        change = (float(np.linalg.norm(last.label - self.diagnostics[-2].label)) if len(self.diagnostics) > 1
                  else None)
        belief.update(plan_cost=last.best_cost, zero_cost_share=last.zero_share, candidates=last.k,
                      label=[float(v) for v in last.label], label_change=change)
        if obs is not None and has_obstacle(obs):
            belief.update(self._judge(obs))
        return belief

    def _judge(self, obs: Mapping[str, np.ndarray]) -> dict:
        from detaug_gym.geometry import obstacle_sdf, robot_clearance

        observation = dict(obs)
        single = {k: np.asarray(v)[None] for k, v in observation.items()}
        state = torch.from_numpy(self.layout.state_vector(single)).double()
        row = torch.cat([state, state.new_zeros(1, self.layout.action_dim)], dim=-1)[:, None]  # (1, 1, D)
        with torch.no_grad():
            cost = float(self._plan_cost(row, observation)[0])
            clearance = float(robot_clearance(state[0, self.layout.key_slice("robot_joint_pos")], observation,
                                              obstacle_sdf(observation, support=self.support)))
        return {"executed_cost": cost, "executed_clearance": clearance}

    # ------------------------------------------------------------------ selection
    def sample_labels(self, obs: Mapping[str, np.ndarray], k: int, scale: float | None = None) -> np.ndarray:
        """(k, L) labels for the current task. ``labels="support"`` (default): the unbent label, then k - 1
        labels drawn uniformly within the task's training support, each transit (a pair of label entries,
        ``phi (cos theta, sin theta)``) on its own: ``phi`` and ``theta`` uniform between the smallest and
        largest of that transit's bent training labels, ``phi``'s top stretched by ``scale`` (default
        ``support_scale``; a transit never bent in training stays unbent).
        ``"random"``: rows of the task's training labels (uniform, without replacement when there are enough);
        the bank holds one zero row per unaugmented demo, so this draws the unbent label far more often than
        any detour (37-68 % of the K on Spatial). ``"zero"``: zeros."""
        if self.label_source == "zero":
            return np.zeros((k, self.label_dim), np.float32)
        bank, tasks = self.labels.bank, self.labels.task
        task = int(np.argmax(obs["task_id"])) if "task_id" in obs else -1
        rows = np.flatnonzero(tasks == task)
        rows = rows if len(rows) else np.arange(len(bank))
        if self.label_source == "support":
            return self._support_labels(bank[rows], k, self.support_scale if scale is None else scale)
        pick = self._rng.choice(rows, size=k, replace=len(rows) < k)
        return bank[pick].astype(np.float32)

    def _support_labels(self, bank: np.ndarray, k: int, scale: float) -> np.ndarray:
        out = np.zeros((k, self.label_dim), np.float32)
        for j in range(0, self.label_dim, 2):
            phi, theta = np.hypot(bank[:, j], bank[:, j + 1]), np.arctan2(bank[:, j + 1], bank[:, j])
            bent = phi > 0.0
            if not bent.any():
                continue
            p = self._rng.uniform(phi[bent].min(), phi[bent].max() * scale, k - 1)
            t = self._rng.uniform(theta[bent].min(), theta[bent].max(), k - 1)
            out[1:, j], out[1:, j + 1] = p * np.cos(t), p * np.sin(t)
        return out

    def next_plan(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        if self._latched is not None:
            return self.plan(obs, self._latched[None], num_samples=1)[0].numpy()
        use_labels = self.mode in ("select", "guided_select")
        k = 1 if self.mode == "null_guidance" else self.k
        labels = self.sample_labels(obs, k) if use_labels else None
        kept = labels is not None and self.commit and bool(self.diagnostics) and k > 1
        if kept:
            labels[-1] = self.diagnostics[-1].label  # the previous choice stands as the last candidate
        guidance = self._guidance(obs) if self.mode in ("null_guidance", "guided_select") else None
        plans = self.plan(obs, labels, num_samples=k, guidance=guidance)
        costs = self.score(plans, obs)
        if labels is not None:
            labels, plans, costs = self._widen(obs, labels, plans, costs, guidance)
            k = len(labels)
        norms = np.zeros(k) if labels is None else np.linalg.norm(labels, axis=1)
        rounded = np.round(costs, 6)
        keys = [norms, rounded]  # lowest cost, then least bent
        if kept:
            keys.insert(1, np.arange(k) != self.k - 1)  # lowest cost, then the previous label, then least bent
        tied = rounded == rounded.min()
        if self.tiebreak_margin > 0.0 and has_obstacle(obs) and tied.sum() > 1:
            wide = np.full(k, np.inf)
            wide[tied] = self.score(plans[torch.from_numpy(tied)], obs, self.inflate + self.tiebreak_margin)
            keys.insert(1, np.round(wide, 6))  # lowest cost, then least into the wider margin, then least bent
        best = int(np.lexsort(keys)[0])
        chosen = labels[best] if labels is not None else np.zeros(self.label_dim, np.float32)
        self.diagnostics.append(ReplanDiagnostics(chosen, float(costs[best]), float(np.median(costs)), k,
                                                  float(np.mean(costs <= 0.0))))
        if self.latch and labels is not None:
            self._latched = chosen
        return plans[best].numpy()

    def _widen(self, obs, labels: np.ndarray, plans: torch.Tensor, costs: np.ndarray, guidance):
        """``wider_batches``: while no candidate is free, another batch of K with a wider phi range, appended.
        Returns labels (N, L), plans (N, H, D) and costs (N,) over every batch drawn (N = K x batches)."""
        for i in range(1, self.wider_batches + 1):
            if costs.min() <= 0.0:
                break
            more = self.sample_labels(obs, self.k, scale=(1 + i) * self.support_scale)
            more_plans = self.plan(obs, more, num_samples=self.k, guidance=guidance)
            labels, plans = np.concatenate([labels, more]), torch.cat([plans, more_plans])
            costs = np.concatenate([costs, self.score(more_plans, obs)])
        return labels, plans, costs

    def score(self, plans: torch.Tensor, obs: Mapping[str, np.ndarray], inflate: float | None = None) -> np.ndarray:
        """(K,) collision cost of plans (K, H, D) against the observed obstacle inflated by ``inflate`` (default
        the policy's; 0 without an obstacle), in float32: 25 % faster than float64 and within 1e-5 m of it, far
        below the SDF grid's own error (benchmarks/detaug_latency.py); a plan that clears the inflated obstacle
        costs exactly 0 either way."""
        if not has_obstacle(obs):
            return np.zeros(len(plans))
        with torch.no_grad():  # not inference_mode: the geometry caches tensors that guidance differentiates
            return self._plan_cost(plans.float(), dict(obs), inflate).double().numpy()

    def _plan_cost(self, plans: torch.Tensor, obs: dict[str, np.ndarray], inflate: float | None = None) -> torch.Tensor:
        """(...) cost of plans (..., H, D): the robot's points, plus the held object's points if enabled."""
        from detaug_gym.geometry import held_object_cost, obstacle_sdf, plan_collision_cost

        sdf = obstacle_sdf(obs, support=self.support)
        margin = (self.inflate if inflate is None else inflate) if self.cost_kind == "penetration" else None
        cost = plan_collision_cost(plans[..., self.layout.key_slice("robot_joint_pos")], obs, kind=self.cost_kind,
                                   sdf=sdf, margin=margin)
        if self.held_object:
            cost = cost + held_object_cost(plans[..., self.layout.key_slice("eef_pos")],
                                           plans[..., self.layout.key_slice("gripper_qpos")], obs, sdf,
                                           kind=self.cost_kind, margin=margin)
        return cost

    def _guidance(self, obs: Mapping[str, np.ndarray]) -> Guidance | None:
        if not has_obstacle(obs):
            return None
        observation = dict(obs)

        def cost(plan: torch.Tensor, t: float) -> torch.Tensor:
            return self._plan_cost(plan, observation)

        return Guidance(cost, scale=self.guidance_scale, t_min=self.guidance_t_min)
