"""DemoGen's train-time obstacle shapes: SafeLIBERO's six obstacle meshes (read from a SafeLIBERO scene and
cached on disk) and random boxes / cylinders, each in its own upright frame with 256 surface samples (the
env's ``obstacle_points`` convention).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import trimesh

from detaug_gym.envs.suites import SuiteSpec, get_suite

SAFELIBERO_TYPES = ("moka_pot", "white_storage_box", "milk", "wine_bottle", "red_coffee_mug", "yellow_book")
PRIMITIVES = ("box", "cylinder")
N_POINTS = 256
SHAPE_FALLBACK_SUITE = "spatial"  # whose SafeLIBERO meshes a suite without its own set (Newton) borrows


@dataclass(frozen=True)
class ObstacleShape:
    """An obstacle in its own frame: upright, footprint centred on the origin, lowest point at z = 0."""

    kind: str
    mesh: trimesh.Trimesh
    points: np.ndarray  # (N_POINTS, 3) surface samples

    def placed(self, xy: np.ndarray, yaw: float, support_z: float) -> tuple[trimesh.Trimesh, np.ndarray, np.ndarray]:
        """(world mesh, world points (N, 3), 4x4 pose) standing on ``support_z`` at ``xy``, turned by ``yaw``."""
        pose = np.eye(4)
        c, s = np.cos(yaw), np.sin(yaw)
        pose[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        pose[:3, 3] = [xy[0], xy[1], support_z]
        mesh = self.mesh.copy()
        mesh.apply_transform(pose)
        return mesh, self.points @ pose[:3, :3].T + pose[:3, 3], pose


def _standardise(kind: str, mesh: trimesh.Trimesh, points: np.ndarray) -> ObstacleShape:
    lo, hi = mesh.bounds
    shift = -np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    mesh = mesh.copy()
    mesh.apply_translation(shift)
    return ObstacleShape(kind, mesh, np.asarray(points, float) + shift)


def primitive_shape(kind: str, rng: np.random.Generator, half_width: tuple[float, float],
                    half_height: tuple[float, float]) -> ObstacleShape:
    """A random box (half-widths drawn independently) or upright cylinder (radius) of the given size ranges (m)."""
    hz = rng.uniform(*half_height)
    if kind == "box":
        hx, hy = rng.uniform(*half_width, size=2)
        mesh = trimesh.creation.box(extents=2 * np.array([hx, hy, hz]))
    else:
        mesh = trimesh.creation.cylinder(radius=rng.uniform(*half_width), height=2 * hz, sections=24)
    points, _ = trimesh.sample.sample_surface(mesh, N_POINTS, seed=int(rng.integers(2 ** 31)))
    return _standardise(kind, mesh, points)


def cache_dir() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(root) / "detaug_gym"


_SAFELIBERO: dict[str, dict[str, ObstacleShape]] = {}


def safelibero_shapes(suite: SuiteSpec) -> dict[str, ObstacleShape]:
    """SafeLIBERO's six obstacles as the env of the suite's ``shape_source_level`` compiles them (collision
    mesh, upright; the same 256 surface samples the env puts in ``obstacle_points``). A suite without that
    level (Newton) uses the meshes of :data:`SHAPE_FALLBACK_SUITE` (Spatial). Built once (~5 s), then cached
    on disk."""
    if suite.shape_source_level is None:
        suite = get_suite(SHAPE_FALLBACK_SUITE)
    if suite.name in _SAFELIBERO:
        return _SAFELIBERO[suite.name]
    path = cache_dir() / f"demogen_obstacles_{suite.name}_mj{mujoco.__version__}.npz"
    if not path.exists():
        _build_shape_cache(suite, path)
    data = np.load(path)
    shapes = {k: ObstacleShape(k, trimesh.Trimesh(data[f"{k}_v"], data[f"{k}_f"], process=False), data[f"{k}_p"])
              for k in SAFELIBERO_TYPES}
    _SAFELIBERO[suite.name] = shapes
    return shapes


def _build_shape_cache(suite: SuiteSpec, path: Path) -> None:
    import gymnasium as gym

    import detaug_gym  # noqa: F401
    from detaug_gym.geometry.meshes import geom_pose_in_body, geom_trimesh

    # Scenario version 0's six types at LIBERO's scale: the shapes the zoo's DemoGen checkpoints were built with
    # (version 1 adds SafeLIBERO's enlarged models; a DemoGen trained on those is a new zoo recipe, not this one).
    env = gym.make(suite.env_id(suite.shape_source_level, version=0))
    try:
        scene = env.unwrapped.scene_for(0)
        arrays = {}
        for kind, h in scene.obstacles.items():
            parts = []  # the handle's own geom list: parked obstacles have their contacts switched off
            for g in h.geom_ids:
                part = geom_trimesh(scene.model, int(g))
                part.apply_transform(geom_pose_in_body(scene.model, int(g)))
                parts.append(part)
            mesh = trimesh.util.concatenate(parts)
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, h.upright_quat)
            rot = rot.reshape(3, 3)
            upright = trimesh.Trimesh(mesh.vertices @ rot.T, mesh.faces, process=False)
            shape = _standardise(kind, upright, h.local_points @ rot.T)
            arrays.update({f"{kind}_v": shape.mesh.vertices, f"{kind}_f": shape.mesh.faces, f"{kind}_p": shape.points})
    finally:
        env.close()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **arrays)
    tmp.replace(path)


def sample_shape(rng: np.random.Generator, suite: SuiteSpec, shapes: str, half_width: tuple[float, float],
                 half_height: tuple[float, float]) -> ObstacleShape:
    """One obstacle shape: of SafeLIBERO's six (``shapes="safelibero"``), a primitive (``"primitives"``) or either,
    half each (``"all"``); primitives take their size from ``half_width`` / ``half_height`` (m)."""
    use_safelibero = shapes == "safelibero" or (shapes == "all" and rng.random() < 0.5)
    if use_safelibero:
        return safelibero_shapes(suite)[SAFELIBERO_TYPES[int(rng.integers(len(SAFELIBERO_TYPES)))]]
    return primitive_shape(PRIMITIVES[int(rng.integers(2))], rng, half_width, half_height)
