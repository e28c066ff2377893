"""The augmentation engine: what every mode shares, from a source demo to its accepted copies.

A *mode* only proposes plans; the engine does the rest. Per source demo:

1. build the :class:`~detaug_gym.augment.context.SourceContext` (env on the demo's first frame, float64 eef
   poses, segmentation, held objects, IK solver, contact checker) and let the mode prepare its own per-source
   state from it (:meth:`Mode.prepare`); a source the mode cannot use is counted once under
   :meth:`Mode.skip_reason`;
2. for each of ``copies`` copies, up to ``tries`` samples, each: the mode's :meth:`Mode.propose` (every random
   draw of a sample happens there, so a seed gives the same data), then the checks, cheapest first: the
   plan's length (``too_long``), IK / joint limits / speed / acceleration / contacts of every span
   (``SourceContext.check_span``), the closed-loop replay (:func:`~detaug_gym.augment.replay.run_plan`) and
   its checks (``SourceContext.replay_reason``), and the mode's own post-replay check (:meth:`Mode.accept`).
   The first sample that passes becomes the copy; every failed one adds a count to its rejection reason;
3. the accepted replay becomes a :class:`~detaug_gym.data.Demo` (the replay's actions, states and
   observations, reward 1 on the last step when it succeeded) with the provenance every mode writes
   (``source_demo``, ``augmented``, ``augment_mode``, ``transits``, ``max_deviation``, ``max_offset_drift``,
   ``augment_params``) plus the mode's own attributes.

Adding a mode: one file with a :class:`Mode` subclass instance and one line in
:data:`detaug_gym.augment.runner.MODES` (see ``docs/augment.md``).
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import asdict, dataclass, field

import numpy as np

from detaug_gym.augment.context import SourceContext, reset_to_demo
from detaug_gym.augment.feasibility import FeasibilityConfig
from detaug_gym.augment.ik import IKConfig
from detaug_gym.augment.plan import Plan, Timing
from detaug_gym.augment.replay import Recording, ReplayConfig, length_limit, run_plan, tail_steps
from detaug_gym.augment.segment import SegmentConfig
from detaug_gym.envs.suites import SuiteSpec


@dataclass(frozen=True)
class StageConfigs:
    """The pipeline stages every augmentation mode shares (segmentation, timing, IK, feasibility, replay);
    a mode's config extends it with its own fields.

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


@dataclass
class Proposal:
    """One candidate copy, as a mode proposes it.

    Attributes:
        plan: the new timeline of targets (``Plan.spans``: the changed transits).
        label: (L,) the copy's conditioning label, L = the mode's ``label_size`` (0 for none).
        attrs: the mode's own demo attributes (JSON-able), next to the common provenance.
        span_attrs: per span of ``plan``, extra keys of its ``transits`` entry (``phi``, ``rrt_nodes``, ...).
        obstacle_points: (P, 3) world-frame obstacle cloud stored with the demo, or None.
        detail: whatever the mode's :meth:`Mode.accept` needs again (DemoGen: the obstacle).
    """

    plan: Plan
    label: np.ndarray
    attrs: dict = field(default_factory=dict)
    span_attrs: list[dict] = field(default_factory=list)
    obstacle_points: np.ndarray | None = None
    detail: object = None


class Mode:
    """An augmentation mode: how plans are proposed; everything else is the engine's.

    Subclasses set ``name`` and ``config_cls`` and implement :meth:`make_config`, :meth:`prepare` and
    :meth:`propose`; the other hooks have defaults (no label, no options, no skip, no extra check).
    """

    name: str = ""
    config_cls: type[StageConfigs] = StageConfigs

    def label_size(self, suite: SuiteSpec) -> int:
        """Length L of every label this mode writes for ``suite`` (originals get L zeros)."""
        return 0

    def add_arguments(self, group) -> None:
        """The mode's own options (an argparse group); the shared ones are :func:`add_arguments`'s."""

    def make_config(self, ns, stages: dict) -> StageConfigs:
        """A ``config_cls`` from parsed options; ``stages`` holds the shared fields (:func:`stage_options`)."""
        raise NotImplementedError

    def prepare(self, ctx: SourceContext, config: StageConfigs, suite: SuiteSpec) -> object:
        """Per-source state shared by all samples of the source (computed once)."""
        raise NotImplementedError

    def skip_reason(self, source) -> str | None:
        """Why the prepared ``source`` cannot be augmented at all (counted once), or None."""
        return None

    def propose(self, source, rng: np.random.Generator, config: StageConfigs) -> Proposal | str:
        """One sample: a :class:`Proposal`, or the rejection reason when none could be made."""
        raise NotImplementedError

    def accept(self, source, proposal: Proposal, recording: Recording, config: StageConfigs) -> str | None:
        """A mode-specific check of a replay that passed the common ones: a rejection reason, or None."""
        return None


@dataclass
class SourceResult:
    """What one source produced: accepted demos and the fate of every sample."""

    demos: list = field(default_factory=list)
    tries: int = 0
    reasons: Counter = field(default_factory=Counter)
    seconds: float = 0.0


def augment_source(env, demo, copies: int, rng: np.random.Generator, mode: Mode, suite: SuiteSpec,
                   config: StageConfigs | None = None) -> SourceResult:
    """Up to ``copies`` accepted copies of ``demo`` by ``mode`` (see the module docstring); ``config``
    defaults to the mode's ``config_cls()``."""
    config = mode.config_cls() if config is None else config
    if not isinstance(config, mode.config_cls):
        raise TypeError(f"mode {mode.name!r} needs a {mode.config_cls.__name__}, got {type(config).__name__}")
    start = time.perf_counter()
    result = SourceResult()
    ctx = SourceContext.build(env, demo, config.segment, config.ik, config.feasibility.penetration)
    source = mode.prepare(ctx, config, suite)
    max_length = length_limit(env, demo, config.max_length)
    label_len = mode.label_size(suite)
    skip = mode.skip_reason(source)
    if skip is not None:
        result.reasons[skip] += 1
    for _ in range(copies if skip is None else 0):
        for _ in range(config.tries):
            result.tries += 1
            proposal, rec, reason = try_sample(ctx, mode, source, rng, config, max_length)
            if reason is not None:
                result.reasons[reason] += 1
                continue
            result.demos.append(augmented_demo(demo, mode.name, proposal, rec, config, label_len))
            break
    result.seconds = time.perf_counter() - start
    return result


def try_sample(ctx: SourceContext, mode: Mode, source, rng: np.random.Generator, config: StageConfigs,
               max_length: int) -> tuple[Proposal | None, Recording | None, str | None]:
    """One sample: the mode's proposal, its checks (cheapest first) and its replay;
    ``(proposal, recording, rejection reason)``, the reason None for a sample to keep."""
    proposal = mode.propose(source, rng, config)
    if isinstance(proposal, str):
        return None, None, proposal
    plan = proposal.plan
    if plan.n_steps > max_length:
        return proposal, None, "too_long"
    for k in range(len(plan.spans)):
        reason = ctx.check_span(plan, k, config.feasibility)
        if reason is not None:
            return proposal, None, reason
    rec = replay(ctx, plan, config.replay)
    if not config.validate:  # the replay still records the data; it just is not judged
        return proposal, rec, None
    reason = ctx.replay_reason(plan, rec, config.replay)
    if reason is None:
        reason = mode.accept(source, proposal, rec, config)
    return proposal, rec, reason


def replay(ctx: SourceContext, plan: Plan, config: ReplayConfig) -> Recording:
    """Run ``plan`` in the env from the source's first frame, watching each carry's held object."""
    obs = reset_to_demo(ctx.env, ctx.demo)
    held = {k: ctx.held[ctx.transit_index(span.sample.transit)] for k, span in enumerate(plan.spans)}
    held_body = {k: h.body for k, h in held.items() if h is not None}
    return run_plan(ctx.env, obs, plan, ctx.demo.actions, config, held_body, tail=tail_steps(ctx.demo))


def augmented_demo(source, mode_name: str, proposal: Proposal, rec: Recording, config: StageConfigs,
                   label_len: int):
    """A :class:`~detaug_gym.data.Demo` holding the replay of an accepted proposal, its label and provenance."""
    from detaug_gym.data import Demo

    label = np.asarray(proposal.label, dtype=np.float32)
    if label.shape != (label_len,):
        raise ValueError(f"mode {mode_name!r} proposed a label of shape {label.shape}, expected ({label_len},)")
    actions = np.asarray(rec.actions, dtype=np.float32)
    rewards = np.zeros(len(actions), dtype=np.float32)
    rewards[-1] = float(rec.success)
    transits = [{"kind": s.sample.transit.kind, "grasp": s.sample.transit.grasp,
                 "source_start": s.sample.transit.start, "source_end": s.sample.transit.end,
                 "start": s.start, "end": s.end, **extra, "chord": s.chord}
                for s, extra in zip(proposal.plan.spans, proposal.span_attrs or [{}] * len(proposal.plan.spans))]
    attrs = {k: v for k, v in source.attrs.items() if k != "num_samples"}
    attrs.update({"source_demo": source.name, "augmented": True, "augment_mode": mode_name, **proposal.attrs,
                  "transits": transits, "max_deviation": rec.max_deviation,
                  "max_offset_drift": rec.max_offset_drift, "augment_params": jsonable(config.as_dict())})
    points = None if proposal.obstacle_points is None else np.asarray(proposal.obstacle_points, np.float32)
    return Demo(actions=actions, states=np.asarray(rec.states), obs=rec.stacked_obs(),
                gripper_command=actions[:, -1].copy(), attrs=attrs, label=label, rewards=rewards,
                dones=rewards.copy(), obstacle_points=points)


def jsonable(value):
    """``value`` with tuples as lists and numpy scalars as Python numbers (for HDF5 JSON attributes)."""
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


# ---------------------------------------------------------------------------------------------- CLI
def add_arguments(parser) -> None:
    """The options of ``python -m detaug_gym.augment`` every mode shares (the :class:`StageConfigs` fields)."""
    g = parser.add_argument_group("every mode")
    g.add_argument("--tries", type=int, default=4, help="samples per requested copy (default 4)")
    g.add_argument("--max-length", type=int, default=None, help="longest demo in steps (default: env limit)")
    g.add_argument("--margin", type=float, default=0.4, help="s kept on both sides of a window (default 0.4)")
    g.add_argument("--window", type=float, default=0.25, help="half-width (s) of an interaction window (0.25)")
    g.add_argument("--max-speed", type=float, default=0.012, help="planned peak eef speed, m/step (0.012)")
    g.add_argument("--tolerance", type=float, default=0.015,
                   help="max eef distance (m) from the planned path on replay (default 0.015)")
    g.add_argument("--grasp-tolerance", type=float, default=0.008,
                   help="max shift (m) of a held object in the hand at the start of its carry, against the source")
    g.add_argument("--no-validate", action="store_true",
                   help="keep samples whose replay fails or leaves the planned path (not recommended)")


def stage_options(ns) -> dict:
    """The shared :class:`StageConfigs` fields of parsed options (``SystemExit`` on a bad value)."""
    if ns.tries < 1:
        raise SystemExit("error: --tries must be >= 1")
    return {"tries": ns.tries, "max_length": ns.max_length, "validate": not ns.no_validate,
            "segment": SegmentConfig(margin_s=ns.margin, window_s=ns.window),
            "timing": Timing(max_speed=ns.max_speed),
            "replay": ReplayConfig(tolerance=ns.tolerance, grasp_tolerance=ns.grasp_tolerance)}


def make_config(mode: Mode, ns) -> StageConfigs:
    """``mode``'s config of parsed options: the shared ones plus the mode's own."""
    return mode.make_config(ns, stage_options(ns))
