"""DemoGen mode: train-time obstacles on the free-space demos, with planned detours around them.

Per source demo and per requested copy, up to ``tries`` samples are drawn:

1. an obstacle shape: one of SafeLIBERO's six types (their collision meshes, from a SafeLIBERO L1 scene of
   the same suite, cached on disk) or a random box / cylinder (half-width 0.015-0.06 m, half-height
   0.02-0.11 m), with a random yaw;
2. a placement on the support under a random point of a random transit's path (20-80% of its length,
   up to 2 cm sideways), kept only where the obstacle's footprint clears every scene object by 1 cm, the
   robot proxy (hand + wrist + held object, :mod:`~detaug_gym.augment.planner`) moving along the
   original transit *intersects* it, and the unchanged frames (interaction windows, margins) are clear
   of it (``placement_tries`` placements per sample, else ``no_placement``);
3. for every transit the obstacle blocks, a detour from RRT-Connect in grip-site position space, then
   shortcutting, corner cutting and retiming (the source's mean speed, capped at ``max_speed``, smooth
   trapezoid progress; orientation slerped with the same progress), re-checked frame by frame;
4. the DetAug pipeline: IK, joint limits / speed / acceleration and MuJoCo contacts with the scene
   (``SourceContext.check_span``), then the closed-loop replay in the (obstacle-free) env, kept if it
   succeeds, tracks the detour and the held object does not slip; finally the recorded robot (surface
   points by FK) and held object must stay out of the obstacle's convex hull (``replay_collision``).

The obstacle exists only in the data: the recorded demo carries its 256 world-frame surface points
(``obstacle_points``, the env's convention) and the originals none (an empty cloud: mask 0 in training).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
import trimesh

from detaug_gym.augment.arcs import arc_steps, peak_factor, smooth_trapezoid
from detaug_gym.augment.context import SourceContext, reset_to_demo
from detaug_gym.augment.detaug import SourceResult, StageConfigs, suite_of
from detaug_gym.augment.plan import ArcSample, Plan, Replacement, Timing, splice_transits
from detaug_gym.augment.planner import (
    PlannerConfig,
    ProxyWorld,
    box_part,
    mesh_part,
    polyline_length,
    resample,
    rrt_connect,
    sampling_box,
    shortcut,
    smooth,
    sphere_part,
)
from detaug_gym.augment.replay import ReplayConfig, length_limit, run_plan, tail_steps
from detaug_gym.augment.segment import Transit
from detaug_gym.envs.suites import get_suite
from detaug_gym.rotations import quat_xyzw_to_mat, slerp

__all__ = ["DemoGenConfig", "ObstacleShape", "augment_source", "label_size", "suite_of"]

SAFELIBERO_TYPES = ("moka_pot", "white_storage_box", "milk", "wine_bottle", "red_coffee_mug", "yellow_book")
PRIMITIVES = ("box", "cylinder")
N_POINTS = 256


def label_size(env_id: str) -> int:
    """DemoGen demos carry no label (the obstacle cloud is their conditioning)."""
    return 0


@dataclass(frozen=True)
class DemoGenConfig(StageConfigs):
    """Everything that shapes DemoGen samples; stored with every augmented demo.

    Attributes:
        shapes: ``"all"`` (SafeLIBERO types and primitives, half each), ``"safelibero"`` or ``"primitives"``.
        half_width, half_height: primitive size ranges (m).
        lateral: largest sideways offset of the obstacle from the path (m).
        path_fraction: where along the transit (fraction of its length) the obstacle stands.
        scene_gap: clearance of the obstacle's footprint to every scene object (m).
        proxy_margin: inflation of the hand / wrist proxy (m): the detour's clearance.
        placement_tries: placements tried per sample (``tries``, samples per copy, is in :class:`StageConfigs`).
        replay_tolerance: depth (m) a recorded robot / object point may reach inside the obstacle's hull.
    """

    shapes: str = "all"
    half_width: tuple[float, float] = (0.015, 0.06)
    half_height: tuple[float, float] = (0.02, 0.11)
    lateral: float = 0.02
    path_fraction: tuple[float, float] = (0.2, 0.8)
    scene_gap: float = 0.01
    proxy_margin: float = 0.01
    placement_tries: int = 60
    replay_tolerance: float = 0.005
    planner: PlannerConfig = field(default_factory=PlannerConfig)


# ---------------------------------------------------------------------------------------------- obstacles
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


def primitive_shape(kind: str, rng: np.random.Generator, config: DemoGenConfig) -> ObstacleShape:
    """A random box (half-widths drawn independently) or upright cylinder of the configured size ranges."""
    hz = rng.uniform(*config.half_height)
    if kind == "box":
        hx, hy = rng.uniform(*config.half_width, size=2)
        mesh = trimesh.creation.box(extents=2 * np.array([hx, hy, hz]))
    else:
        mesh = trimesh.creation.cylinder(radius=rng.uniform(*config.half_width), height=2 * hz, sections=24)
    points, _ = trimesh.sample.sample_surface(mesh, N_POINTS, seed=int(rng.integers(2 ** 31)))
    return _standardise(kind, mesh, points)


def cache_dir() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(root) / "detaug_gym"


_SAFELIBERO: dict[str, dict[str, ObstacleShape]] = {}


def safelibero_shapes(suite: str) -> dict[str, ObstacleShape]:
    """SafeLIBERO's six obstacles as the suite's L1 env compiles them (collision mesh, upright; the same
    256 surface samples the env puts in ``obstacle_points``). Built once (~5 s), then cached on disk."""
    suite = suite if suite in ("spatial", "object", "goal", "long") else "spatial"
    if suite in _SAFELIBERO:
        return _SAFELIBERO[suite]
    path = cache_dir() / f"demogen_obstacles_{suite}_mj{mujoco.__version__}.npz"
    if not path.exists():
        _build_shape_cache(suite, path)
    data = np.load(path)
    shapes = {k: ObstacleShape(k, trimesh.Trimesh(data[f"{k}_v"], data[f"{k}_f"], process=False), data[f"{k}_p"])
              for k in SAFELIBERO_TYPES}
    _SAFELIBERO[suite] = shapes
    return shapes


def _build_shape_cache(suite: str, path: Path) -> None:
    import gymnasium as gym

    import detaug_gym  # noqa: F401
    from detaug_gym.geometry.meshes import geom_pose_in_body, geom_trimesh

    spec = get_suite(suite)
    if spec.shape_source_level is None:
        raise ValueError(f"suite {suite!r} has no scene with SafeLIBERO's obstacle set; use --shapes primitives")
    env = gym.make(spec.env_id(spec.shape_source_level))
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


def sample_shape(rng: np.random.Generator, config: DemoGenConfig, suite: str) -> ObstacleShape:
    use_safelibero = config.shapes == "safelibero" or (config.shapes == "all" and rng.random() < 0.5)
    if use_safelibero:
        return safelibero_shapes(suite)[SAFELIBERO_TYPES[int(rng.integers(len(SAFELIBERO_TYPES)))]]
    return primitive_shape(PRIMITIVES[int(rng.integers(2))], rng, config)


# ---------------------------------------------------------------------------------------------- robot proxy
def hand_proxy(ctx: SourceContext, margin: float) -> list:
    """Hand + fingers (the box of their collision geoms in the grip-site frame, fingers as in the first
    frame: open) and a sphere around the wrist (link 7), inflated by ``margin``."""
    from detaug_gym.geometry.meshes import geom_trimesh

    model, data, scene = ctx.scene.model, ctx.ik.data, ctx.scene
    ctx.ik.load(ctx.qpos[0])
    site_p, site_r = data.site_xpos[scene.eef_site].copy(), data.site_xmat[scene.eef_site].reshape(3, 3).copy()
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or "" for b in range(model.nbody)]
    corners = []
    for g in scene.robot_geom_ids:
        if not names[model.geom_bodyid[g]].startswith("gripper0_"):
            continue
        vertices = geom_trimesh(model, int(g)).vertices
        corners.append(vertices @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g])
    local = (np.vstack(corners) - site_p) @ site_r
    link7 = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "robot0_link7")
    wrist = (data.xpos[link7] - site_p) @ site_r
    return [box_part(local.min(0) - margin, local.max(0) + margin), sphere_part(wrist, 0.06 + margin)]


def held_part(ctx: SourceContext, transit_index: int):
    held = ctx.held.get(transit_index)
    if held is None:
        return None
    from detaug_gym.geometry.meshes import body_collision_mesh

    mesh = body_collision_mesh(ctx.scene.model, held.body, include_children=True)
    local = np.eye(4)
    local[:3, :3], local[:3, 3] = held.offset_rot, held.offset_pos
    return mesh_part(mesh, local)


# ---------------------------------------------------------------------------------------------- one source
@dataclass
class DemoGenSource:
    """Per-source state shared by all its samples: the context, proxies, footprints and the table height."""

    ctx: SourceContext
    hand: list
    held: dict[int, object]
    footprints: list
    rots: np.ndarray  # (T, 3, 3) grip-site rotations of the source
    carrying: np.ndarray  # (T,) frame lies between a grasp's close and its release
    suite: str

    @classmethod
    def build(cls, env, demo, config: DemoGenConfig, suite: str) -> DemoGenSource:
        ctx = SourceContext.build(env, demo, config.segment, config.ik, config.feasibility.penetration)
        problem = env.unwrapped.placement_problem(np.random.default_rng(0))
        footprints = [problem.pick, problem.place, *problem.others]
        held = {i: held_part(ctx, i) for i in range(len(ctx.segmentation.transits))}
        carrying = np.zeros(len(ctx.pos), dtype=bool)
        for g in ctx.segmentation.grasps:
            carrying[g.close:(g.release if g.release is not None else len(carrying))] = True
        rots = np.stack([quat_xyzw_to_mat(q) for q in ctx.quat])
        return cls(ctx, hand_proxy(ctx, config.proxy_margin), held, footprints, rots, carrying, suite)

    def parts(self, transit_index: int | None) -> list:
        part = self.held.get(transit_index) if transit_index is not None else None
        return self.hand + ([part] if part is not None else [])

    def carry_part(self):
        return next((p for p in self.held.values() if p is not None), None)


@dataclass
class Placement:
    shape: ObstacleShape
    mesh: trimesh.Trimesh
    points: np.ndarray
    pose: np.ndarray
    blocked: list[int]  # transit indices whose original path hits the obstacle
    table_top: float


def footprint_clear(mesh: trimesh.Trimesh, footprints, gap: float) -> bool:
    lo, hi = mesh.bounds[0][:2] - gap, mesh.bounds[1][:2] + gap
    return all(np.any(hi < f.lo) or np.any(lo > f.hi) for f in footprints)


def path_hits(src: DemoGenSource, mesh: trimesh.Trimesh, table_top: float, frames: np.ndarray,
              transit_index: int | None) -> bool:
    """The proxy (with the held object on carrying frames) touches the obstacle at any of ``frames``."""
    hand = ProxyWorld(mesh, table_top, src.parts(None))
    carry_parts = src.parts(transit_index) if transit_index is not None else src.hand + (
        [src.carry_part()] if src.carry_part() is not None else [])
    carry = ProxyWorld(mesh, table_top, carry_parts)
    for t in frames:
        world = carry if src.carrying[t] else hand
        if world.collides(src.ctx.pos[t], src.rots[t], with_table=False):
            return True
    return False


def sample_placement(src: DemoGenSource, rng: np.random.Generator, config: DemoGenConfig) -> Placement | None:
    """An obstacle that blocks at least one transit and leaves the scene objects and unchanged frames clear."""
    ctx = src.ctx
    transits = [i for i, ok in ctx.bendable.items() if ok]
    for _ in range(config.placement_tries):
        shape = sample_shape(rng, config, src.suite)
        i = transits[int(rng.integers(len(transits)))]
        tr = ctx.segmentation.transits[i]
        path = ctx.pos[tr.start:tr.end + 1]
        point = resample(path, np.array([rng.uniform(*config.path_fraction)]))[0]
        xy = point[:2] + rng.uniform(-config.lateral, config.lateral, size=2)
        support = ctx.scene.support_height(xy)
        mesh, points, pose = shape.placed(xy, rng.uniform(0.0, 2 * np.pi), support)
        if not footprint_clear(mesh, src.footprints, config.scene_gap):
            continue
        blocked = [j for j in transits
                   if path_hits(src, mesh, support, np.arange(ctx.segmentation.transits[j].start + 1,
                                                              ctx.segmentation.transits[j].end), j)]
        if i not in blocked:
            continue
        changed = np.zeros(len(ctx.pos), dtype=bool)
        for j in blocked:
            changed[ctx.segmentation.transits[j].start + 1:ctx.segmentation.transits[j].end] = True
        if path_hits(src, mesh, support, np.flatnonzero(~changed), None):
            continue
        return Placement(shape, mesh, points, pose, blocked, support)
    return None


@dataclass
class Detour:
    transit: Transit
    pos: np.ndarray  # (n + 1, 3) targets, rows 0 and n the source's endpoints
    quat: np.ndarray  # (n + 1, 4) xyzw
    length: float
    raw_nodes: int


def plan_detour(src: DemoGenSource, place: Placement, i: int, rng: np.random.Generator,
                config: DemoGenConfig) -> Detour | str:
    """RRT-Connect + shortcut + smoothing + retiming for transit ``i``; a rejection reason on failure."""
    ctx = src.ctx
    tr = ctx.segmentation.transits[i]
    parts = src.parts(i) if tr.kind == "carry" else src.hand
    start, goal = ctx.pos[tr.start], ctx.pos[tr.end]
    r0, r1 = src.rots[tr.start], src.rots[tr.end]
    probe = ProxyWorld(place.mesh, place.table_top, parts)
    table_top = min(place.table_top, probe.lowest_point(start, r0), probe.lowest_point(goal, r1)) - 0.005
    world = ProxyWorld(place.mesh, table_top, parts)
    is_free = world.free_in_all([r0, r1])
    if not (is_free(start) and is_free(goal)):
        return "endpoint_blocked"
    lo, hi = sampling_box(start, goal, table_top, config.planner)
    raw = rrt_connect(start, goal, is_free, lo, hi, rng, config.planner)
    if raw is None:
        return "planner_failed"
    path = smooth(shortcut(raw, is_free, rng, config.planner), is_free, config.planner)
    length = polyline_length(path)
    timing = config.timing
    n = arc_steps(tr.steps, polyline_length(ctx.pos[tr.start:tr.end + 1]), length, timing.max_speed,
                  peak_factor(timing.profile, timing.ramp))
    progress = smooth_trapezoid(np.linspace(0.0, 1.0, n + 1), timing.ramp)
    pos = resample(path, progress)
    quat = slerp(ctx.quat[tr.start], ctx.quat[tr.end], progress)
    pos[0], pos[-1], quat[0], quat[-1] = start, goal, ctx.quat[tr.start], ctx.quat[tr.end]
    if any(world.collides(p, quat_xyzw_to_mat(q)) for p, q in zip(pos, quat)):
        return "detour_collision"
    return Detour(tr, pos, quat, length, len(raw))


def build_detour_plan(ctx: SourceContext, detours: list[Detour]) -> Plan:
    """The new timeline: the source's frames, with each detoured transit replaced by its targets."""
    replacements = [Replacement(ArcSample(d.transit, 0.0, 0.0), d.pos, d.quat, d.length,
                                float(np.linalg.norm(d.pos[-1] - d.pos[0]))) for d in detours]
    return splice_transits(ctx.pos, ctx.quat, ctx.demo.gripper_command, replacements)


# ---------------------------------------------------------------------------------------------- checks
_ROBOT_GEOMETRY: dict[int, object] = {}


def replay_penetration(ctx: SourceContext, states: np.ndarray, mesh: trimesh.Trimesh,
                       held_bodies: list[int]) -> float:
    """Deepest (m) any recorded robot surface point (FK) or held-object surface point reaches into the
    obstacle's convex hull over ``states`` (T, 1 + nq + nv); 0 when none is inside."""
    import torch

    from detaug_gym.geometry.meshes import body_collision_mesh, sample_surface
    from detaug_gym.geometry.robot_points import RobotGeometry

    scene = ctx.scene
    model = scene.model
    key = id(model)
    if key not in _ROBOT_GEOMETRY:
        _ROBOT_GEOMETRY[key] = RobotGeometry.from_model(model, num_points=600)
    geometry = _ROBOT_GEOMETRY[key]
    qpos = np.asarray(states, np.float64)[:, 1:1 + model.nq]
    with torch.no_grad():
        robot = geometry.surface_points(torch.as_tensor(qpos[:, scene.arm_qpos]),
                                        torch.as_tensor(qpos[:, scene.gripper_qpos])).numpy().reshape(-1, 3)
    clouds = [robot]
    for body in held_bodies:
        adr = int(model.jnt_qposadr[model.body_jntadr[body]])
        local = sample_surface(body_collision_mesh(model, body, include_children=True), 200)
        for q in qpos:
            rot = np.zeros(9)
            mujoco.mju_quat2Mat(rot, q[adr + 3:adr + 7])
            clouds.append(local @ rot.reshape(3, 3).T + q[adr:adr + 3])
    points = np.vstack(clouds)
    hull = place_hull(mesh)
    offsets = np.einsum("ij,ij->i", hull.face_normals, hull.triangles[:, 0])
    inside = (points @ hull.face_normals.T - offsets).max(axis=1)
    return float(max(0.0, -inside.min()))


def place_hull(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    return mesh.convex_hull


def try_sample(src: DemoGenSource, rng: np.random.Generator, config: DemoGenConfig, max_length: int):
    """One obstacle + detours + checks + replay: ``(placement, detours, plan, recording, reason)``."""
    ctx = src.ctx
    place = sample_placement(src, rng, config)
    if place is None:
        return None, None, None, None, "no_placement"
    detours = []
    for i in place.blocked:
        d = plan_detour(src, place, i, rng, config)
        if isinstance(d, str):
            return place, None, None, None, d
        detours.append(d)
    plan = build_detour_plan(ctx, detours)
    if plan.n_steps > max_length:
        return place, detours, plan, None, "too_long"
    for k in range(len(plan.spans)):
        reason = ctx.check_span(plan, k, config.feasibility)
        if reason is not None:
            return place, detours, plan, None, reason
    obs = reset_to_demo(ctx.env, ctx.demo)
    held = {k: ctx.held[ctx.transit_index(s.sample.transit)] for k, s in enumerate(plan.spans)}
    held_body = {k: h.body for k, h in held.items() if h is not None}
    rec = run_plan(ctx.env, obs, plan, ctx.demo.actions, config.replay, held_body, tail=tail_steps(ctx.demo))
    if not config.validate:
        return place, detours, plan, rec, None
    reason = ctx.replay_reason(plan, rec, config.replay)
    if reason is not None:
        return place, detours, plan, rec, reason
    carried = sorted({h.body for h in ctx.held.values() if h is not None})
    if replay_penetration(ctx, np.asarray(rec.states), place.mesh, carried) > config.replay_tolerance:
        return place, detours, plan, rec, "replay_collision"
    return place, detours, plan, rec, None


def augment_source(env, demo, copies: int, rng: np.random.Generator, config: DemoGenConfig,
                   label_len: int) -> SourceResult:
    """Up to ``copies`` accepted DemoGen copies of ``demo`` (see the module docstring)."""
    start = time.perf_counter()
    result = SourceResult()
    suite = suite_of(str(demo.attrs.get("env_id", "SafeLibero-Spatial-Free-v0")))
    src = DemoGenSource.build(env, demo, config, suite)
    max_length = length_limit(env, demo, config.max_length)
    if not src.ctx.segmentation.grasps or not any(src.ctx.bendable.values()):
        result.reasons["no_transit"] += 1
        result.seconds = time.perf_counter() - start
        return result
    for _ in range(copies):
        for _ in range(config.tries):
            result.tries += 1
            place, detours, plan, rec, reason = try_sample(src, rng, config, max_length)
            if reason is not None:
                result.reasons[reason] += 1
                continue
            result.demos.append(augmented_demo(demo, place, detours, plan, rec, config, label_len))
            break
    result.seconds = time.perf_counter() - start
    return result


def augmented_demo(source, place: Placement, detours: list[Detour], plan: Plan, rec, config: DemoGenConfig,
                   label_len: int):
    """A :class:`~detaug_gym.data.Demo` of the replay, with the obstacle's cloud and the provenance."""
    from detaug_gym.augment.detaug import _jsonable
    from detaug_gym.data import Demo

    actions = np.asarray(rec.actions, dtype=np.float32)
    rewards = np.zeros(len(actions), dtype=np.float32)
    rewards[-1] = float(rec.success)
    transits = [{"kind": s.sample.transit.kind, "grasp": s.sample.transit.grasp,
                 "source_start": s.sample.transit.start, "source_end": s.sample.transit.end,
                 "start": s.start, "end": s.end, "path_length": s.arc_len, "chord": s.chord,
                 "rrt_nodes": d.raw_nodes} for s, d in zip(plan.spans, sorted(detours, key=lambda d: d.transit.start))]
    attrs = {k: v for k, v in source.attrs.items() if k != "num_samples"}
    attrs.update({
        "source_demo": source.name, "augmented": True, "augment_mode": "demogen",
        "obstacle_kind": place.shape.kind,
        "obstacle_pose": place.pose[:3, 3].tolist() + [float(np.arctan2(place.pose[1, 0], place.pose[0, 0]))],
        "obstacle_size": (0.5 * (place.mesh.bounds[1] - place.mesh.bounds[0])).tolist(),
        "transits": transits, "max_deviation": rec.max_deviation, "max_offset_drift": rec.max_offset_drift,
        "augment_params": _jsonable(config.as_dict()),
    })
    return Demo(actions=actions, states=np.asarray(rec.states), obs=rec.stacked_obs(),
                gripper_command=actions[:, -1].copy(), attrs=attrs, label=np.zeros(label_len, np.float32),
                rewards=rewards, dones=rewards.copy(), obstacle_points=place.points.astype(np.float32))


# ---------------------------------------------------------------------------------------------- CLI hooks
def add_arguments(parser) -> None:
    """DemoGen's options of ``python -m detaug_gym.augment --mode demogen``."""
    g = parser.add_argument_group("demogen")
    g.add_argument("--shapes", choices=("all", "safelibero", "primitives"), default="all",
                   help="obstacle shapes: SafeLIBERO's six and random boxes/cylinders (all, default)")
    g.add_argument("--tries", type=int, default=4, help="samples per requested copy (default 4)")
    g.add_argument("--placement-tries", type=int, default=60, help="obstacle placements per sample (60)")
    g.add_argument("--clearance", type=float, default=0.01, help="hand proxy inflation, m (default 0.01)")
    g.add_argument("--rrt-iters", type=int, default=2000, help="RRT-Connect iterations (default 2000)")
    g.add_argument("--max-length", type=int, default=None, help="longest demo in steps (default: env limit)")
    g.add_argument("--max-speed", type=float, default=0.012, help="planned peak eef speed, m/step (0.012)")
    g.add_argument("--tolerance", type=float, default=0.015, help="max eef distance from the detour on replay (m)")
    g.add_argument("--grasp-tolerance", type=float, default=0.008,
                   help="max shift (m) of a held object in the hand at the start of its carry, against the source")
    g.add_argument("--no-validate", action="store_true", help="keep samples whose replay fails (not recommended)")


def make_config(ns) -> DemoGenConfig:
    """The :class:`DemoGenConfig` of parsed command-line options."""
    if ns.tries < 1 or ns.placement_tries < 1:
        raise SystemExit("error: --tries and --placement-tries must be >= 1")
    return DemoGenConfig(shapes=ns.shapes, tries=ns.tries, placement_tries=ns.placement_tries,
                         proxy_margin=ns.clearance, max_length=ns.max_length, validate=not ns.no_validate,
                         planner=PlannerConfig(max_iters=ns.rrt_iters),
                         timing=Timing(max_speed=ns.max_speed),
                         replay=ReplayConfig(tolerance=ns.tolerance, grasp_tolerance=ns.grasp_tolerance))
