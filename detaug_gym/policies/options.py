"""The options of every registered policy as typed dataclasses: one home for their types, defaults and checks.

``python -m detaug_gym.bench --methods detaug:k=8,latch=false`` hands the bench strings; the policy's
options dataclass (named in its :func:`~detaug_gym.policies.register_policy` entry) says what they mean.
:func:`~detaug_gym.policies.parse_policy_options` converts the strings by the declared field types and
builds the dataclass, whose ``__post_init__`` runs the range checks, all without importing torch or
loading a checkpoint. The policy constructors build the same dataclass from their keyword arguments, so a
bad value fails the same way whichever door it comes in by. Checks that need the checkpoint (``action_steps``
at most the trained horizon, a label bank to sample from) stay in the constructors.

This module imports only the standard library (:mod:`detaug_gym.config` is standard library too).
Defaults that mirror constants of heavier modules (the AEGIS ellipsoid, the CAPE spheres) are pinned by
``tests/test_policy_options.py`` against the constructors' own defaults.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import Any, ClassVar

from detaug_gym.config import check_value, config_fields

LABEL_MODES = ("auto", "zero", "null")  # FlowPolicy: which label act() plans with
MODES = ("select", "null_guidance", "guided_select", "null_select")  # DetAug: selection vs guidance ablation
LABEL_SOURCES = ("random", "support", "zero")  # DetAug: where the K candidate labels come from
COSTS = ("penetration", "clearance")  # DetAug: how a candidate plan is scored
GUIDE_TARGETS = ("both", "states", "actions")  # CAPE: which part of the plan the guidance cost sees


def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


@dataclass
class PolicyOptions:
    """Base of the options dataclasses: checks every field's value against its declared type and choices
    (``int`` fields reject ``2.5`` and ``True``, ``bool`` fields reject ``"false"``), normalising numpy
    scalars to Python ones. Subclasses add range checks in ``__post_init__`` after calling this one.

    ``WRAPS`` names the field that holds the registered name of a wrapped policy (AEGIS); options that are
    not this dataclass's own are then the wrapped policy's.
    """

    WRAPS: ClassVar[str | None] = None

    def __post_init__(self) -> None:
        for name, (_, kind) in config_fields(type(self)).items():
            setattr(self, name, check_value(getattr(self, name), kind, name))

    @classmethod
    def from_kwargs(cls, **kwargs: Any) -> PolicyOptions:
        """``cls(**kwargs)``, but an unknown keyword raises a ``TypeError`` that lists the valid ones."""
        valid = [f.name for f in dataclasses.fields(cls) if f.init]
        unknown = [key for key in kwargs if key not in valid]
        if unknown:
            raise TypeError(f"unknown option {unknown[0]!r} for {cls.__name__}; valid: {', '.join(sorted(valid))}")
        return cls(**kwargs)

    def given(self, *names: str) -> dict[str, Any]:
        """``{name: value}`` of the named fields (all fields without names)."""
        names = names or tuple(f.name for f in dataclasses.fields(self))
        return {name: getattr(self, name) for name in names}


@dataclass
class RandomOptions(PolicyOptions):
    """``random``: uniform random actions."""

    scale: float = 1.0
    """Bound on the arm part of the action, in (0, 1]."""
    seed: int | None = None
    """Default seed used when reset() is called without one."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(0.0 < self.scale <= 1.0, f"scale must lie in (0, 1], got {self.scale}")


@dataclass
class ScriptedOptions(PolicyOptions):
    """``scripted``: the privileged scripted expert."""

    task: str | None = None
    """Recipe name (a key of detaug_gym.policies.scripted_tasks.RECIPES); default: recognised from the first
    observation of each episode."""
    variation: float = 1.0
    """Scale of the per-demo variation (0: the same nominal motion every episode)."""
    seed: int | None = None
    """Default seed used when reset() is called without one."""
    fumble: float = 0.0
    """Chance that a grasp's first try deliberately misses: the drawer handle's (3.5-5 cm in front of, above or
    below the bar) and each pick's of a can or a box (the descent 2.5-4 cm beside the grasp point; never a
    rim-held mug or bowl, which a miss tips over). The miss is acted out in what the collection sends while the
    recorded action stays the correct one, so that the demo shows the expert letting go, backing off and
    grasping again (recovery demos, docs/data.md). 0: never."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(0.0 <= self.fumble <= 1.0, f"fumble must be in [0, 1], got {self.fumble}")
        if self.task is not None:
            from detaug_gym.policies.scripted_tasks import RECIPES  # numpy only

            _require(self.task in RECIPES, f"unknown task recipe {self.task!r}; valid: {', '.join(sorted(RECIPES))}")
        _require(self.variation >= 0, f"variation must be >= 0, got {self.variation}")


@dataclass
class FlowSamplingOptions(PolicyOptions):
    """What every flow-matching policy shares: where its checkpoint is and how plans are sampled."""

    suite: str = "spatial"
    """Zoo suite folder: the policy loads policies/<method>/<suite>/ (the bench passes the suite it runs)."""
    checkpoint: str | None = None
    """A checkpoint folder (made by python -m detaug_gym.train) instead of the zoo's."""
    flow_steps: int = 10
    """Euler steps per plan (>= 1)."""
    label_mode: str = field(default="auto", metadata={"choices": LABEL_MODES})
    """Label a plain plan uses: zero (the unaugmented demos' label), null (the null token: unconditional) or
    auto (zero for label models, nothing for base)."""
    binarize_gripper: bool = True
    """Snap the gripper command to -1 (open) / +1 (close)."""
    noise_scale: float = 1.0
    """Scale of the Gaussian noise each plan starts from (1: the training distribution; below 1 samples
    nearer the flow's mode, 0 is deterministic per observation, above 1 spreads the plans wider; >= 0)."""
    seed: int | None = None
    """Default seed of the sampling noise when reset() is called without one."""
    device: str = "cpu"
    """Torch device the network runs on: cpu, cuda, cuda:N or auto (cuda when torch sees one, else cpu). The
    sampling noise is drawn on the CPU, so a seed gives the same noise everywhere; collision scoring stays
    on the CPU."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(self.flow_steps >= 1, f"flow_steps must be >= 1, got {self.flow_steps}")
        _require(self.noise_scale >= 0.0, f"noise_scale must be >= 0, got {self.noise_scale}")
        check_device(self.device)

    def flow_policy_kwargs(self) -> dict[str, Any]:
        """The keyword arguments of :class:`~detaug_gym.models.policy.FlowPolicy` these options set."""
        return self.given("flow_steps", "label_mode", "binarize_gripper", "noise_scale", "seed", "device")


@dataclass
class FlowOptions(FlowSamplingOptions):
    """``base`` (and the plain :class:`~detaug_gym.models.policy.FlowPolicy`): a flow policy that executes
    ``action_steps`` actions of each plan before replanning."""

    action_steps: int | None = None
    """N, actions executed from each plan before replanning (1..horizon); default the checkpoint's own
    (config.json policy.action_steps, written by train --action-steps), else 10."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(self.action_steps is None or self.action_steps >= 1,
                 f"action_steps must be >= 1, got {self.action_steps}")

    def flow_policy_kwargs(self) -> dict[str, Any]:
        return {**super().flow_policy_kwargs(), "action_steps": self.action_steps}


@dataclass
class DetAugOptions(FlowOptions):
    """``detaug``: K-label selection by collision cost (and the paper's ablations)."""

    k: int = 32
    """Candidate plans per replan, generated in one batch (paper: 32; >= 1)."""
    latch: bool = False
    """Keep the first selected label for the whole episode (the paper found this halves clean success)."""
    labels: str = field(default="support", metadata={"choices": LABEL_SOURCES})
    """Candidate labels: support (the paper's: uniform within the task's training support, per transit, and the
    unbent label once), random (rows of the task's training labels, 37-68 % of them unbent on Spatial) or zero
    (the unbent label)."""
    cost: str = field(default="penetration", metadata={"choices": COSTS})
    """Score of a candidate: penetration (paper) or clearance."""
    mode: str = field(default="select", metadata={"choices": MODES})
    """select (DetAug), null_guidance (null token + guidance, no selection), guided_select (guidance and
    selection) or null_select (selection over null-token samples)."""
    guidance_scale: float = 3.0
    """lambda, the gradient step of the guidance variants (>= 0)."""
    guidance_t_min: float = 0.8
    """chi, guidance acts at flow times t >= chi (in [0, 1])."""
    held_object: bool = True
    """Also score the object in the hand (its observed surface points, carried with the grip site); false is
    the paper's score."""
    inflate: float = 0.015
    """Metres the obstacle is inflated by before penetration is scored (>= 0): the scorer's measured model
    error (benchmarks/scorer_fidelity.py); 0 is the paper's score. Penetration-only still: a plan that stays
    this far off costs nothing, however close it passes beyond that."""
    tiebreak_margin: float = 0.0
    """Metres beyond inflate (>= 0): among the plans of equal lowest cost, the one that penetrates least into the
    obstacle inflated by this much more wins before the least bent (0: the least bent, the paper's rule)."""
    support: bool = True
    """Also score penetration into what the obstacle stands on (a pedestal or base; docs/detaug.md)."""
    support_scale: float = 1.0
    """labels=support draws each transit's phi up to this multiple of its largest training phi (> 0; 1 is the
    paper's training support, more asks the network for wider detours than it was shown; docs/detaug.md)."""
    wider_batches: int = 2
    """When none of the K candidates is free, up to this many more batches of K (>= 0), the i-th with phi up to
    (1 + i) x support_scale x the largest training phi (labels=support; random and zero draw as they do), until
    one holds a free plan (0: the paper's one batch; 2, the default, avoided 74 Spatial episodes of 320 that 0
    hit and hit 11 that 0 avoided, at equal Clean; docs/detaug.md)."""

    commit: bool = False
    """From the second replan on, the previous replan's label is one of the candidates (in place of a drawn one),
    and among the plans of lowest cost it wins before the least bent: a detour is kept while it stays as good,
    as every step of an augmented demo keeps its one label (false: the paper's fresh draw; ``latch`` keeps the
    first label even when it collides)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(self.k >= 1, f"k must be >= 1, got {self.k}")
        _require(self.inflate >= 0.0, f"inflate must be >= 0 (metres), got {self.inflate}")
        _require(self.support_scale > 0.0, f"support_scale must be > 0, got {self.support_scale}")
        _require(self.wider_batches >= 0, f"wider_batches must be >= 0, got {self.wider_batches}")
        _require(self.tiebreak_margin >= 0.0, f"tiebreak_margin must be >= 0 (metres), got {self.tiebreak_margin}")
        _check_guidance(self.guidance_scale, self.guidance_t_min)


@dataclass
class DemoGenOptions(FlowOptions):
    """``demogen``: the flow policy conditioned on the obstacle's point cloud (no options of its own)."""


@dataclass
class CapeOptions(FlowSamplingOptions):
    """``cape``: receding-horizon re-noising of the base policy's plan with collision guidance. CAPE sets its
    replan period with ``prefix_steps``; it takes no ``action_steps``."""

    prefix_steps: int = 2
    """Actions executed from each plan before re-noising the rest (CAPE: ~2; 1 <= prefix_steps < horizon)."""
    t_start: float = 0.5
    """Flow time the remainder is re-noised to (1 - delta), in (0, 1)."""
    refine_steps: int | None = None
    """Euler steps from t_start to 1 (>= 1; default: what flow_steps leaves, at least 1)."""
    guidance_scale: float = 3.0
    """lambda, the gradient step in normalised plan coordinates (>= 0)."""
    guidance_t_min: float = 0.8
    """chi, guidance acts at flow times t >= chi (in [0, 1])."""
    sphere_radius: float = 0.065
    """Radius (m) of the end-effector spheres (CAPE: 0.06-0.08; > 0)."""
    margin: float = 0.02
    """Hinge margin (m) added to the sphere radius (>= 0)."""
    guide: str = field(default="both", metadata={"choices": GUIDE_TARGETS})
    """Which part of the plan the cost sees: both, states or actions."""
    action_gain: float = 0.25
    """Achieved fraction of the commanded displacement per step, for the actions term (in (0, 1])."""
    track_cost: bool = False
    """Record the cost of every executed plan in diagnostics (one more FK pass per replan)."""
    support: bool = False
    """Also guide away from what the obstacle stands on (a pedestal or base). Off: measured on 40 Spatial L2
    -v2 episodes, it drops CAPE's clean success from 20 % to 2.5 % (docs/detaug.md)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(self.prefix_steps >= 1, f"prefix_steps must lie in [1, horizon), got {self.prefix_steps}")
        _require(0.0 < self.t_start < 1.0, f"t_start must lie in (0, 1), got {self.t_start}")
        _require(self.refine_steps is None or self.refine_steps >= 1,
                 f"refine_steps must be >= 1, got {self.refine_steps}")
        _check_guidance(self.guidance_scale, self.guidance_t_min)
        _require(self.sphere_radius > 0.0, f"sphere_radius must be > 0, got {self.sphere_radius}")
        _require(self.margin >= 0.0, f"margin must be >= 0, got {self.margin}")
        _require(0.0 < self.action_gain <= 1.0, f"action_gain must lie in (0, 1], got {self.action_gain}")


@dataclass
class AegisOptions(PolicyOptions):
    """``aegis``: the CBF-QP safety filter around another registered policy. Options that are not AEGIS's
    own go to the wrapped policy: ``aegis:base=detaug,alpha=5,k=8``."""

    WRAPS: ClassVar[str | None] = "base"

    suite: str = "spatial"
    """Passed to the wrapped policy (zoo folder of flow policies)."""
    base: str = "base"
    """Registered name of the wrapped policy (not aegis)."""
    alpha: float = 10.0
    """Class-K gain of dh/dt >= -alpha h (1/s); alpha * dt must lie in (0, 1]."""
    dt: float = 0.05
    """Control period (s): 20 Hz."""
    ee_semi_axes: tuple[float, float, float] = (0.12, 0.06, 0.11)
    """End-effector ellipsoid semi-axes (m) along the grip-site x (finger travel), y (palm normal), z (tool)."""
    ee_offset: float = 0.056
    """End-effector ellipsoid centre, m from the grip site towards the wrist."""
    support: bool = True
    """Also keep clear of what the obstacle stands on (a pedestal or base: a second ellipsoid and barrier)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        _require(self.base.lower() != "aegis",
                 "AEGIS cannot wrap itself; pass base='base' (or another registered policy)")
        _require(self.alpha > 0 and self.dt > 0 and self.alpha * self.dt <= 1.0,
                 f"need alpha > 0, dt > 0 and alpha * dt <= 1, got alpha={self.alpha}, dt={self.dt}")
        _require(min(self.ee_semi_axes) > 0,
                 f"end-effector semi-axes must be 3 positive lengths, got {self.ee_semi_axes}")


DEVICE_PATTERN = re.compile(r"(cpu|auto|cuda(:\d+)?)")


def check_device(device: str) -> str:
    """``device`` if it names a device this library runs on (no torch import: availability is checked when
    a network is placed, by :func:`detaug_gym.models.checkpoint.resolve_device`)."""
    _require(isinstance(device, str) and DEVICE_PATTERN.fullmatch(device) is not None,
             f"device must be cpu, cuda, cuda:N or auto, got {device!r}")
    return device


def _check_guidance(scale: float, t_min: float) -> None:
    _require(scale >= 0.0, f"guidance_scale must be >= 0, got {scale}")
    _require(0.0 <= t_min <= 1.0, f"guidance_t_min must lie in [0, 1], got {t_min}")
