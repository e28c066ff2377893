"""What every augmentation mode needs to know about one source demo, computed once per source.

``SourceContext`` puts the env on the demo's first frame (its task's scene loaded), recomputes the
end-effector poses in float64 from the recorded simulator states (the stored observations are float32),
segments the demo, and finds what each carry holds. It also builds the tools that act on that scene: the
IK solver and the contact checker (both on scratch ``MjData``) and the replay. DemoGen reuses all of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from detaug_gym.augment.feasibility import (
    ContactChecker,
    FeasibilityConfig,
    HeldObject,
    articulated_motion,
    find_held_object,
    grip_frame_position,
    held_offset_drift,
    path_kinematics_reason,
)
from detaug_gym.augment.ik import ArmIK, IKConfig
from detaug_gym.augment.plan import Plan
from detaug_gym.augment.replay import Recording, ReplayConfig
from detaug_gym.augment.segment import Segmentation, SegmentConfig, Transit, segment_gripper
from detaug_gym.rotations import mat_to_quat_xyzw, quat_xyzw_to_mat


def reset_to_demo(env, demo) -> dict:
    """Put ``env`` on the demo's first recorded frame (:meth:`~detaug_gym.envs.base.ObstacleManipulationEnv.restore`:
    its task, init state and seed, then its first state); returns the observation there."""
    obs, _ = env.unwrapped.restore(demo.attrs, demo.states[0])
    return obs


@dataclass
class SourceContext:
    """A source demo prepared for augmentation (see the module docstring).

    Attributes:
        qpos: (T, nq) scene configuration per frame; ``pos`` (T, 3) / ``quat`` (T, 4, xyzw) grip-site poses.
        segmentation: interaction windows and transits.
        held: per carry transit (by its index in ``segmentation.transits``), the held object or None.
        bendable: per transit, False for carries that drag an articulated part (a drawer) - left unbent.
        source_drift: per carry, how far (m) the held object already moved in the grip-site frame during the
            source's own carry (a rim-held bowl swings ~2 cm as it leaves the table); the replay may add
            ``offset_tolerance`` to it.
    """

    demo: object
    env: object
    qpos: np.ndarray
    pos: np.ndarray
    quat: np.ndarray
    segmentation: Segmentation
    ik: ArmIK
    checker: ContactChecker
    held: dict[int, HeldObject | None] = field(default_factory=dict)
    bendable: dict[int, bool] = field(default_factory=dict)
    source_drift: dict[int, float] = field(default_factory=dict)

    @classmethod
    def build(cls, env, demo, segment: SegmentConfig | None = None, ik: IKConfig | None = None,
              penetration: float = 0.002) -> SourceContext:
        reset_to_demo(env, demo)
        scene = env.unwrapped.scene
        model = scene.model
        qpos = _qpos_path(model, demo.states)
        rest = np.asarray(scene.robot.controller.initial_joint, dtype=np.float64)
        solver = ArmIK(model, scene.arm_qpos, scene.arm_qvel, scene.eef_site, rest=rest, config=ik)
        pos, quat = _site_poses(solver, qpos)
        seg = segment_gripper(demo.gripper_command, segment)
        ctx = cls(demo, env, qpos, pos, quat, seg, solver, ContactChecker(model, penetration))
        for i, tr in enumerate(seg.transits):
            ctx.held[i] = None
            ctx.bendable[i] = True
            if tr.kind == "carry":
                path = qpos[tr.start:tr.end + 1]
                ctx.held[i] = find_held_object(model, solver.data, path, scene.eef_site)
                ctx.bendable[i] = not articulated_motion(model, path, scene.arm_qpos)
                if ctx.held[i] is not None:
                    ctx.source_drift[i] = held_offset_drift(model, solver.data, path, scene.eef_site, ctx.held[i])
        return ctx

    @property
    def scene(self):
        return self.env.unwrapped.scene

    def transit_index(self, transit: Transit) -> int:
        return self.segmentation.transits.index(transit)

    def check_span(self, plan: Plan, span_index: int, config: FeasibilityConfig) -> str | None:
        """IK + kinematic + collision checks of one bent span of ``plan``; None if feasible, else the reason."""
        span = plan.spans[span_index]
        tr = span.sample.transit
        targets_pos = plan.target_pos[span.start:span.end + 1]
        targets_rot = quat_xyzw_to_mat(plan.target_quat[span.start:span.end + 1])
        scene = self.scene
        q0 = self.qpos[tr.start, scene.arm_qpos]
        self.ik.load(self.qpos[tr.start])
        result = self.ik.solve_path(q0, targets_pos, targets_rot)
        if not result.solved(self.ik.config):
            return "ik_failed"
        reason = path_kinematics_reason(result.q, self.ik.lower, self.ik.upper, config)
        if reason is not None:
            return reason
        return self._collision_reason(tr, result.q, targets_pos, targets_rot)

    def replay_reason(self, plan: Plan, rec: Recording, config: ReplayConfig) -> str | None:
        """Why a replayed sample is rejected (it failed, left its arcs, let the held object slip or grasped it
        elsewhere than the source did), or None to keep it."""
        if not rec.success:
            return "replay_failed"
        if rec.max_deviation > config.tolerance:
            return "replay_tracking"
        allowed_drift = max((self.source_drift.get(self.transit_index(s.sample.transit), 0.0) for s in plan.spans),
                            default=0.0) + config.offset_tolerance
        if rec.max_offset_drift > allowed_drift:
            return "object_slipped"
        if self.grasp_shift(plan, rec) > config.grasp_tolerance:
            return "grasp_moved"
        return None

    def grasp_shift(self, plan: Plan, rec: Recording) -> float:
        """Largest distance (m), over the carries, between the held object's position in the grip-site frame
        at the carry's first frame in the replay and in the source (0 without carries)."""
        model, data, site = self.scene.model, self.ik.data, self.scene.eef_site
        shift = 0.0
        for i, tr in enumerate(self.segmentation.transits):
            held = self.held.get(i)
            frames = np.flatnonzero(plan.source_frame == tr.start)
            if held is None or not len(frames) or frames[0] >= len(rec.states):
                continue
            data.qpos[:] = np.asarray(rec.states[frames[0]])[1:1 + model.nq]
            mujoco.mj_kinematics(model, data)
            shift = max(shift, float(np.linalg.norm(grip_frame_position(data, site, held.body) - held.offset_pos)))
        return shift

    def _collision_reason(self, tr: Transit, q: np.ndarray, targets_pos: np.ndarray,
                          targets_rot: np.ndarray) -> str | None:
        held = self.held.get(self.transit_index(tr))
        checker, arm = self.checker, self.scene.arm_qpos
        checker.set_held(held)
        checker.allow_from([self.qpos[tr.start], self.qpos[tr.end]])
        base = self.qpos[tr.start].copy()
        for k in range(len(q)):
            base[arm] = q[k]
            if held is not None:
                base[held.qpos_adr:held.qpos_adr + 7] = held.world_qpos(targets_pos[k], targets_rot[k])
            if checker.collides(base) is not None:
                return "collision"
        return None


def _qpos_path(model: mujoco.MjModel, states: np.ndarray) -> np.ndarray:
    """(T, nq) configurations from flattened ``[time, qpos, qvel]`` states of this scene."""
    states = np.asarray(states, dtype=np.float64)
    if states.ndim != 2 or states.shape[1] != 1 + model.nq + model.nv:
        raise ValueError(f"states of shape {states.shape} do not match this scene's layout "
                         f"(T, {1 + model.nq + model.nv}); augment demos recorded in the same env")
    return states[:, 1:1 + model.nq].copy()


def _site_poses(solver: ArmIK, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pos = np.zeros((len(qpos), 3))
    quat = np.zeros((len(qpos), 4))
    for t, q in enumerate(qpos):
        solver.load(q)
        p, r = solver.site_pose()
        pos[t], quat[t] = p, mat_to_quat_xyzw(r)
    return pos, quat
