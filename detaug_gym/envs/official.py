"""The official SafeLIBERO scenarios (Hu et al. 2025, THU-RCSCT/vlsa-aegis), read from the user's own copy of
its files: ``safelibero_root=`` or ``$SAFELIBERO_ROOT``, the ``safelibero/libero/libero`` folder of a checkout.

What is read from that folder (nothing of it is part of this package)::

    bddl_files/safelibero_<suite>/<task>.bddl               the scene: LIBERO's objects, six obstacles, one base
    init_files/safelibero_<suite>/<task>_level_<I|II>.pruned_init   50 flattened MuJoCo states per task and level
    assets/obstacle_objects/<category>/<category>.xml       the obstacle and base models the bddl files name

``<task>`` is the SafeLIBERO task name (:attr:`~detaug_gym.envs.suites.TaskSpec.official`). An init file is
LIBERO's format saved with ``torch.save``: a float64 array ``(50, 1 + nq + nv)`` in the bddl scene's own state
layout. It is read here without torch and without running any code from the file (only numpy arrays unpickle).

In each state exactly one obstacle stands in the workspace; SafeLIBERO's rule picks it as the first obstacle
object (bddl order) whose position has ``z > 0`` and ``|x|, |y| < 0.5``; the other five are parked far away.
A base (``box_base`` or the half-height ``box_small_base``) is a free body too: a raised obstacle stands on it.
"""

from __future__ import annotations

import codecs
import io
import os
import pickle
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detaug_gym.envs.scene import Scene, quiet
from detaug_gym.envs.suites import TaskSpec

ROOT_VARIABLE = "SAFELIBERO_ROOT"
LEVEL_FILE_SUFFIX = {"L1": "I", "L2": "II"}
BASE_CATEGORIES = ("box_base", "box_small_base")
WORKSPACE_HALF_WIDTH = 0.5  # m: SafeLIBERO's active-obstacle box, |x|, |y| < 0.5 and z > 0
PENETRATION_TOLERANCE = 1e-3  # m: deeper than this, an official obstacle or base is lifted out before the settle

def is_obstacle_category(category: str) -> bool:
    """Whether a bddl object category is one of SafeLIBERO's obstacles or bases (not part of the task)."""
    return category.endswith("_obstacle") or category in BASE_CATEGORIES


def obstacle_kind(category: str) -> str:
    """The obstacle type reported in ``info["obstacle"]``: the category without ``_obstacle``
    (``moka_pot``, ``moka_pot_small``, ...)."""
    return category.removesuffix("_obstacle")


@dataclass(frozen=True)
class SafeLiberoFiles:
    """The user's SafeLIBERO folder and the paths of its files."""

    root: Path

    @classmethod
    def locate(cls, root: str | os.PathLike | None = None) -> SafeLiberoFiles:
        """``root``, else ``$SAFELIBERO_ROOT``; ``FileNotFoundError`` says what to point at."""
        value = root if root is not None else os.environ.get(ROOT_VARIABLE)
        if not value:
            raise FileNotFoundError(
                "official SafeLIBERO scenarios need the SafeLIBERO files: pass safelibero_root=PATH (bench: "
                f"--safelibero-root PATH) or set {ROOT_VARIABLE} to the safelibero/libero/libero folder of a "
                "THU-RCSCT/vlsa-aegis checkout")
        path = Path(value).expanduser()
        if not path.is_dir():
            raise FileNotFoundError(f"SafeLIBERO root {path} is not a folder; it should be the "
                                    "safelibero/libero/libero folder of a THU-RCSCT/vlsa-aegis checkout (holding "
                                    "bddl_files/, init_files/, assets/obstacle_objects/)")
        return cls(path.resolve())

    def bddl(self, suite: str, task: TaskSpec) -> Path:
        return self.root / "bddl_files" / f"safelibero_{suite}" / f"{task.official}.bddl"

    def init_file(self, suite: str, task: TaskSpec, level: str) -> Path:
        name = f"{task.official}_level_{LEVEL_FILE_SUFFIX[level]}.pruned_init"
        return self.root / "init_files" / f"safelibero_{suite}" / name

    def asset(self, category: str) -> Path:
        return self.root / "assets" / "obstacle_objects" / category / f"{category}.xml"

    def missing(self, suite: str, level: str, tasks: tuple[TaskSpec, ...]) -> list[Path]:
        """The expected files of these tasks at ``level`` that are absent (bddl, init file, obstacle models)."""
        absent = []
        for task in tasks:
            bddl, init = self.bddl(suite, task), self.init_file(suite, task, level)
            absent += [p for p in (bddl, init) if not p.is_file()]
            if bddl.is_file():
                absent += [p for p in map(self.asset, declared_obstacles(bddl)) if not p.is_file()]
        return list(dict.fromkeys(absent))

    def require(self, suite: str, level: str, tasks: tuple[TaskSpec, ...]) -> None:
        """Raise ``FileNotFoundError`` naming every expected file that is absent."""
        absent = self.missing(suite, level, tasks)
        if absent:
            listed = "\n  ".join(str(p) for p in absent)
            raise FileNotFoundError(f"the SafeLIBERO root {self.root} lacks {len(absent)} file(s) of "
                                    f"safelibero_{suite} {level}:\n  {listed}")

    def init_states(self, suite: str, task: TaskSpec, level: str) -> np.ndarray:
        """The official init states of ``task`` at ``level``, ``(50, 1 + nq + nv)`` float64."""
        return read_init_file(self.init_file(suite, task, level))


def declared_obstacles(bddl: Path) -> list[str]:
    """Obstacle and base categories declared in a bddl file's ``:objects`` section, in file order."""
    text = bddl.read_text()
    match = re.search(r"\(:objects(.*?)\)", text, flags=re.S)
    categories = re.findall(r"-\s*([A-Za-z0-9_]+)", match.group(1)) if match else []
    return list(dict.fromkeys(c for c in categories if is_obstacle_category(c)))


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays and nothing else (an init file must not run code)."""

    ALLOWED = {("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
               ("numpy", "ndarray"), ("numpy", "dtype"), ("_codecs", "encode")}

    def find_class(self, module: str, name: str):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"unexpected {module}.{name}")
        if name == "_reconstruct":
            return _reconstruct()
        return codecs.encode if name == "encode" else getattr(np, name)

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("init files hold a plain numpy array, not torch tensors")


def _reconstruct():
    try:
        from numpy._core.multiarray import _reconstruct as fn
    except ImportError:  # numpy < 2
        from numpy.core.multiarray import _reconstruct as fn
    return fn


def read_init_file(path: Path) -> np.ndarray:
    """The states of a LIBERO ``.pruned_init`` file (a ``torch.save`` zip holding a numpy array), ``(N, D)``."""
    try:
        with zipfile.ZipFile(path) as archive:
            member = next(n for n in archive.namelist() if n.endswith("/data.pkl") or n == "data.pkl")
            states = _ArrayUnpickler(io.BytesIO(archive.read(member))).load()
    except (zipfile.BadZipFile, StopIteration, pickle.UnpicklingError, EOFError) as exc:
        raise ValueError(f"{path} is not a SafeLIBERO init file (a torch.save archive of a numpy array): "
                         f"{exc or type(exc).__name__}") from None
    states = np.asarray(states, dtype=np.float64)
    if states.ndim != 2 or not np.all(np.isfinite(states)):
        raise ValueError(f"{path} should hold a finite (episodes, state) array, got shape {states.shape}")
    return states


def register_obstacle_objects(files: SafeLiberoFiles, categories: list[str]) -> None:
    """Make LIBERO's object registry build the SafeLIBERO obstacle and base ``categories`` from the user's
    assets (free joint; LIBERO's usual object attributes). A category registered from the same file stays."""
    with quiet():
        from libero.libero.envs.objects import OBJECTS_DICT
        from robosuite.models.objects import MujocoXMLObject

    for category in categories:
        xml = files.asset(category)
        if getattr(OBJECTS_DICT.get(category), "asset_xml", None) == str(xml):
            continue

        def __init__(self, name=category, _xml=str(xml), _category=category):
            MujocoXMLObject.__init__(self, _xml, name=name, joints=[dict(type="free", damping="0.0005")],
                                     obj_type="all", duplicate_collision_geoms=False)
            self.category_name = _category
            self.rotation = (np.pi / 2, np.pi / 2)
            self.rotation_axis = "x"
            self.object_properties = {"vis_site_names": {}}

        class_name = "".join(part.capitalize() for part in category.split("_"))
        OBJECTS_DICT[category] = type(class_name, (MujocoXMLObject,), {"__init__": __init__, "asset_xml": str(xml)})


def active_obstacle(scene: Scene) -> str | None:
    """The kind of the first obstacle (bddl order, as ``scene.obstacles`` holds them) inside the workspace box,
    or None: SafeLIBERO's rule."""
    return next((kind for kind, h in scene.obstacles.items() if _in_workspace(scene.data.xpos[h.body_id])), None)


def active_bases(scene: Scene, bases: tuple[int, ...]) -> list[int]:
    """The base bodies (root body ids) inside the workspace box."""
    return [b for b in bases if _in_workspace(scene.data.xpos[b])]


def lift_out_of_penetration(scene: Scene, bodies: list[int], tolerance: float = PENETRATION_TOLERANCE) -> float:
    """Raise each of ``bodies`` (free-joint root bodies, lowest first) straight up until none of its collision
    geoms sinks more than ``tolerance`` into another body; returns the largest lift (m).

    Some official states put an obstacle a few centimetres inside its support (e.g. the small moka pot of the
    Long suite, 2.3 cm into the table): MuJoCo then ejects it during the settle, it tumbles and the episode starts
    with a collision nobody caused. Lifting keeps SafeLIBERO's xy and orientation; the settle drops it back.
    """
    import mujoco

    m, d = scene.model, scene.data
    largest = 0.0
    for body in bodies:
        own = np.zeros(m.ngeom, dtype=bool)
        own[scene.collision_geoms(body)] = True
        adr = int(m.jnt_qposadr[m.body_jntadr[body]])
        for _ in range(10):
            mujoco.mj_forward(m, d)
            contacts = d.contact[: d.ncon]
            mine = own[contacts.geom1] != own[contacts.geom2]
            depth = float(-contacts.dist[mine].min()) if mine.any() else 0.0
            if depth <= tolerance:
                break
            d.qpos[adr + 2] += depth
            largest = max(largest, depth)
    mujoco.mj_forward(m, d)
    return largest


def _in_workspace(pos: np.ndarray) -> bool:
    return bool(pos[2] > 0 and abs(pos[0]) < WORKSPACE_HALF_WIDTH and abs(pos[1]) < WORKSPACE_HALF_WIDTH)


def build_official_scene(files: SafeLiberoFiles, suite: str, task: TaskSpec, level: str
                         ) -> tuple[Scene, np.ndarray, tuple[int, ...]]:
    """Compile the official SafeLIBERO scene of ``task`` and read its init states at ``level``.

    Returns:
        The scene (its obstacles, in bddl order, posed by the state and never parked), the init states
        ``(50, 1 + nq + nv)`` and the root body ids of its bases.
    """
    import mujoco

    from detaug_gym.envs.obstacles import OBSTACLE_SETS
    from detaug_gym.envs.safe_libero import compile_libero, libero_scene

    files.require(suite, level, (task,))
    bddl = files.bddl(suite, task)
    register_obstacle_objects(files, declared_obstacles(bddl))
    sim_env = compile_libero(str(bddl))
    m = sim_env.sim.model._model
    obstacles = {obstacle_kind(obj.category_name): obj.root_body for obj in sim_env.objects_dict.values()
                 if is_obstacle_category(obj.category_name) and obj.category_name not in BASE_CATEGORIES}
    bases = tuple(mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, obj.root_body)
                  for obj in sim_env.objects_dict.values() if obj.category_name in BASE_CATEGORIES)
    upright = {kind: v.upright_x for kind, v in OBSTACLE_SETS[0].items()}  # LIBERO's milk carton lies along y
    scene = libero_scene(sim_env, obstacles, (m.nq, m.nv), parked=False, upright_x=upright)
    states = files.init_states(suite, task, level)
    if states.shape[1] != 1 + m.nq + m.nv:
        raise ValueError(f"{files.init_file(suite, task, level)} holds states of {states.shape[1]} entries; the scene "
                         f"of {files.bddl(suite, task)} takes {1 + m.nq + m.nv} (1 + nq + nv)")
    return scene, states, bases
