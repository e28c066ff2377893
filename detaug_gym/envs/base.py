"""The gymnasium env shared by the SafeLIBERO-style suites and the Newton-style pick-and-place.

Subclasses say how to build a :class:`~detaug_gym.envs.scene.Scene` for a task and how to pick an episode's
task; this class owns everything else: drawing the init state and obstacle from the seed and the cell
(:func:`detaug_gym.seeds.episode_rng`), the Dict observation, action checks, the control loop (fast or stock
OSC_POSE), SafeLIBERO's collision rule and the info metrics.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from dataclasses import dataclass

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces

from detaug_gym.envs.control import CONTROLLERS, make_stepper
from detaug_gym.envs.obstacles import (
    OBSTACLE_POINTS,
    OBSTACLE_TYPES,
    SUPPORT_POINTS,
    SupportView,
    activate,
    raise_pedestal,
    support_view,
)
from detaug_gym.envs.placement import Placement, PlacementProblem, place_obstacle
from detaug_gym.envs.scene import OBJECT_POINTS, SETTLE_ACTION, Scene
from detaug_gym.envs.suites import SuiteSpec, TaskSpec
from detaug_gym.seeds import episode_rng

ACTION_DIM = 7
SETTLE_STEPS = 10
SETTLE_MODES = ("steps", "still")
STILL_SPEED = 1e-4  # m per step (summed |dx|): below this the obstacle counts as still
MAX_SETTLE_STEPS = 200
COLLISION_DISPLACEMENT = 1e-3  # m, SafeLIBERO: summed absolute displacement of the obstacle
NEAR_CONTACT = 0.03  # m: at the first collision step with nothing in contact, bodies this close count as the hit
ROBOT_CONTACTS = ("link:", "gripper:")  # the labels of Scene.contact_labels that are the robot's own bodies
# MuJoCo resets the simulation by itself when one of these fires (bad qpos / qvel / qacc); the episode's state
# is then meaningless, and without a check the env carried on and reported the reset as a collision.
INSTABILITY_WARNINGS = (mujoco.mjtWarning.mjWARN_BADQPOS, mujoco.mjtWarning.mjWARN_BADQVEL,
                        mujoco.mjtWarning.mjWARN_BADQACC)


class SimulationError(RuntimeError):
    """The physics became unstable (non-finite state or MuJoCo's own bad-state reset) during a step."""


@dataclass
class Episode:
    """What one reset decided; reported in ``info`` and recorded by the bench."""

    task: int
    init_state: int
    obstacle: str | None
    placement: Placement | None


class ObstacleManipulationEnv(gym.Env):
    """Franka Panda manipulation with OSC_POSE delta actions and an optional obstacle.

    Observation (``spaces.Dict``, float32):
        ``robot_joint_pos`` (7,), ``robot_joint_vel`` (7,), ``gripper_qpos`` (2,), ``eef_pos`` (3,),
        ``eef_quat`` (4,) xyzw, ``object_poses`` (S, 7) pos + xyzw quat of the task-relevant objects,
        ``object_mask`` (S,), ``object_points`` (S, 64, 3) world-frame surface samples of those objects (zeros
        for a slot without a body), ``task_id`` (T,) one-hot over the suite's T tasks in the suite's order (a
        task has the same index at every level, so a policy trained on Free reads it right at L1 / L2),
        ``obstacle_points`` (256, 3) world-frame surface samples, ``obstacle_local_points`` (256, 3) the same
        samples in the obstacle's own frame (the same numbers every episode for a shape: what shape-derived
        caches are built from), ``obstacle_pose`` (7,),
        ``obstacle_size`` (3,) half-extents, ``obstacle_mask`` (1,); and what the obstacle stands on (a pedestal
        or base: touching it moves the obstacle, so it counts with the obstacle for collision, contact and
        clearance): ``obstacle_support_points`` (128, 3) world-frame surface samples, ``obstacle_support_local_points``
        (128, 3) the same in the support's frame, ``obstacle_support_pose`` (7,), ``obstacle_support_mask`` (1,).
        Obstacle entries are zero (mask 0) without an obstacle, support entries without a support.
    Action: ``Box(-1, 1, (7,))``: OSC_POSE delta (scales in :mod:`detaug_gym.actions`) and the gripper
        (-1 open, +1 close). Wrong shapes and non-finite values raise ``ValueError``.
    Info (every step): ``is_success``, ``goals_met`` (how many of the task's sub-goals hold now: its goal
        predicates, e.g. two for a Long task that places two objects; success is all of them), ``goals``
        (the task's number of sub-goals), ``collision`` (latched), ``robot_obstacle_contact``,
        ``obstacle_contacts`` (who touches the obstacle now, e.g. ``("gripper:gripper0_leftfinger",
        "held:akita_black_bowl_1")``; see :meth:`~detaug_gym.envs.scene.Scene.contact_labels`),
        ``collision_bodies`` (at the step the collision starts: the contacts, or when a fast hit left none at the
        step's end, the bodies within :data:`NEAR_CONTACT`; empty at every other step),
        ``obstacle_displacement``, ``min_clearance`` (m, robot collision geometry to the obstacle; inf
        without one), ``task``, ``init_state``, ``obstacle``, ``obstacle_raised`` (it stands on a pedestal or base).
    Step limit: gymnasium's ``TimeLimit`` (``gym.make(id, max_episode_steps=N)``, default the suite's); an
        env built directly truncates itself only when given ``max_episode_steps``.

    Data tools use the public surface, never the private members: :meth:`observe`, :meth:`restore`
    (a recorded episode's first frame), :meth:`placement_problem`, :meth:`scene_for`, :meth:`get_state`
    and :meth:`set_state`.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}
    obstacle_types: tuple[str, ...] = OBSTACLE_TYPES
    version: int = 0  # scenario version of the procedural obstacles (the env id's -vN)

    def __init__(self, *, suite: SuiteSpec, level: str, max_steps: int | None = None,
                 obstacle: str | list[str] | None = None, init_state: int | None = None,
                 controller: str = "fast", render_mode: str | None = None, settle: str = "steps") -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"unknown render_mode {render_mode!r}; valid: None, 'rgb_array'")
        if settle not in SETTLE_MODES:
            raise ValueError(f"unknown settle {settle!r}; valid: {', '.join(SETTLE_MODES)}")
        self.settle = settle
        self._support_geoms: list[int] = []
        self._support: SupportView | None = None
        if max_steps is not None and not (_is_int(max_steps) and max_steps >= 1):
            raise ValueError(f"max_episode_steps must be a positive integer, got {max_steps!r}")
        self.render_mode = render_mode
        self.suite = suite
        self.level = suite.check_level(level)
        self.tasks: tuple[TaskSpec, ...] = suite.tasks_for(self.level)
        self.fixed_init_state = None if init_state is None else suite.check_init_state(init_state)
        self.max_steps = None if max_steps is None else int(max_steps)
        num_tasks, object_slots = len(self.tasks), suite.object_slots
        if controller not in CONTROLLERS:
            raise ValueError(f"unknown controller {controller!r}; valid controllers: {', '.join(CONTROLLERS)}")
        self.controller = controller
        self.num_tasks = num_tasks
        self.object_slots = object_slots
        self.obstacle_choices = self._obstacle_choices(obstacle)
        self.observation_space = spaces.Dict({
            "robot_joint_pos": _box(7),
            "robot_joint_vel": _box(7),
            "gripper_qpos": _box(2),
            "eef_pos": _box(3),
            "eef_quat": _box(4, -1.0, 1.0),
            "object_poses": _box((object_slots, 7)),
            "object_mask": _box(object_slots, 0.0, 1.0),
            "object_points": _box((object_slots, OBJECT_POINTS, 3)),
            "task_id": _box(len(suite.tasks), 0.0, 1.0),
            "obstacle_points": _box((OBSTACLE_POINTS, 3)),
            "obstacle_local_points": _box((OBSTACLE_POINTS, 3)),
            "obstacle_pose": _box(7),
            "obstacle_size": _box(3, 0.0, np.inf),
            "obstacle_mask": _box(1, 0.0, 1.0),
            "obstacle_support_points": _box((SUPPORT_POINTS, 3)),
            "obstacle_support_local_points": _box((SUPPORT_POINTS, 3)),
            "obstacle_support_pose": _box(7),
            "obstacle_support_mask": _box(1, 0.0, 1.0),
        })
        self.action_space = spaces.Box(-1.0, 1.0, (ACTION_DIM,), dtype=np.float32)
        self._scenes: dict[int, Scene] = {}
        self._steppers: dict[int, object] = {}
        self.scene: Scene | None = None
        self.episode: Episode | None = None
        self._renderer = None
        self._steps = 0

    @property
    def task_spec(self) -> TaskSpec:
        """The task of the current episode."""
        if self.episode is None:
            raise RuntimeError("call reset() first")
        return self.tasks[self.episode.task]

    # ------------------------------------------------------------------ to implement
    def _build_scene(self, task: int) -> Scene:
        raise NotImplementedError

    def _sample_task(self, rng: np.random.Generator, options: dict) -> int:
        """Return the task index of a new episode (``options["task"]``, the fixed one, or a draw)."""
        raise NotImplementedError

    def _load_init_state(self, scene: Scene, task: int, init_state: int, rng: np.random.Generator) -> None:
        raise NotImplementedError

    def _placement_problem(self, scene: Scene, rng: np.random.Generator, step: int | None = None) -> PlacementProblem:
        raise NotImplementedError

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        task = self._sample_task(self.np_random, options)
        rng = episode_rng(int(self.np_random.integers(2**63)), self.suite.name, self.level, task)
        init_state = options.get("init_state", self.fixed_init_state)
        init_state = (int(rng.integers(self.suite.num_init_states)) if init_state is None
                      else self.suite.check_init_state(init_state))
        scene = self.scene_for(task)
        self.scene = scene
        scene.reset_dynamics()
        self._load_init_state(scene, task, init_state, rng)
        mujoco.mj_forward(scene.model, scene.data)
        obstacle, placement, support = self._set_obstacle(scene, task, options, rng)
        self.episode = Episode(task, init_state, obstacle, placement)
        self._support_geoms = support
        mujoco.mj_forward(scene.model, scene.data)
        self._settle(self._steppers[task])
        self._support = support_view(scene.model, scene.data, support)
        self._steps = 0
        self._obstacle_ref = self._obstacle_position()
        self._collided = False
        return self.observe(), self._info(contacts=())

    def step(self, action):
        if self.scene is None:
            raise RuntimeError("call reset() before step()")
        action = np.asarray(action, dtype=np.float64)
        if action.shape != (ACTION_DIM,):
            raise ValueError(f"action must have shape ({ACTION_DIM},), got {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action must be finite, got {action}")
        before = self._instability_count()
        self._steppers[self.episode.task].step(np.clip(action, -1.0, 1.0))
        self._check_stable(before)
        self._steps += 1
        info = self._info(contacts=self._obstacle_contacts())
        terminated = bool(info["is_success"])
        truncated = self.max_steps is not None and self._steps >= self.max_steps and not terminated
        return self.observe(), float(terminated), terminated, truncated, info

    def render(self):
        if self.render_mode != "rgb_array" or self.scene is None:
            return None
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.scene.model, 256, 256)
        has_agentview = mujoco.mj_name2id(self.scene.model, mujoco.mjtObj.mjOBJ_CAMERA, "agentview") >= 0
        camera = "agentview" if has_agentview else -1
        self._renderer.update_scene(self.scene.data, camera=camera)
        return self._renderer.render()

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        for scene in self._scenes.values():
            scene.sim_env.close()
        self._scenes.clear()
        self._steppers.clear()
        self.scene = None

    # ------------------------------------------------------------------ public surface for data tools
    def observe(self) -> dict[str, np.ndarray]:
        """The observation of the current state (what :meth:`step` would return now)."""
        if self.scene is None:
            raise RuntimeError("call reset() before observe()")
        return self._observation()

    def restore(self, attrs: Mapping, state: np.ndarray | None = None) -> tuple[dict[str, np.ndarray], dict]:
        """Put the env on a recorded episode's frame: reset to the episode named by ``attrs`` (a demo's
        ``task``, ``init_state`` and ``seed``; missing ones are drawn as in :meth:`reset`), then load the
        flattened ``state`` when given. The controller's internal state (goal orientation, gripper ramp) is
        the one a fresh episode starts with, as when the demo was recorded.

        Returns:
            ``(obs, info)`` of the restored frame.
        """
        options = {}
        if "task" in attrs and len(self.tasks) > 1:
            options["task"] = int(attrs["task"])
        if int(attrs.get("init_state", -1)) >= 0:
            options["init_state"] = int(attrs["init_state"])
        seed = attrs.get("seed")
        _, info = self.reset(seed=None if seed is None else int(seed), options=options)
        if state is not None:
            self.set_state(state)
        return self.observe(), info

    def placement_problem(self, rng: np.random.Generator | None = None, step: int | None = None) -> PlacementProblem:
        """Where an obstacle may go in the current scene (pick and place footprints, other objects, the
        sampling box) for the pick-place ``step`` of the task; without one, ``rng`` draws it (default
        ``default_rng(0)``)."""
        if self.scene is None:
            raise RuntimeError("call reset() before placement_problem()")
        return self._placement_problem(self.scene, rng if rng is not None else np.random.default_rng(0), step)

    def scene_for(self, task: int) -> Scene:
        """The compiled scene of ``task`` (index into :attr:`tasks`), built on first use and cached."""
        if task not in self._scenes:
            scene = self._build_scene(task)
            self._scenes[task] = scene
            self._steppers[task] = make_stepper(self.controller, scene)
        return self._scenes[task]

    def get_state(self) -> np.ndarray:
        """Flattened simulator state ``[time, qpos, qvel]`` of the current scene."""
        return self.scene.get_state()

    def set_state(self, state: np.ndarray) -> None:
        """Load a flattened state into the current scene and recompute derived quantities."""
        self.scene.set_state(state)
        mujoco.mj_forward(self.scene.model, self.scene.data)

    # ------------------------------------------------------------------ internals
    def _instability_count(self) -> int:
        warnings = self.scene.data.warning
        return int(sum(warnings[int(w)].number for w in INSTABILITY_WARNINGS))

    def _check_stable(self, before: int) -> None:
        """Raise :class:`SimulationError` if the step left a non-finite state or MuJoCo reset itself."""
        d = self.scene.data
        if self._instability_count() > before:
            names = [w.name.removeprefix("mjWARN_") for w in INSTABILITY_WARNINGS
                     if d.warning[int(w)].number > 0]
            raise SimulationError(f"simulation unstable at step {self._steps + 1}: MuJoCo reported "
                                  f"{', '.join(names)} and reset the state (episode ended as an error)")
        if not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))):
            raise SimulationError(f"simulation unstable at step {self._steps + 1}: non-finite qpos/qvel")

    def _obstacle_choices(self, obstacle) -> tuple[str, ...]:
        if obstacle is None:
            return self.obstacle_types
        if self.level == "Free":
            raise ValueError(f"obstacle={obstacle!r} has no effect at the Free level (no obstacle is placed); "
                             "use an L1 or L2 id")
        chosen = (obstacle,) if isinstance(obstacle, str) else tuple(obstacle)
        if not chosen:
            raise ValueError(f"obstacle must name at least one type; valid types: {', '.join(self.obstacle_types)}")
        return tuple(self._check_obstacle(o) for o in chosen)

    def _check_obstacle(self, kind: str) -> str:
        if kind not in self.obstacle_types:
            raise ValueError(f"unknown obstacle type {kind!r}; valid types: {', '.join(self.obstacle_types)}")
        return kind

    def _set_obstacle(self, scene: Scene, task: int, options: dict, rng: np.random.Generator
                      ) -> tuple[str | None, Placement | None, list[int]]:
        """Put this episode's obstacle in the scene: ``(type, placement, support geoms)``, where the support
        (a pedestal) counts with the obstacle for contact and clearance. Procedural: drawn and placed."""
        if not (scene.obstacles and self.level in ("L1", "L2")):
            return None, None, []
        obstacle = options.get("obstacle") or self.obstacle_choices[int(rng.integers(len(self.obstacle_choices)))]
        self._check_obstacle(obstacle)
        placement = self._place(scene, obstacle, rng)
        support = [] if placement.pedestal is None else [scene.pedestals[placement.pedestal].geom_id]
        return obstacle, placement, support

    def _settle(self, stepper) -> None:
        """SafeLIBERO's settle: :data:`SETTLE_STEPS` no-op steps (gripper open); with ``settle="still"``, then
        on until the obstacle moves less than :data:`STILL_SPEED` per step (at most :data:`MAX_SETTLE_STEPS`)."""
        stepper.reset()
        for _ in range(SETTLE_STEPS):
            stepper.step(SETTLE_ACTION)
        if self.settle != "still" or self._active_obstacle() is None:
            return
        before = self._obstacle_position()
        for _ in range(MAX_SETTLE_STEPS - SETTLE_STEPS):
            stepper.step(SETTLE_ACTION)
            now = self._obstacle_position()
            if np.abs(now - before).sum() < STILL_SPEED:
                return
            before = now

    def _place(self, scene: Scene, obstacle: str, rng: np.random.Generator) -> Placement:
        handle = scene.obstacles[obstacle]
        problem = self._placement_problem(scene, rng)
        placement = place_obstacle(problem, handle.half_extents, self.level, rng)
        fp = placement.footprint
        support = max(scene.support_heights(fp))
        if placement.pedestal is not None:
            support = raise_pedestal(scene.model, scene.pedestals[placement.pedestal], placement.xy,
                                     placement.yaw, support)
        activate(scene.model, scene.data, handle, placement.xy, placement.yaw, support)
        return placement

    def _active_obstacle(self):
        if self.episode is None or self.episode.obstacle is None:
            return None
        return self.scene.obstacles[self.episode.obstacle]

    def _obstacle_position(self) -> np.ndarray | None:
        handle = self._active_obstacle()
        return None if handle is None else self.scene.data.xpos[handle.body_id].copy()

    def _obstacle_geoms(self) -> np.ndarray:
        return np.array([*self._active_obstacle().geom_ids, *self._support_geoms])

    def _obstacle_contacts(self, within: float = 0.0) -> tuple[str, ...]:
        if self._active_obstacle() is None:
            return ()
        mask = np.zeros(self.scene.model.ngeom, dtype=bool)
        mask[self._obstacle_geoms()] = True
        return self.scene.contact_labels(mask, within)

    def _info(self, contacts: tuple[str, ...]) -> dict:
        displacement = 0.0
        clearance = float("inf")
        if self._active_obstacle() is not None:
            displacement = float(np.abs(self._obstacle_position() - self._obstacle_ref).sum())
            clearance = self.scene.min_distance(self._obstacle_geoms())
        hit = not self._collided and displacement > COLLISION_DISPLACEMENT
        goals = self.scene.goals_fn()
        self._collided = self._collided or hit
        return {
            "is_success": all(goals),
            "goals_met": sum(goals),
            "goals": len(goals),
            "collision": self._collided,
            "robot_obstacle_contact": any(c.startswith(ROBOT_CONTACTS) for c in contacts),
            "obstacle_contacts": contacts,
            "collision_bodies": (contacts or self._obstacle_contacts(within=NEAR_CONTACT)) if hit else (),
            "obstacle_displacement": displacement,
            "min_clearance": clearance,
            "task": self.episode.task,
            "init_state": self.episode.init_state,
            "obstacle": self.episode.obstacle,
            "obstacle_raised": bool(self._support_geoms),
        }

    def _observation(self) -> dict[str, np.ndarray]:
        scene = self.scene
        d = scene.data
        eef_pos, eef_quat = scene.eef_pose()
        poses, mask = scene.tracked_poses(self.object_slots)
        task_id = np.zeros(len(self.suite.tasks))
        task_id[self.suite.suite_task(self.level, self.episode.task)] = 1.0
        obs = {
            "robot_joint_pos": d.qpos[scene.arm_qpos],
            "robot_joint_vel": d.qvel[scene.arm_qvel],
            "gripper_qpos": d.qpos[scene.gripper_qpos],
            "eef_pos": eef_pos,
            "eef_quat": eef_quat,
            "object_poses": poses,
            "object_mask": mask,
            "object_points": scene.tracked_points(self.object_slots),
            "task_id": task_id,
            "obstacle_points": np.zeros((OBSTACLE_POINTS, 3)),
            "obstacle_local_points": np.zeros((OBSTACLE_POINTS, 3)),
            "obstacle_pose": np.zeros(7),
            "obstacle_size": np.zeros(3),
            "obstacle_mask": np.zeros(1),
            "obstacle_support_points": np.zeros((SUPPORT_POINTS, 3)),
            "obstacle_support_local_points": np.zeros((SUPPORT_POINTS, 3)),
            "obstacle_support_pose": np.zeros(7),
            "obstacle_support_mask": np.zeros(1),
        }
        handle = self._active_obstacle()
        if handle is not None:
            rot = d.xmat[handle.body_id].reshape(3, 3)
            pos = d.xpos[handle.body_id]
            quat = d.xquat[handle.body_id]
            obs["obstacle_points"] = handle.local_points @ rot.T + pos
            obs["obstacle_local_points"] = handle.local_points
            obs["obstacle_pose"] = np.concatenate([pos, quat[[1, 2, 3, 0]]])
            obs["obstacle_size"] = handle.half_extents
            obs["obstacle_mask"] = np.ones(1)
        if handle is not None and self._support is not None:
            body = self._support.body_id
            rot, pos = d.xmat[body].reshape(3, 3), d.xpos[body]
            obs["obstacle_support_points"] = self._support.local_points @ rot.T + pos
            obs["obstacle_support_local_points"] = self._support.local_points
            obs["obstacle_support_pose"] = np.concatenate([pos, d.xquat[body][[1, 2, 3, 0]]])
            obs["obstacle_support_mask"] = np.ones(1)
        return {k: np.asarray(v, dtype=np.float32) for k, v in obs.items()}


def _is_int(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _box(shape, low: float = -np.inf, high: float = np.inf) -> spaces.Box:
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    return spaces.Box(low, high, shape, dtype=np.float32)
