"""Demonstration augmentation: one engine, two modes (DetAug detour arcs, DemoGen planned detours).

Pipeline per source demo, run by :mod:`~.engine` for every mode: :mod:`~.context` (:mod:`~.segment`:
interaction windows and transits from the gripper command; held objects) -> the mode's proposal
(:mod:`~.detaug`: random arcs, :mod:`~.arcs` / :mod:`~.plan`; :mod:`~.demogen`: an obstacle and RRT detours,
:mod:`~.planner`) -> :mod:`~.ik` + :mod:`~.feasibility` (damped-least-squares IK on the env's MuJoCo model,
limits, smoothness, contacts) -> :mod:`~.replay` (closed-loop execution in the env; the replay is the
recorded demo). :mod:`~.runner` holds the resumable file-to-file run and the mode registry;
``python -m detaug_gym.augment`` is the command (see ``docs/augment.md``).

    >>> from detaug_gym.augment import segment_gripper, arc_points, arc_label
"""

from detaug_gym.augment.arcs import arc_label, arc_length, arc_points, label_to_arc
from detaug_gym.augment.segment import Segmentation, SegmentConfig, Transit, segment_gripper

__all__ = ["Segmentation", "SegmentConfig", "Transit", "arc_label", "arc_length", "arc_points",
           "label_to_arc", "segment_gripper"]
