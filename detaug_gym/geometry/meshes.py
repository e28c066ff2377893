"""Triangle meshes of MuJoCo collision geoms, for surface sampling and exact signed distances.

Every module that needs the shape of a robot link or an obstacle goes through here, so that the env's
clearance, the planners and the collision costs agree on what a body looks like.
"""

from __future__ import annotations

import mujoco
import numpy as np
import trimesh

from detaug_gym.rotations import quat_wxyz_to_mat


def is_collision_geom(model: mujoco.MjModel, geom_id: int) -> bool:
    """True where the geom takes part in contacts (visual-only geoms have contype = conaffinity = 0)."""
    return bool(model.geom_contype[geom_id] or model.geom_conaffinity[geom_id])


def geom_trimesh(model: mujoco.MjModel, geom_id: int) -> trimesh.Trimesh:
    """The geom's shape in its own frame (primitive types tessellated, meshes copied).

    Raises:
        ValueError: for geom types without a closed surface (planes, height fields).
    """
    gtype = int(model.geom_type[geom_id])
    size = np.asarray(model.geom_size[geom_id], dtype=np.float64)
    if gtype == mujoco.mjtGeom.mjGEOM_BOX:
        return trimesh.creation.box(extents=2.0 * size)
    if gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
        return trimesh.creation.icosphere(subdivisions=2, radius=size[0])
    if gtype == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return trimesh.creation.cylinder(radius=size[0], height=2.0 * size[1], sections=24)
    if gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return trimesh.creation.capsule(radius=size[0], height=2.0 * size[1], count=[12, 12])
    if gtype == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        sphere = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
        sphere.apply_scale(size)
        return sphere
    if gtype == mujoco.mjtGeom.mjGEOM_MESH:
        mesh_id = int(model.geom_dataid[geom_id])
        v0, nv = int(model.mesh_vertadr[mesh_id]), int(model.mesh_vertnum[mesh_id])
        f0, nf = int(model.mesh_faceadr[mesh_id]), int(model.mesh_facenum[mesh_id])
        vertices = np.asarray(model.mesh_vert[v0 : v0 + nv], dtype=np.float64)
        faces = np.asarray(model.mesh_face[f0 : f0 + nf], dtype=np.int64)
        return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    raise ValueError(f"geom {geom_id} has type {gtype}, which has no closed surface to mesh")


def geom_pose_in_body(model: mujoco.MjModel, geom_id: int) -> np.ndarray:
    """4x4 transform of the geom frame in its body's frame."""
    transform = np.eye(4)
    transform[:3, :3] = quat_wxyz_to_mat(model.geom_quat[geom_id])
    transform[:3, 3] = model.geom_pos[geom_id]
    return transform


def body_collision_mesh(model: mujoco.MjModel, body_id: int, include_children: bool = False) -> trimesh.Trimesh:
    """All collision geoms of a body (optionally its subtree) merged into one mesh in the body frame.

    Raises:
        ValueError: the body has no collision geoms.
    """
    bodies = {body_id}
    if include_children:
        for b in range(model.nbody):
            parent = b
            while parent > 0 and parent not in bodies:
                parent = int(model.body_parentid[parent])
            if parent in bodies:
                bodies.add(b)
    parts = []
    for gid in range(model.ngeom):
        owner = int(model.geom_bodyid[gid])
        if owner not in bodies or not is_collision_geom(model, gid):
            continue
        mesh = geom_trimesh(model, gid)
        mesh.apply_transform(_relative_body_pose(model, owner, body_id) @ geom_pose_in_body(model, gid))
        parts.append(mesh)
    if not parts:
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body_id)
        raise ValueError(f"body {name!r} has no collision geoms")
    return trimesh.util.concatenate(parts)


def _relative_body_pose(model: mujoco.MjModel, body_id: int, root_id: int) -> np.ndarray:
    """Pose of ``body_id`` in the frame of its ancestor ``root_id`` from the model's rest offsets."""
    transform = np.eye(4)
    b = body_id
    while b != root_id:
        local = np.eye(4)
        local[:3, :3] = quat_wxyz_to_mat(model.body_quat[b])
        local[:3, 3] = model.body_pos[b]
        transform = local @ transform
        b = int(model.body_parentid[b])
        if b == 0 and root_id != 0:
            raise ValueError(f"body {root_id} is not an ancestor of body {body_id}")
    return transform


def sample_surface(mesh: trimesh.Trimesh, count: int, seed: int = 0) -> np.ndarray:
    """``count`` area-weighted random points (fixed seed) on the mesh surface, shape ``(count, 3)``."""
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points, dtype=np.float64)
