"""The suite registry: every question about a suite (env ids, levels, tasks, step limits, init states) has
its answer here, and no other module spells an env id.

SafeLIBERO (Hu et al. 2025) evaluates 4 tasks per suite at two obstacle levels. The Goal suite uses a
different fourth task per level ("open the top drawer and put the bowl inside" at Level 1, "put the cream
cheese in the bowl" at Level 2); its Free variant offers both, so it has five tasks. The Newton-style
pick-and-place (the paper's fine-tuning task) is a suite too: one task, a Free level and one obstacle
level (L2, the cylinder on the path).

    >>> from detaug_gym.envs.suites import SUITES, suite_of_env
    >>> SUITES["spatial"].env_id("L2")
    'SafeLibero-Spatial-L2-v2'
    >>> SUITES["spatial"].env_id("L2", version=0)
    'SafeLibero-Spatial-L2-v0'
    >>> suite_of_env("Newton-PickPlace-Cylinder-v0")
    (SuiteSpec(name='newton', ...), 'L2')
"""

from __future__ import annotations

from dataclasses import dataclass, field

LEVELS = ("L1", "L2", "Free")
LEVEL_ALIASES = {"1": "L1", "l1": "L1", "2": "L2", "l2": "L2", "free": "Free"}
NUM_INIT_STATES = 50  # LIBERO's official init states per task (and Newton's fixed layouts)
ENV_PREFIX = "detaug_gym:"  # gymnasium's "module:EnvId" form
SCENARIO_VERSION = 2  # the current procedural scenarios of SafeLIBERO's L1/L2 ids
# Official episodes are the same under every version's id; the bench files them under the -v1 id (where it first
# did), so a results folder stays resumable when the procedural scenarios get a new version.
OFFICIAL_ID_VERSION = 1


@dataclass(frozen=True)
class TaskSpec:
    """One task of a suite.

    Attributes:
        key: short name used in ids, file names and the scripted expert's recipes (``"bowl_on_stove"``).
        libero_suite: LIBERO benchmark name (``"libero_spatial"``; empty for Newton).
        libero_index: index of the task inside that benchmark (task order 0; -1 for Newton).
        language: the instruction, as a person would type it.
        official: SafeLIBERO's name of the task (its bddl file's stem; empty where SafeLIBERO has none).
    """

    key: str
    libero_suite: str
    libero_index: int
    language: str
    official: str = ""


@dataclass(frozen=True)
class SuiteSpec:
    """A suite: what its envs are and how episodes are drawn.

    Attributes:
        name: ``"spatial" | "object" | "goal" | "long" | "newton"``.
        max_steps: control steps (20 Hz) before truncation.
        tasks: every task of the suite (the Free level offers all of them).
        level_tasks: indices into ``tasks`` for each obstacle level, in SafeLIBERO's order.
        object_slots: rows of the ``object_poses`` observation (task-relevant objects, zero padded).
        ids: env id per level (the levels this suite has), the current scenario version.
        legacy_ids: ``{version: {level: env id}}`` of older scenario versions that stay registered and reproducible
            (SafeLIBERO's L1/L2 ``-v0``: the procedural scenarios before their calibration to the official ones;
            ``-v1``: calibrated spots on LIBERO's unedited layouts).
        entry_point: gymnasium entry point of its env class; ``kwargs`` per level are given by ``env_kwargs``.
        max_grasps: most grasps of any task (DetAug's label has 4 entries per grasp).
        num_init_states: init states per task (LIBERO's 50 official ones; Newton's 50 fixed layouts).
        shape_source_level: level whose scene holds SafeLIBERO's obstacle set (DemoGen takes its meshes
            from there), or None when the suite has none.
        official: whether SafeLIBERO has official scenarios of this suite (``scenarios="official"``).
        aegis_max_steps: AEGIS's step limit for the suite (the bench's ``--step-limits aegis``).
        infeasible: task indices per level that the DetAug authors leave out as infeasible (``--cells feasible``).
    """

    name: str
    max_steps: int
    tasks: tuple[TaskSpec, ...]
    level_tasks: dict[str, tuple[int, ...]]
    object_slots: int
    ids: dict[str, str]
    entry_point: str
    max_grasps: int = 1
    num_init_states: int = NUM_INIT_STATES
    shape_source_level: str | None = "L1"
    level_kwargs: dict[str, dict] = field(default_factory=dict)
    official: bool = False
    aegis_max_steps: int | None = None
    infeasible: dict[str, tuple[int, ...]] = field(default_factory=dict)
    legacy_ids: dict[int, dict[str, str]] = field(default_factory=dict)

    @property
    def levels(self) -> tuple[str, ...]:
        """The levels this suite has, in :data:`LEVELS` order."""
        return tuple(level for level in LEVELS if level in self.ids)

    def env_id(self, level: str, version: int | None = None) -> str:
        """The registered env id of ``level`` (``"L1"``, ``"1"``, ``"free"``, ...): the current scenarios, or
        those of an older ``version`` where the level has one (a level a version did not change keeps its id)."""
        level = self.check_level(level)
        if version is None or version == self.version(self.ids[level]):
            return self.ids[level]
        if version in self.legacy_ids:
            return self.legacy_ids[version].get(level, self.ids[level])
        known = sorted({self.version(i) for i in self.ids.values()} | set(self.legacy_ids))
        raise ValueError(f"suite {self.name!r} has no scenario version {version!r}; its versions: "
                         f"{', '.join(map(str, known))}")

    @staticmethod
    def version(env_id: str) -> int:
        """The scenario version of an env id (its ``-vN`` suffix)."""
        return int(env_id.rsplit("-v", 1)[1])

    def env_kwargs(self, level: str, version: int | None = None) -> dict:
        """Constructor kwargs the registration passes for ``level`` (at ``version``, default the current one)."""
        kwargs = dict(self.level_kwargs.get(self.check_level(level), {}))
        if "version" in kwargs:
            kwargs["version"] = self.version(self.env_id(level, version))
        return kwargs

    def registered(self) -> list[tuple[str, str, int]]:
        """Every ``(env id, level, version)`` this suite registers: the current ids, then the legacy ones."""
        rows = [(self.ids[lv], lv, self.version(self.ids[lv])) for lv in self.levels]
        return rows + [(i, lv, v) for v, ids in sorted(self.legacy_ids.items()) for lv, i in ids.items()]

    def check_level(self, level: str) -> str:
        """The canonical level name; ``ValueError`` names the levels this suite has."""
        canonical = parse_level(level)
        if canonical not in self.ids:
            raise ValueError(f"suite {self.name!r} has no level {level!r}; its levels: {', '.join(self.levels)}")
        return canonical

    def tasks_for(self, level: str) -> tuple[TaskSpec, ...]:
        """The tasks offered at ``level``."""
        level = self.check_level(level)
        if level == "Free" or level not in self.level_tasks:
            return self.tasks
        return tuple(self.tasks[i] for i in self.level_tasks[level])

    def suite_task(self, level: str, task: int) -> int:
        """Index into :attr:`tasks` (the suite's own order, which the observation's ``task_id`` one-hot uses at
        every level) of task ``task`` of ``level``'s list: Goal's Level 2 task 3 is the suite's task 4."""
        level = self.check_level(level)
        if level == "Free" or level not in self.level_tasks:
            return int(task)
        return int(self.level_tasks[level][task])

    def resolve_task(self, level: str, task) -> int:
        """Index (into ``tasks_for(level)``) of ``task`` given as an index, key, instruction or SafeLIBERO name.

        Integer types (``int``, ``numpy.int64``) are indices; ``bool`` is not.

        Raises:
            ValueError: the task is not offered at this level; the message lists the valid choices.
        """
        tasks = self.tasks_for(level)
        if _is_index(task):
            if 0 <= int(task) < len(tasks):
                return int(task)
        elif isinstance(task, str):
            wanted = task.strip().lower().replace("_", " ")
            for i, spec in enumerate(tasks):
                if wanted in (spec.key.replace("_", " "), spec.language, spec.official.lower().replace("_", " ")):
                    return i
        choices = "; ".join(f"{i} = {t.key} ({t.language!r})" for i, t in enumerate(tasks))
        raise ValueError(f"unknown task {task!r} for {self.name} {level}; valid tasks: {choices}")

    def check_init_state(self, index) -> int:
        """``index`` as an int if it names one of the init states, else ``ValueError``."""
        if not (_is_index(index) and 0 <= int(index) < self.num_init_states):
            raise ValueError(f"init_state must be an index in [0, {self.num_init_states}), got {index!r}")
        return int(index)


def _is_index(value) -> bool:
    import numbers

    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def parse_level(level: str) -> str:
    """``"L1"`` for ``"L1"``, ``"l1"`` or ``"1"`` (likewise L2, Free); ``ValueError`` lists the valid forms."""
    if level in LEVELS:
        return level
    canonical = LEVEL_ALIASES.get(str(level).strip().lower())
    if canonical is None:
        raise ValueError(f"unknown level {level!r}; valid levels: {', '.join(LEVELS)} (or 1, 2, free)")
    return canonical


def _safelibero(name: str, max_steps: int, tasks: tuple[TaskSpec, ...], level_tasks: dict, object_slots: int,
                max_grasps: int, aegis_max_steps: int, infeasible: dict | None = None) -> SuiteSpec:
    # Version 2 (L1/L2): procedural scenarios calibrated to the official ones, with SafeLIBERO's scene edits
    # (docs/scenarios.md); versions 0 and 1 stay registered. The Free level has no obstacle and keeps -v0.
    ids = {level: f"SafeLibero-{name.capitalize()}-{level}-v{SCENARIO_VERSION if level != 'Free' else 0}"
           for level in LEVELS}
    legacy = {v: {level: f"SafeLibero-{name.capitalize()}-{level}-v{v}" for level in ("L1", "L2")} for v in (0, 1)}
    return SuiteSpec(name, max_steps, tasks, level_tasks, object_slots, ids,
                     "detaug_gym.envs.safe_libero:SafeLiberoEnv", max_grasps,
                     level_kwargs={level: {"suite": name, "level": level, "version": 0} for level in LEVELS},
                     official=True, aegis_max_steps=aegis_max_steps, infeasible=infeasible or {},
                     legacy_ids=legacy)


def _spatial(key: str, index: int, where: str) -> TaskSpec:
    language = f"pick up the black bowl {where} and place it on the plate"
    return TaskSpec(key, "libero_spatial", index, language, language.replace(" ", "_"))


def _object(key: str, index: int, what: str) -> TaskSpec:
    language = f"pick up the {what} and place it in the basket"
    return TaskSpec(key, "libero_object", index, language, language.replace(" ", "_"))


def _goal(key: str, index: int, language: str) -> TaskSpec:
    return TaskSpec(key, "libero_goal", index, language, language.replace(" ", "_"))


def _long(key: str, index: int, scene: int, language: str, official: str) -> TaskSpec:
    return TaskSpec(key, "libero_10", index, language, f"LIVING_ROOM_SCENE{scene}_{official}")


SUITES: dict[str, SuiteSpec] = {
    "spatial": _safelibero(
        "spatial", 220,
        (
            _spatial("bowl_between_plate_ramekin", 0, "between the plate and the ramekin"),
            _spatial("bowl_on_ramekin", 5, "on the ramekin"),
            _spatial("bowl_on_stove", 7, "on the stove"),
            _spatial("bowl_on_cabinet", 9, "on the wooden cabinet"),
        ),
        {"L1": (0, 1, 2, 3), "L2": (0, 1, 2, 3)}, object_slots=2, max_grasps=1,
        aegis_max_steps=300, infeasible={"L1": (0,), "L2": (0,)},
    ),
    "object": _safelibero(
        "object", 280,
        (
            _object("orange_juice", 9, "orange juice"),
            _object("chocolate_pudding", 8, "chocolate pudding"),
            _object("milk", 7, "milk"),
            _object("bbq_sauce", 3, "bbq sauce"),
        ),
        {"L1": (0, 1, 2, 3), "L2": (0, 1, 2, 3)}, object_slots=2, max_grasps=1, aegis_max_steps=300,
    ),
    "goal": _safelibero(
        "goal", 300,
        (
            _goal("bowl_on_plate", 8, "put the bowl on the plate"),
            _goal("bowl_on_cabinet", 4, "put the bowl on top of the cabinet"),
            _goal("bowl_on_stove", 1, "put the bowl on the stove"),
            _goal("drawer_bowl", 3, "open the top drawer and put the bowl inside"),
            _goal("cream_cheese_in_bowl", 6, "put the cream cheese in the bowl"),
        ),
        # the drawer task: drawer handle, then bowl
        {"L1": (0, 1, 2, 3), "L2": (0, 1, 2, 4)}, object_slots=2, max_grasps=2, aegis_max_steps=300,
    ),
    "long": _safelibero(
        "long", 520,
        (
            _long("soup_cheese_basket", 7, 1, "put both the alphabet soup and the cream cheese box in the basket",
                  "put_both_the_alphabet_soup_and_the_cream_cheese_box_in_the_basket"),
            _long("soup_sauce_basket", 0, 2, "put both the alphabet soup and the tomato sauce in the basket",
                  "put_both_the_alphabet_soup_and_the_tomato_sauce_in_the_basket"),
            _long("mugs_on_plates", 4, 5,
                  "put the white mug on the left plate and the yellow and white mug on the right plate",
                  "put_the_white_mug_on_the_left_plate_and_put_the_yellow_and_white_mug_on_the_right_plate"),
            _long("mug_plate_pudding", 6, 6,
                  "put the white mug on the plate and the chocolate pudding to the right of the plate",
                  "put_the_white_mug_on_the_plate_and_put_the_chocolate_pudding_to_the_right_of_the_plate"),
        ),
        {"L1": (0, 1, 2, 3), "L2": (0, 1, 2, 3)}, object_slots=4, max_grasps=2,
        aegis_max_steps=550, infeasible={"L1": (0,)},
    ),
    "newton": SuiteSpec(
        name="newton",
        max_steps=200,
        tasks=(TaskSpec("newton_cube", "", -1, "pick up the cube and place it on the target"),),
        level_tasks={"L2": (0,)},
        object_slots=2,
        ids={"L2": "Newton-PickPlace-Cylinder-v0", "Free": "Newton-PickPlace-v0"},
        entry_point="detaug_gym.envs.newton:NewtonPickPlaceEnv",
        max_grasps=1,
        shape_source_level=None,
        level_kwargs={"L2": {"cylinder": True}, "Free": {"cylinder": False}},
    ),
}


def get_suite(name: str) -> SuiteSpec:
    """The suite called ``name`` (case-insensitive); ``ValueError`` lists the valid names."""
    key = str(name).lower()
    if key not in SUITES:
        raise ValueError(f"unknown suite {name!r}; valid suites: {', '.join(SUITES)}")
    return SUITES[key]


def suite_of_env(env_id: str) -> tuple[SuiteSpec, str]:
    """``(suite, level)`` of a registered env id (``"detaug_gym:"`` prefix allowed); ``ValueError`` lists the ids."""
    bare = env_id[len(ENV_PREFIX):] if env_id.startswith(ENV_PREFIX) else env_id
    for suite in SUITES.values():
        for candidate, level, _ in suite.registered():
            if candidate == bare:
                return suite, level
    raise ValueError(f"unknown env id {env_id!r}; registered ids: {', '.join(all_env_ids())}")


def all_env_ids() -> list[str]:
    """Every registered env id of every suite, suite by suite (current ids, then legacy ones)."""
    return [env_id for suite in SUITES.values() for env_id, _, _ in suite.registered()]
