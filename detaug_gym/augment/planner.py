"""A sampling planner for end-effector detours (DemoGen mode): RRT-Connect, shortcutting, smoothing, retiming.

The planner works in grip-site *position* space. Orientation is not planned: along a detour it is slerped
between the transit's endpoint orientations by progress, so while searching, a position counts as free
only if the robot proxy is free there in *both* endpoint orientations (conservative); the final retimed
path is checked again with its real per-frame orientations.

Collision checks use python-fcl: a :class:`ProxyWorld` holds the obstacle (a triangle mesh, world frame),
the table (a half-space approximated by a large box) and the robot proxy (boxes / spheres / a mesh rigidly
attached to the grip site: hand, wrist, held object). Everything here is plain numpy + fcl, no simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import fcl
import numpy as np
import trimesh


@dataclass(frozen=True)
class PlannerConfig:
    """RRT-Connect and post-processing settings.

    Attributes:
        step: longest tree extension (m).
        resolution: spacing of the collision checks along an edge (m).
        max_iters: RRT-Connect iterations before giving up.
        margin_xy: how far (m) the sampling box extends beyond the endpoints in x and y.
        margin_up: how far (m) above the higher endpoint samples may go.
        shortcut_iters: random shortcut attempts.
        smooth_iters: rounds of corner cutting (each re-checked; a colliding round is undone).
    """

    step: float = 0.03
    resolution: float = 0.005
    max_iters: int = 2000
    margin_xy: float = 0.2
    margin_up: float = 0.2
    shortcut_iters: int = 100
    smooth_iters: int = 3


def fcl_mesh(mesh: trimesh.Trimesh) -> fcl.BVHModel:
    bvh = fcl.BVHModel()
    bvh.beginModel(len(mesh.vertices), len(mesh.faces))
    bvh.addSubModel(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32))
    bvh.endModel()
    return bvh


@dataclass
class ProxyPart:
    """One rigid part of the robot proxy: an fcl geometry at ``local`` (4x4) in the grip-site frame, and the
    points (local frame) that bound it from below (for the table's height)."""

    geometry: object
    local: np.ndarray
    corners: np.ndarray


def box_part(lo: np.ndarray, hi: np.ndarray) -> ProxyPart:
    """An axis-aligned box ``[lo, hi]`` of the grip-site frame."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    local = np.eye(4)
    local[:3, 3] = 0.5 * (lo + hi)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return ProxyPart(fcl.Box(*(hi - lo)), local, corners)


def sphere_part(centre: np.ndarray, radius: float) -> ProxyPart:
    local = np.eye(4)
    local[:3, 3] = centre
    corners = np.asarray(centre, float)[None] + radius * np.vstack([np.eye(3), -np.eye(3)])
    return ProxyPart(fcl.Sphere(float(radius)), local, corners)


def mesh_part(mesh: trimesh.Trimesh, local: np.ndarray) -> ProxyPart:
    """A mesh whose vertices are given in its own frame, placed at ``local`` in the grip-site frame."""
    corners = np.asarray(mesh.vertices) @ local[:3, :3].T + local[:3, 3]
    return ProxyPart(fcl_mesh(mesh), np.asarray(local, float), corners)


class ProxyWorld:
    """The robot proxy against an obstacle mesh and the table top (everything below ``table_top``)."""

    def __init__(self, obstacle: trimesh.Trimesh, table_top: float, parts: list[ProxyPart],
                 extra: list[trimesh.Trimesh] = ()) -> None:
        self.table_top = float(table_top)
        self.parts = parts
        self._objects = [fcl.CollisionObject(p.geometry, fcl.Transform()) for p in parts]
        self._obstacles = [fcl.CollisionObject(fcl_mesh(m), fcl.Transform()) for m in (obstacle, *extra)]
        depth = 1.0
        self._table = fcl.CollisionObject(fcl.Box(20.0, 20.0, depth),
                                          fcl.Transform(np.array([0.0, 0.0, table_top - depth / 2])))
        self._request = fcl.CollisionRequest()

    def lowest_point(self, pos: np.ndarray, rot: np.ndarray) -> float:
        """Lowest z of the proxy's bounding points at a grip-site pose."""
        return min(float(np.min((p.corners @ rot.T + pos)[:, 2])) for p in self.parts)

    def collides(self, pos: np.ndarray, rot: np.ndarray, with_table: bool = True) -> bool:
        """True if any proxy part at grip-site pose (pos, rot) touches the obstacle (or the table)."""
        for part, obj in zip(self.parts, self._objects):
            world_rot = rot @ part.local[:3, :3]
            obj.setTransform(fcl.Transform(world_rot, pos + rot @ part.local[:3, 3]))
            targets = self._obstacles + ([self._table] if with_table else [])
            for other in targets:
                if fcl.collide(obj, other, self._request, fcl.CollisionResult()):
                    return True
        return False

    def free_in_all(self, rots: list[np.ndarray]):
        """``is_free(p)``: the proxy at ``p`` is free in every orientation of ``rots``."""
        return lambda p: not any(self.collides(p, r) for r in rots)


# ---------------------------------------------------------------------------------------------- RRT-Connect
def edge_free(a: np.ndarray, b: np.ndarray, is_free, resolution: float) -> bool:
    """Every point of the segment a-b at ``resolution`` spacing (end included, start excluded) is free."""
    n = max(1, int(np.ceil(np.linalg.norm(b - a) / resolution)))
    return all(is_free(a + (b - a) * (k / n)) for k in range(1, n + 1))


class _Tree:
    def __init__(self, root: np.ndarray) -> None:
        self.points = [np.asarray(root, float)]
        self.parent = [-1]

    def nearest(self, p: np.ndarray) -> int:
        return int(np.argmin(np.linalg.norm(np.asarray(self.points) - p, axis=1)))

    def add(self, p: np.ndarray, parent: int) -> int:
        self.points.append(p)
        self.parent.append(parent)
        return len(self.points) - 1

    def path_to_root(self, i: int) -> list[np.ndarray]:
        out = []
        while i >= 0:
            out.append(self.points[i])
            i = self.parent[i]
        return out


def _extend(tree: _Tree, target: np.ndarray, is_free, config: PlannerConfig) -> tuple[str, int]:
    """One step from the nearest node towards ``target``: ("reached" | "advanced" | "trapped", node)."""
    i = tree.nearest(target)
    p = tree.points[i]
    d = target - p
    dist = float(np.linalg.norm(d))
    new = target if dist <= config.step else p + d * (config.step / dist)
    if not edge_free(p, new, is_free, config.resolution):
        return "trapped", i
    j = tree.add(new, i)
    return ("reached" if dist <= config.step else "advanced"), j


def _connect(tree: _Tree, target: np.ndarray, is_free, config: PlannerConfig) -> tuple[str, int]:
    while True:
        status, j = _extend(tree, target, is_free, config)
        if status != "advanced":
            return status, j


def rrt_connect(start: np.ndarray, goal: np.ndarray, is_free, lo: np.ndarray, hi: np.ndarray,
                rng: np.random.Generator, config: PlannerConfig = PlannerConfig()) -> list[np.ndarray] | None:
    """A collision-free polyline from ``start`` to ``goal`` (both included) or None.

    Two trees grow towards uniform samples of the box ``[lo, hi]`` in turn; after each extension the other
    tree tries to connect greedily to the new node (Kuffner & LaValle's RRT-Connect).
    """
    start, goal = np.asarray(start, float), np.asarray(goal, float)
    if edge_free(start, goal, is_free, config.resolution):
        return [start, goal]
    a, b = _Tree(start), _Tree(goal)
    for _ in range(config.max_iters):
        sample = rng.uniform(lo, hi)
        status, i = _extend(a, sample, is_free, config)
        if status != "trapped":
            status_b, j = _connect(b, a.points[i], is_free, config)
            if status_b == "reached":
                half_a, half_b = a.path_to_root(i)[::-1], b.path_to_root(j)[1:]
                path = half_a + half_b
                return path if np.allclose(path[0], start) else path[::-1]
        a, b = b, a
    return None


def shortcut(path: list[np.ndarray], is_free, rng: np.random.Generator, config: PlannerConfig) -> list[np.ndarray]:
    """Random shortcutting: replace the stretch between two random vertices by a straight edge when free."""
    path = [np.asarray(p, float) for p in path]
    for _ in range(config.shortcut_iters):
        if len(path) < 3:
            break
        i, j = sorted(rng.choice(len(path), 2, replace=False))
        if j - i < 2:
            continue
        if edge_free(path[i], path[j], is_free, config.resolution):
            path = path[:i + 1] + path[j:]
    return path


def smooth(path: list[np.ndarray], is_free, config: PlannerConfig) -> list[np.ndarray]:
    """Chaikin corner cutting (endpoints kept), each round kept only if every new edge is free."""
    for _ in range(config.smooth_iters):
        if len(path) < 3:
            break
        new = [path[0]]
        last = len(path) - 2
        for k, (a, b) in enumerate(zip(path[:-1], path[1:])):
            if k > 0:
                new.append(0.75 * a + 0.25 * b)
            if k < last:
                new.append(0.25 * a + 0.75 * b)
        new.append(path[-1])
        if all(edge_free(p, q, is_free, config.resolution) for p, q in zip(new[:-1], new[1:])):
            path = new
        else:
            break
    return path


def polyline_length(path) -> float:
    return float(np.linalg.norm(np.diff(np.asarray(path), axis=0), axis=1).sum())


def resample(path, progress: np.ndarray) -> np.ndarray:
    """Points at fractions ``progress`` (in [0, 1]) of the polyline's arc length, ``(len(progress), 3)``."""
    path = np.asarray(path, float)
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.clip(progress, 0.0, 1.0) * cum[-1]
    return np.stack([np.interp(s, cum, path[:, k]) for k in range(3)], axis=1)


def sampling_box(start: np.ndarray, goal: np.ndarray, floor: float,
                 config: PlannerConfig) -> tuple[np.ndarray, np.ndarray]:
    """The box RRT samples from: the endpoints' box widened by ``margin_xy`` and raised by ``margin_up``."""
    lo = np.minimum(start, goal) - np.array([config.margin_xy, config.margin_xy, 0.0])
    hi = np.maximum(start, goal) + np.array([config.margin_xy, config.margin_xy, config.margin_up])
    lo[2] = floor
    return lo, hi
