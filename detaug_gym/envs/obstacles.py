"""SafeLIBERO's obstacle set, added to a robosuite model as free bodies that start parked.

Two procedural sets (:data:`OBSTACLE_SETS`), by scenario version of the env ids. Version 0 (``-v0``): the six
types at LIBERO's own scale and two static pedestals. Version 1 (``-v1``, calibrated to the official SafeLIBERO
scenarios, :mod:`~detaug_gym.envs.calibration`): the nine types SafeLIBERO uses (its moka pot, milk and wine
bottle enlarged 1.6 / 2 / 1.6 times, LIBERO's scale as the ``_small`` ones, the storage box lying on its side) and
two free, movable bases with the outer size of SafeLIBERO's (``box_base`` 14 cm tall, ``box_small_base`` 7.6 cm).
Version 2 (``-v2``) changes where obstacles stand and the scene around them, not the set: it compiles version 1's.
Every type and base of a set is compiled into the model once, so that an episode can switch the active obstacle
with a soft reset. Inactive obstacles are parked far below the
scene with contacts and gravity switched off; the active one gets its contacts and gravity back and is
set down on the support surface. Obstacle joints come after every LIBERO joint in ``qpos``, so LIBERO's
official init states fill the leading part of the state unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import trimesh

from detaug_gym.envs.placement import PEDESTALS
from detaug_gym.geometry.meshes import (
    body_collision_mesh,
    geom_pose_in_body,
    geom_trimesh,
    is_collision_geom,
    sample_surface,
)

OBSTACLE_POINTS = 256  # surface samples per obstacle in the observation
SUPPORT_POINTS = 128  # surface samples of what the obstacle stands on (a pedestal or base) in the observation
PARK_DEPTH = -5.0  # z of parked obstacles (below the floor, out of every sensor's way)


@dataclass(frozen=True)
class ObstacleVariant:
    """How a procedural set builds one obstacle type.

    Attributes:
        category: the LIBERO object category of its model.
        scale: uniform scale on the LIBERO model (meshes, geoms, positions; mass by volume).
        upright_x: rotation about x (rad) that stands it as the scenarios do (LIBERO's milk carton lies along y;
            SafeLIBERO lays the storage box on its side).
    """

    category: str
    scale: float = 1.0
    upright_x: float = 0.0


OBSTACLE_SETS: dict[int, dict[str, ObstacleVariant]] = {
    0: {"moka_pot": ObstacleVariant("moka_pot"), "white_storage_box": ObstacleVariant("white_storage_box"),
        "milk": ObstacleVariant("milk", upright_x=np.pi / 2), "wine_bottle": ObstacleVariant("wine_bottle"),
        "red_coffee_mug": ObstacleVariant("red_coffee_mug"), "yellow_book": ObstacleVariant("yellow_book")},
    # SafeLIBERO's types and sizes: its moka pot at mesh scale 0.04 (LIBERO 0.025), milk 0.015 (0.0075), wine
    # bottle 0.8 (0.5); its "_small" ones are LIBERO's.
    1: {"moka_pot": ObstacleVariant("moka_pot", 1.6), "moka_pot_small": ObstacleVariant("moka_pot"),
        "milk": ObstacleVariant("milk", 2.0, np.pi / 2), "milk_small": ObstacleVariant("milk", upright_x=np.pi / 2),
        "wine_bottle": ObstacleVariant("wine_bottle", 1.6), "wine_bottle_small": ObstacleVariant("wine_bottle"),
        "white_storage_box": ObstacleVariant("white_storage_box", upright_x=np.pi / 2),
        "red_coffee_mug": ObstacleVariant("red_coffee_mug"), "yellow_book": ObstacleVariant("yellow_book")},
}
OBSTACLE_SETS[2] = OBSTACLE_SETS[1]
OBSTACLE_TYPES = tuple(OBSTACLE_SETS[0])  # version 0's types, in its compile order
# Version 1's movable bases: free boxes with the outer size of SafeLIBERO's (half-extents, m) and its density.
BASES: dict[str, np.ndarray] = {
    "box_base": np.array([0.0704, 0.0583, 0.0701]),
    "box_small_base": np.array([0.0704, 0.0583, 0.0382]),
}
BASE_DENSITY = 100.0  # kg/m^3, SafeLIBERO's base
SCENARIO_VERSIONS = tuple(OBSTACLE_SETS)


def obstacle_body_name(kind: str) -> str:
    return f"obstacle_{kind}"


def add_obstacles_to_model(task_model, object_factory, version: int = 0) -> None:
    """Append a procedural set to a robosuite ``ManipulationTask``: its obstacles (free joints), then version 0's
    two static pedestals or version 1's two free bases.

    Args:
        task_model: robosuite ``ManipulationTask`` (``env.model`` inside ``_load_model``).
        object_factory: ``category -> class`` (LIBERO's ``get_object_fn``).
        version: the scenario version (:data:`SCENARIO_VERSIONS`).
    """
    from robosuite.models.objects import BoxObject
    from robosuite.utils.mjcf_utils import new_body, new_geom

    objects = []
    for kind, variant in OBSTACLE_SETS[version].items():
        obj = object_factory(variant.category)(name=obstacle_body_name(kind))
        if variant.scale != 1.0:
            _scale_object(obj, variant.scale)
        objects.append(obj)
    if version >= 1:
        objects += [BoxObject(name=name, size=tuple(half), rgba=(0.76, 0.6, 0.42, 1.0), density=BASE_DENSITY,
                              friction=(0.95, 0.3, 0.1)) for name, half in BASES.items()]
    task_model.merge_objects(objects)
    if version >= 1:
        return
    for i, (name, half) in enumerate(PEDESTALS.items()):
        body = new_body(name=f"pedestal_{name}", pos=(0.0, 2.0 * i, PARK_DEPTH))
        body.append(
            new_geom(name=f"pedestal_{name}_box", type="box", size=tuple(half), rgba=(0.93, 0.93, 0.9, 1.0),
                     group=0, friction=(1.0, 0.005, 0.0001), solref=(0.01, 1), density=500)
        )
        task_model.worldbody.append(body)


@dataclass
class ObstacleHandle:
    """Indices and geometry of one obstacle body in a compiled model.

    Attributes:
        kind: obstacle type.
        body_id: the obstacle's root body.
        qpos_adr, dof_adr: start of its free joint in ``qpos`` (7) and ``qvel`` (6).
        geom_ids: its collision geoms; ``contype``/``conaffinity`` saved to restore on activation.
        local_points: ``(OBSTACLE_POINTS, 3)`` surface samples in the body frame.
        upright_quat: body orientation (wxyz) that stands the asset upright before any yaw.
        local_lo, local_hi: axis-aligned bounds of the collision mesh in the upright frame, ``(3,)`` each.
    """

    kind: str
    body_id: int
    qpos_adr: int
    dof_adr: int
    geom_ids: np.ndarray
    contype: np.ndarray
    conaffinity: np.ndarray
    local_points: np.ndarray
    upright_quat: np.ndarray
    local_lo: np.ndarray
    local_hi: np.ndarray

    @property
    def half_extents(self) -> np.ndarray:
        return 0.5 * (self.local_hi - self.local_lo)

    def pose_on_support(self, xy: np.ndarray, yaw: float, support_z: float) -> tuple[np.ndarray, np.ndarray]:
        """Body position and quaternion (wxyz) that stand the obstacle upright with its bounds centred
        on ``xy`` and its lowest point on ``support_z``, rotated by ``yaw`` about z."""
        q_yaw = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
        quat = np.zeros(4)
        mujoco.mju_mulQuat(quat, q_yaw, self.upright_quat)
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, q_yaw)
        anchor = np.array([0.5 * (self.local_lo[0] + self.local_hi[0]),
                           0.5 * (self.local_lo[1] + self.local_hi[1]), self.local_lo[2]])
        pos = np.array([xy[0], xy[1], support_z]) - rot.reshape(3, 3) @ anchor
        return pos, quat


@dataclass
class PedestalHandle:
    name: str
    body_id: int
    geom_id: int
    half: np.ndarray


def _scale_object(obj, factor: float) -> None:
    """Scale a robosuite XML object in place before it is merged: mesh scales, geom sizes (primitive geoms),
    every body, geom, site and inertial position, and inertial masses (by volume)."""
    for mesh in obj.asset.iter("mesh"):
        scale = np.array([float(v) for v in mesh.get("scale", "1 1 1").split()])
        mesh.set("scale", " ".join(f"{v:g}" for v in scale * factor))
    for el in obj._obj.iter():
        if "pos" in el.attrib:
            el.set("pos", " ".join(f"{float(v) * factor:g}" for v in el.get("pos").split()))
        if el.tag in ("geom", "site") and "size" in el.attrib and el.get("type") != "mesh":
            el.set("size", " ".join(f"{float(v) * factor:g}" for v in el.get("size").split()))
        if el.tag == "inertial" and "mass" in el.attrib:
            el.set("mass", f"{float(el.get('mass')) * factor ** 3:g}")
            if "diaginertia" in el.attrib:
                el.set("diaginertia", " ".join(f"{float(v) * factor ** 5:g}" for v in el.get("diaginertia").split()))


def procedural_bodies(kinds: tuple[str, ...] = OBSTACLE_TYPES) -> dict[str, str]:
    """``{kind: root body}`` of the obstacles :func:`add_obstacles_to_model` compiles in (``obstacle_<kind>_main``)."""
    return {kind: f"{obstacle_body_name(kind)}_main" for kind in kinds}


def procedural_joints(version: int) -> int:
    """How many free joints :func:`add_obstacles_to_model` appends for ``version`` (obstacles and bases)."""
    return len(OBSTACLE_SETS[version]) + (len(BASES) if version >= 1 else 0)


def obstacle_handles(model: mujoco.MjModel, bodies: dict[str, str],
                     upright_x: dict[str, float] | None = None) -> dict[str, ObstacleHandle]:
    """The obstacles of a compiled model, from ``{kind: root body name}`` (each body has a free joint);
    ``upright_x`` gives the rotation about x that stands a kind as the scenarios do (default: none)."""
    upright_x = upright_x or {}
    handles = {}
    for kind, body in bodies.items():
        body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
        if body_id < 0:
            raise KeyError(f"obstacle body {body!r} ({kind}) missing from the model")
        joint = int(model.body_jntadr[body_id])
        geoms = np.array(
            [g for g in range(model.ngeom) if model.geom_bodyid[g] == body_id and is_collision_geom(model, g)]
        )
        mesh = body_collision_mesh(model, body_id)
        angle = upright_x.get(kind, 0.0)
        upright = np.array([np.cos(angle / 2), np.sin(angle / 2), 0.0, 0.0])
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, upright)
        upright_vertices = mesh.vertices @ rot.reshape(3, 3).T
        handles[kind] = ObstacleHandle(
            kind=kind,
            body_id=body_id,
            qpos_adr=int(model.jnt_qposadr[joint]),
            dof_adr=int(model.jnt_dofadr[joint]),
            geom_ids=geoms,
            contype=model.geom_contype[geoms].copy(),
            conaffinity=model.geom_conaffinity[geoms].copy(),
            local_points=sample_surface(mesh, OBSTACLE_POINTS, seed=0),
            upright_quat=upright,
            local_lo=upright_vertices.min(axis=0),
            local_hi=upright_vertices.max(axis=0),
        )
    return handles


def pedestal_handles(model: mujoco.MjModel) -> dict[str, PedestalHandle]:
    """The pedestals of a compiled model (none where :func:`add_obstacles_to_model` was not applied)."""
    out = {}
    for name, half in PEDESTALS.items():
        body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"pedestal_{name}")
        if body_id < 0:
            continue
        geom_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"pedestal_{name}_box")
        out[name] = PedestalHandle(name, body_id, geom_id, half.copy())
    return out


def base_handles(model: mujoco.MjModel) -> dict[str, ObstacleHandle]:
    """Version 1's movable bases of a compiled model (none where they were not compiled in)."""
    names = {name: f"{name}_main" for name in BASES}
    present = {n: b for n, b in names.items() if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b) >= 0}
    return obstacle_handles(model, present) if present else {}


def park_all(model: mujoco.MjModel, data: mujoco.MjData, obstacles: dict[str, ObstacleHandle],
             pedestals: dict[str, PedestalHandle], bases: dict[str, ObstacleHandle] | None = None) -> None:
    """Move every obstacle, base and pedestal out of the scene, with contacts and gravity off."""
    for i, h in enumerate([*obstacles.values(), *(bases or {}).values()]):
        model.geom_contype[h.geom_ids] = 0
        model.geom_conaffinity[h.geom_ids] = 0
        model.body_gravcomp[h.body_id] = 1.0
        data.qpos[h.qpos_adr : h.qpos_adr + 7] = (3.0 + i, 3.0, PARK_DEPTH, 1.0, 0.0, 0.0, 0.0)
        data.qvel[h.dof_adr : h.dof_adr + 6] = 0.0
    for i, p in enumerate(pedestals.values()):
        model.body_pos[p.body_id] = (-3.0 - i, 3.0, PARK_DEPTH)
        model.geom_contype[p.geom_id] = 0
        model.geom_conaffinity[p.geom_id] = 0


def activate(model: mujoco.MjModel, data: mujoco.MjData, handle: ObstacleHandle, xy: np.ndarray,
             yaw: float, support_z: float) -> None:
    """Give ``handle`` its contacts and gravity back and stand it on ``support_z`` at ``xy``, yawed."""
    model.geom_contype[handle.geom_ids] = handle.contype
    model.geom_conaffinity[handle.geom_ids] = handle.conaffinity
    model.body_gravcomp[handle.body_id] = 0.0
    pos, quat = handle.pose_on_support(xy, yaw, support_z + 5e-4)
    data.qpos[handle.qpos_adr : handle.qpos_adr + 3] = pos
    data.qpos[handle.qpos_adr + 3 : handle.qpos_adr + 7] = quat
    data.qvel[handle.dof_adr : handle.dof_adr + 6] = 0.0


def raise_pedestal(model: mujoco.MjModel, pedestal: PedestalHandle, xy: np.ndarray, yaw: float,
                   support_z: float) -> float:
    """Stand ``pedestal`` on the support at ``xy``; returns the height of its top face."""
    model.body_pos[pedestal.body_id] = (xy[0], xy[1], support_z + pedestal.half[2])
    model.body_quat[pedestal.body_id] = (np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2))
    model.geom_contype[pedestal.geom_id] = 1
    model.geom_conaffinity[pedestal.geom_id] = 1
    return support_z + 2 * pedestal.half[2]


@dataclass(frozen=True)
class SupportView:
    """What the obstacle stands on (a pedestal or base), as the observation shows it.

    Attributes:
        body_id: the body whose frame the points are fixed in (the body of the first support geom).
        local_points: ``(SUPPORT_POINTS, 3)`` points on the support geoms in that body's frame: the vertices of
            their convex hull (at most half of them), then area-weighted surface samples.
    """

    body_id: int
    local_points: np.ndarray


def support_view(model: mujoco.MjModel, data: mujoco.MjData, geom_ids: list[int]) -> SupportView | None:
    """The support geoms ``geom_ids`` (as placed now: ``data`` after ``mj_forward``) as one :class:`SupportView`,
    or ``None`` without any. Geoms of several bodies are fixed in the first one's frame as they stand now."""
    if not geom_ids:
        return None
    body = int(model.geom_bodyid[geom_ids[0]])
    rotation = data.xmat[body].reshape(3, 3)
    to_body = np.eye(4)
    to_body[:3, :3], to_body[:3, 3] = rotation.T, -rotation.T @ data.xpos[body]
    parts = []
    for g in geom_ids:
        owner = int(model.geom_bodyid[g])
        world = np.eye(4)
        world[:3, :3], world[:3, 3] = data.xmat[owner].reshape(3, 3), data.xpos[owner]
        mesh = geom_trimesh(model, int(g))
        mesh.apply_transform(to_body @ world @ geom_pose_in_body(model, int(g)))
        parts.append(mesh)
    mesh = trimesh.util.concatenate(parts)
    corners = np.asarray(mesh.convex_hull.vertices)[: SUPPORT_POINTS // 2]  # a hull of samples alone cuts corners
    samples = sample_surface(mesh, SUPPORT_POINTS - len(corners), seed=0)
    return SupportView(body, np.concatenate([corners, samples]))
