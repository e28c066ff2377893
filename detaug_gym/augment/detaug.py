"""DetAug mode: replace each transit of a free-space demo with a random circular arc and label it.

Per source demo and per requested copy, up to ``tries`` samples are drawn: one ``(phi, theta)`` per
bendable transit, assembled into a plan (:mod:`~detaug_gym.augment.plan`), checked (length, IK,
joint limits / speed / acceleration, collisions; :mod:`~detaug_gym.augment.feasibility`), and replayed
in the env (:mod:`~detaug_gym.augment.replay`). The first sample that passes becomes the copy; every
failed sample adds one count to its rejection reason.

Label layout: grasp ``k`` owns entries ``4k..4k+3`` = (approach label, carry label), each
``phi * (cos theta, sin theta)``; unbent transits and missing grasps are zeros. The size is fixed per suite,
4 x the most grasps a task of the suite has (the suite registry's ``max_grasps``).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import asdict, dataclass, field

import numpy as np

from detaug_gym.augment.arcs import arc_label, sample_arc
from detaug_gym.augment.context import SourceContext, reset_to_demo
from detaug_gym.augment.feasibility import FeasibilityConfig
from detaug_gym.augment.ik import IKConfig
from detaug_gym.augment.plan import ArcSample, Plan, Timing, build_plan
from detaug_gym.augment.replay import Recording, ReplayConfig, length_limit, run_plan, tail_steps
from detaug_gym.augment.segment import SegmentConfig
from detaug_gym.envs.suites import suite_of_env

LABEL_PER_GRASP = 4


def suite_of(env_id: str) -> str:
    """The suite name of a registered env id (``"spatial"`` for ``SafeLibero-Spatial-Free-v0``)."""
    return suite_of_env(env_id)[0].name


def label_size(env_id: str) -> int:
    """Fixed label length for the suite of ``env_id``: 4 x its most grasps per task
    (:attr:`~detaug_gym.envs.suites.SuiteSpec.max_grasps`)."""
    return LABEL_PER_GRASP * suite_of_env(env_id)[0].max_grasps


@dataclass(frozen=True)
class StageConfigs:
    """The pipeline stages every augmentation mode shares (segmentation, timing, IK, feasibility, replay).

    Attributes:
        tries: samples drawn per requested copy before giving up on that copy.
        max_length: longest augmented demo (steps); None: the env's episode limit plus the source's tail.
        validate: keep a replayed sample only if it succeeds and tracks its plan (samples are always
            replayed: the replay is what records the demo's states and observations).
    """

    tries: int = 4
    max_length: int | None = None
    validate: bool = True
    segment: SegmentConfig = field(default_factory=SegmentConfig)
    timing: Timing = field(default_factory=Timing)
    ik: IKConfig = field(default_factory=IKConfig)
    feasibility: FeasibilityConfig = field(default_factory=FeasibilityConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class DetAugConfig(StageConfigs):
    """Everything that shapes DetAug samples; stored with every augmented demo.

    Attributes:
        phi_range: arc half-angle range (rad); paper: [0.15 pi, 0.85 pi].
        theta_range: plane rotation range (rad); paper: [0, pi].
    """

    phi_range: tuple[float, float] = (0.15 * np.pi, 0.85 * np.pi)
    theta_range: tuple[float, float] = (0.0, np.pi)


@dataclass
class SourceResult:
    """What one source produced: accepted demos and the fate of every sample."""

    demos: list = field(default_factory=list)
    tries: int = 0
    reasons: Counter = field(default_factory=Counter)
    seconds: float = 0.0


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


def try_sample(ctx: SourceContext, samples: list[ArcSample], config: DetAugConfig,
               max_length: int) -> tuple[Plan | None, Recording | None, str | None]:
    """Plan, check and (optionally) replay one sample; returns (plan, recording, rejection reason)."""
    plan = build_plan(ctx.pos, ctx.quat, ctx.demo.gripper_command, samples, config.timing)
    if plan.n_steps > max_length:
        return plan, None, "too_long"
    for k in range(len(plan.spans)):
        reason = ctx.check_span(plan, k, config.feasibility)
        if reason is not None:
            return plan, None, reason
    obs = reset_to_demo(ctx.env, ctx.demo)
    held = {k: ctx.held[ctx.transit_index(span.sample.transit)] for k, span in enumerate(plan.spans)}
    held_body = {k: h.body for k, h in held.items() if h is not None}
    rec = run_plan(ctx.env, obs, plan, ctx.demo.actions, config.replay, held_body, tail=tail_steps(ctx.demo))
    if not config.validate:  # the replay still records the data; it just is not judged
        return plan, rec, None
    return plan, rec, ctx.replay_reason(plan, rec, config.replay)


def source_skip_reason(ctx: SourceContext, label_len: int) -> str | None:
    """Why a source cannot be augmented at all (counted once), or None."""
    grasps = len(ctx.segmentation.grasps)
    if grasps == 0:
        return "no_grasp"
    if LABEL_PER_GRASP * grasps > label_len:
        return "too_many_grasps"
    if not any(ctx.bendable.values()):
        return "no_transit"
    return None


def augment_source(env, demo, copies: int, rng: np.random.Generator, config: DetAugConfig,
                   label_len: int) -> SourceResult:
    """Up to ``copies`` accepted augmentations of ``demo`` (see the module docstring)."""
    start = time.perf_counter()
    result = SourceResult()
    ctx = SourceContext.build(env, demo, config.segment, config.ik, config.feasibility.penetration)
    max_length = length_limit(env, demo, config.max_length)
    skip = source_skip_reason(ctx, label_len)
    if skip is not None:
        result.reasons[skip] += 1
        result.seconds = time.perf_counter() - start
        return result
    for _ in range(copies):
        for _ in range(config.tries):
            samples = sample_transits(ctx, rng, config)
            result.tries += 1
            plan, rec, reason = try_sample(ctx, samples, config, max_length)
            if reason is not None:
                result.reasons[reason] += 1
                continue
            result.demos.append(augmented_demo(demo, samples, plan, rec, config, label_len))
            break
    result.seconds = time.perf_counter() - start
    return result


def augmented_demo(source, samples: list[ArcSample], plan: Plan, rec: Recording, config: DetAugConfig,
                   label_len: int):
    """A :class:`~detaug_gym.data.Demo` holding the replay of an accepted sample, its label and provenance."""
    from detaug_gym.data import Demo

    actions = np.asarray(rec.actions, dtype=np.float32)
    n = len(actions)
    rewards = np.zeros(n, dtype=np.float32)
    rewards[-1] = float(rec.success)
    transits = [{"kind": s.sample.transit.kind, "grasp": s.sample.transit.grasp,
                 "source_start": s.sample.transit.start, "source_end": s.sample.transit.end,
                 "start": s.start, "end": s.end, "phi": s.sample.phi, "theta": s.sample.theta,
                 "arc_length": s.arc_len, "chord": s.chord} for s in plan.spans]
    attrs = dict(source.attrs)
    attrs.pop("num_samples", None)
    attrs.update({
        "source_demo": source.name,
        "augmented": True,
        "augment_mode": "detaug",
        "phi": [s.phi for s in samples],
        "theta": [s.theta for s in samples],
        "transits": transits,
        "max_deviation": rec.max_deviation,
        "max_offset_drift": rec.max_offset_drift,
        "augment_params": _jsonable(config.as_dict()),
    })
    return Demo(actions=actions, states=np.asarray(rec.states), obs=rec.stacked_obs(),
                gripper_command=actions[:, -1].copy(), attrs=attrs,
                label=make_label(samples, label_len).astype(np.float32), rewards=rewards, dones=rewards.copy())


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


# ---------------------------------------------------------------------------------------------- CLI hooks
def add_arguments(parser) -> None:
    """DetAug's options of ``python -m detaug_gym.augment``."""
    g = parser.add_argument_group("detaug")
    g.add_argument("--phi", type=float, nargs=2, default=(0.15, 0.85), metavar=("MIN", "MAX"),
                   help="arc half-angle range in units of pi (default 0.15 0.85)")
    g.add_argument("--theta", type=float, nargs=2, default=(0.0, 1.0), metavar=("MIN", "MAX"),
                   help="arc plane rotation range in units of pi (default 0 1)")
    g.add_argument("--margin", type=float, default=0.4, help="s kept on both sides of a window (default 0.4)")
    g.add_argument("--window", type=float, default=0.25, help="half-width (s) of an interaction window (0.25)")
    g.add_argument("--tries", type=int, default=4, help="samples per requested copy (default 4)")
    g.add_argument("--max-length", type=int, default=None, help="longest demo in steps (default: env limit)")
    g.add_argument("--max-speed", type=float, default=0.012, help="planned peak eef speed, m/step (0.012)")
    g.add_argument("--timing", choices=("trapezoid", "min_jerk", "source"), default="trapezoid",
                   help="progress profile along an arc (default trapezoid)")
    g.add_argument("--tolerance", type=float, default=0.015, help="max eef distance from the arc on replay (m)")
    g.add_argument("--grasp-tolerance", type=float, default=0.008,
                   help="max shift (m) of a held object in the hand at the start of its carry, against the source")
    g.add_argument("--no-validate", action="store_true",
                   help="keep samples whose replay fails or leaves the arc (not recommended)")


def make_config(ns) -> DetAugConfig:
    """The :class:`DetAugConfig` of parsed command-line options."""
    if ns.phi[0] < 0 or ns.phi[1] >= 1 or ns.phi[0] > ns.phi[1]:
        raise SystemExit("error: --phi needs 0 <= MIN <= MAX < 1 (units of pi)")
    if ns.theta[0] > ns.theta[1]:
        raise SystemExit("error: --theta needs MIN <= MAX")
    if ns.tries < 1:
        raise SystemExit("error: --tries must be >= 1")
    return DetAugConfig(
        phi_range=(ns.phi[0] * np.pi, ns.phi[1] * np.pi),
        theta_range=(ns.theta[0] * np.pi, ns.theta[1] * np.pi),
        tries=ns.tries,
        max_length=ns.max_length,
        validate=not ns.no_validate,
        segment=SegmentConfig(margin_s=ns.margin, window_s=ns.window),
        timing=Timing(profile=ns.timing, max_speed=ns.max_speed),
        replay=ReplayConfig(tolerance=ns.tolerance, grasp_tolerance=ns.grasp_tolerance),
    )
