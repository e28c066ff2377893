"""Newton-style pick-and-place (``Newton-PickPlace-v0``, ``Newton-PickPlace-Cylinder-v0``).

The paper's fine-tuning task: a Franka Panda picks a cube and places it on a target disc; the Cylinder
variant adds one tall cylinder, placed from the seed on the straight transit, that the straight path would
hit but a detour clears. Built from robosuite primitives on robosuite's table arena; physics, controller
and observation are shared with the SafeLIBERO envs.

Episode layout: the cube starts in a region in front of the robot on its right (y < 0), the target lies
on its left (y > 0), ``0.25-0.35 m`` apart; ``init_state`` indexes 50 fixed layouts (like LIBERO's
official init states), drawn from ``numpy.random.default_rng(index)``.
Success: the cube rests (speed < 5 cm/s) within 3 cm (xy) of the target centre, on the table.
Step limit: 200 control steps (10 s); the scripted expert needs about 120.
"""

from __future__ import annotations

import mujoco
import numpy as np

from detaug_gym.envs.base import ObstacleManipulationEnv
from detaug_gym.envs.obstacles import procedural_bodies
from detaug_gym.envs.placement import Footprint, PlacementProblem
from detaug_gym.envs.scene import PickPlace, Scene, quiet
from detaug_gym.envs.suites import SUITES

CUBE_HALF = 0.02
CYLINDER_RADIUS = 0.035
CYLINDER_HALF_HEIGHT = 0.09
TABLE_TOP = 0.8
SUCCESS_RADIUS = 0.03


def layout(index: int) -> tuple[np.ndarray, float, np.ndarray]:
    """Cube xy, cube yaw and target xy of fixed layout ``index`` (0-49)."""
    rng = np.random.default_rng(10_000 + index)
    cube = np.array([rng.uniform(0.0, 0.12), rng.uniform(-0.2, -0.12)])
    target = np.array([cube[0] + rng.uniform(-0.05, 0.05), rng.uniform(0.1, 0.17)])
    return cube, float(rng.uniform(-np.pi / 4, np.pi / 4)), target


class NewtonPickPlaceEnv(ObstacleManipulationEnv):
    """Pick a cube and place it on a target, optionally around a cylinder.

    Args:
        cylinder: add the cylinder obstacle (the ``-Cylinder-`` id).
        init_state: fix the layout index (0-49); default: drawn from the reset seed and the level.
        controller: ``"fast"`` or ``"stock"``.
        max_episode_steps: truncate after this many steps (``gym.make`` applies the suite's 200 instead).
        settle: ``"steps"`` (10 no-op steps) or ``"still"`` (then on until the cylinder is still).
    """

    obstacle_types = ("cylinder",)

    def __init__(self, cylinder: bool = False, init_state: int | None = None, obstacle: str | None = None,
                 controller: str | None = None, max_episode_steps: int | None = None,
                 render_mode: str | None = None, settle: str = "steps") -> None:
        suite = SUITES["newton"]
        self.cylinder = bool(cylinder)
        kwargs = {} if controller is None else {"controller": controller}
        super().__init__(suite=suite, level="L2" if cylinder else "Free", max_steps=max_episode_steps,
                         obstacle=obstacle, init_state=init_state, render_mode=render_mode, settle=settle, **kwargs)

    def _sample_task(self, rng: np.random.Generator, options: dict) -> int:
        return self.suite.resolve_task(self.level, options.get("task", 0))

    def _build_scene(self, task: int) -> Scene:
        return build_newton_scene(self.cylinder)

    def _load_init_state(self, scene: Scene, task: int, init_state: int, rng: np.random.Generator) -> None:
        cube_xy, yaw, target_xy = layout(init_state)
        d, m = scene.data, scene.model
        d.qpos[scene.arm_qpos] = scene.robot.init_qpos
        d.qpos[scene.gripper_qpos] = scene.robot.gripper.init_qpos
        cube = scene.sim_env.cube_joint_adr
        d.qpos[cube : cube + 7] = (*cube_xy, TABLE_TOP + CUBE_HALF, np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
        m.body_pos[scene.body_id("target")] = (*target_xy, TABLE_TOP + 0.001)

    def _placement_problem(self, scene: Scene, rng: np.random.Generator, step: int | None = None) -> PlacementProblem:
        pick = scene.footprint("cube")
        target = scene.pose_of("target")[:2]
        place = Footprint("target", target - 0.03, target + 0.03)
        start = scene.eef_pose()[0][:2]
        start_height = scene.eef_pose()[0][2] - TABLE_TOP
        return PlacementProblem(pick, place, (), np.array([-0.3, -0.3]), np.array([0.3, 0.3]), start, start_height)


def build_newton_scene(with_cylinder: bool) -> Scene:
    """Compile the Newton table scene."""
    with quiet():
        # LIBERO's import patches robosuite 1.4's MuJoCo bindings for MuJoCo 3 enum types; without it
        # robosuite cannot look up joint addresses on mujoco 3.17.
        import libero.libero.envs  # noqa: F401
    import robosuite
    from robosuite.environments.manipulation.single_arm_env import SingleArmEnv
    from robosuite.models.arenas import TableArena
    from robosuite.models.objects import BoxObject, CylinderObject
    from robosuite.models.tasks import ManipulationTask
    from robosuite.utils.mjcf_utils import new_body, new_geom, new_site

    class NewtonTable(SingleArmEnv):
        """Minimal robosuite env: table, cube, target disc and optional cylinder; we drive it ourselves."""

        def _load_model(self):
            super()._load_model()
            table_size = (0.8, 0.8, 0.05)
            self.robots[0].robot_model.set_base_xpos(
                self.robots[0].robot_model.base_xpos_offset["table"](table_size[0]))
            arena = TableArena(table_full_size=table_size, table_offset=(0, 0, TABLE_TOP))
            arena.set_origin([0, 0, 0])
            self.cube = BoxObject(name="cube", size=[CUBE_HALF] * 3, rgba=[0.8, 0.15, 0.1, 1], density=500)
            objects = [self.cube]
            if with_cylinder:
                objects.append(CylinderObject(name="obstacle_cylinder", size=[CYLINDER_RADIUS, CYLINDER_HALF_HEIGHT],
                                              rgba=[0.2, 0.4, 0.8, 1], density=300))
            self.model = ManipulationTask(mujoco_arena=arena, mujoco_robots=[self.robots[0].robot_model],
                                          mujoco_objects=objects)
            target = new_body(name="target", pos=(0, 0.15, TABLE_TOP + 0.001))
            target.append(new_geom(name="target_disc", type="cylinder", size=(0.04, 0.001), rgba=(0.1, 0.7, 0.2, 0.6),
                                   contype=0, conaffinity=0, group=1))
            target.append(new_site(name="target", pos=(0, 0, 0), size=(0.005,), rgba=(0, 1, 0, 0)))
            self.model.worldbody.append(target)

        def _setup_references(self):
            super()._setup_references()
            joint = self.sim.model.joint_name2id(self.cube.joints[0])
            self.cube_joint_adr = int(self.sim.model.jnt_qposadr[joint])

        def reward(self, action=None):
            return 0.0

    config = robosuite.load_controller_config(default_controller="OSC_POSE")
    sim_env = NewtonTable(robots=["Panda"], controller_configs=config, initialization_noise=None,
                          use_camera_obs=False, has_renderer=False, has_offscreen_renderer=False,
                          hard_reset=False, ignore_done=True, control_freq=20, horizon=10**9)
    sim_env.reset()
    scene_ref: list[Scene] = []

    def goals() -> tuple[bool]:
        scene = scene_ref[0]
        cube = scene.data.xpos[scene.body_id("cube")]
        target = scene.pose_of("target")
        speed = np.linalg.norm(scene.data.cvel[scene.body_id("cube")][3:])
        return (bool(np.linalg.norm(cube[:2] - target[:2]) < SUCCESS_RADIUS and cube[2] < TABLE_TOP + 0.03
                     and speed < 0.05),)

    m = sim_env.sim.model._model
    kinds = procedural_bodies(("cylinder",)) if with_cylinder else {}
    extra_q, extra_v = (7, 6) if with_cylinder else (0, 0)
    scene = Scene(sim_env, [PickPlace("cube", "target")], ["cube", "target"], kinds,
                  (m.nq - extra_q, m.nv - extra_v), goals_fn=goals)
    scene_ref.append(scene)
    mujoco.mj_forward(scene.model, scene.data)
    return scene
