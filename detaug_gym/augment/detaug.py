"""DetAug mode: replace each transit of a free-space demo with a random circular arc and label it.

A sample draws one ``(phi, theta)`` per bendable transit and assembles the plan
(:mod:`~detaug_gym.augment.plan`); the engine (:mod:`~detaug_gym.augment.engine`) checks it (length, IK,
joint limits / speed / acceleration, collisions), replays it and keeps the first sample per copy that passes.

Label layout: grasp ``k`` owns entries ``4k..4k+3`` = (approach label, carry label), each
``phi * (cos theta, sin theta)``; unbent transits and missing grasps are zeros. The size is fixed per suite,
4 x the most grasps a task of the suite has (the suite registry's ``max_grasps``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from detaug_gym.augment.arcs import arc_label, sample_arc
from detaug_gym.augment.context import SourceContext
from detaug_gym.augment.engine import Mode, Proposal, StageConfigs
from detaug_gym.augment.plan import ArcSample, build_plan
from detaug_gym.envs.suites import SuiteSpec

LABEL_PER_GRASP = 4


@dataclass(frozen=True)
class DetAugConfig(StageConfigs):
    """Everything that shapes DetAug samples; stored with every augmented demo.

    Attributes:
        phi_range: arc half-angle range (rad); paper: [0.15 pi, 0.85 pi].
        theta_range: plane rotation range (rad); paper: [0, pi].
    """

    phi_range: tuple[float, float] = (0.15 * np.pi, 0.85 * np.pi)
    theta_range: tuple[float, float] = (0.0, np.pi)


@dataclass(frozen=True)
class DetAugSource:
    """What DetAug keeps per source: the context and the suite's label length."""

    ctx: SourceContext
    label_len: int


def sample_transits(ctx: SourceContext, rng: np.random.Generator, config: DetAugConfig) -> list[ArcSample]:
    """One arc per bendable transit (phi = 0 for the others)."""
    samples = []
    for i, tr in enumerate(ctx.segmentation.transits):
        if ctx.bendable[i]:
            phi, theta = sample_arc(rng, config.phi_range, config.theta_range)
        else:
            phi, theta = 0.0, 0.0
        samples.append(ArcSample(tr, phi, theta))
    return samples


def make_label(samples: list[ArcSample], size: int) -> np.ndarray:
    """The demo's label (size,): approach then carry of each grasp, zero padded."""
    label = np.zeros(size)
    for s in samples:
        slot = 2 * s.transit.grasp + (0 if s.transit.kind == "approach" else 1)
        label[2 * slot:2 * slot + 2] = arc_label(s.phi, s.theta) if s.phi != 0.0 else 0.0
    return label


class DetAugMode(Mode):
    """Random labelled arcs (see the module docstring)."""

    name = "detaug"
    config_cls = DetAugConfig

    def label_size(self, suite: SuiteSpec) -> int:
        """4 x the suite's most grasps per task (:attr:`~detaug_gym.envs.suites.SuiteSpec.max_grasps`)."""
        return LABEL_PER_GRASP * suite.max_grasps

    def prepare(self, ctx: SourceContext, config: DetAugConfig, suite: SuiteSpec) -> DetAugSource:
        return DetAugSource(ctx, self.label_size(suite))

    def skip_reason(self, source: DetAugSource) -> str | None:
        grasps = len(source.ctx.segmentation.grasps)
        if grasps == 0:
            return "no_grasp"
        if LABEL_PER_GRASP * grasps > source.label_len:
            return "too_many_grasps"
        if not any(source.ctx.bendable.values()):
            return "no_transit"
        return None

    def propose(self, source: DetAugSource, rng: np.random.Generator, config: DetAugConfig) -> Proposal:
        ctx = source.ctx
        samples = sample_transits(ctx, rng, config)
        plan = build_plan(ctx.pos, ctx.quat, ctx.demo.gripper_command, samples, config.timing)
        spans = [{"phi": s.sample.phi, "theta": s.sample.theta, "arc_length": s.arc_len} for s in plan.spans]
        return Proposal(plan, make_label(samples, source.label_len),
                        attrs={"phi": [s.phi for s in samples], "theta": [s.theta for s in samples]},
                        span_attrs=spans)

    def add_arguments(self, group) -> None:
        group.add_argument("--phi", type=float, nargs=2, default=(0.15, 0.85), metavar=("MIN", "MAX"),
                           help="arc half-angle range in units of pi (default 0.15 0.85)")
        group.add_argument("--theta", type=float, nargs=2, default=(0.0, 1.0), metavar=("MIN", "MAX"),
                           help="arc plane rotation range in units of pi (default 0 1)")
        group.add_argument("--timing", choices=("trapezoid", "min_jerk", "source"), default="trapezoid",
                           help="progress profile along an arc (default trapezoid)")

    def make_config(self, ns, stages: dict) -> DetAugConfig:
        if ns.phi[0] < 0 or ns.phi[1] >= 1 or ns.phi[0] > ns.phi[1]:
            raise SystemExit("error: --phi needs 0 <= MIN <= MAX < 1 (units of pi)")
        if ns.theta[0] > ns.theta[1]:
            raise SystemExit("error: --theta needs MIN <= MAX")
        return DetAugConfig(**{**stages, "timing": replace(stages["timing"], profile=ns.timing)},
                            phi_range=(ns.phi[0] * np.pi, ns.phi[1] * np.pi),
                            theta_range=(ns.theta[0] * np.pi, ns.theta[1] * np.pi))


MODE = DetAugMode()
