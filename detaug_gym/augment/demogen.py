"""DemoGen mode: train-time obstacles on the free-space demos, with planned detours around them.

A sample (:meth:`DemoGenMode.propose`; the engine, :mod:`~detaug_gym.augment.engine`, draws up to ``tries``
per requested copy) is:

1. an obstacle shape: one of SafeLIBERO's six types (their collision meshes, from the scene of the suite's
   ``shape_source_level``, L1; Spatial's for a suite without one; cached on disk;
   :mod:`~detaug_gym.augment.obstacle_shapes`) or a random box / cylinder (half-width 0.015-0.06 m,
   half-height 0.02-0.11 m), with a random yaw;
2. a placement on the support under a random point of a random transit's path (20-80% of its length,
   up to 2 cm sideways), kept only where the obstacle's footprint clears every scene object by 1 cm, the
   robot proxy (hand + wrist + held object, :mod:`~detaug_gym.augment.planner`) moving along the
   original transit *intersects* it, and the unchanged frames (interaction windows, margins) are clear
   of it (``placement_tries`` placements per sample, else ``no_placement``);
3. for every transit the obstacle blocks, a detour from RRT-Connect in grip-site position space, then
   shortcutting, corner cutting and retiming (the source's mean speed, capped at ``max_speed``, smooth
   trapezoid progress; orientation slerped with the same progress), re-checked frame by frame;
4. the engine's checks: IK, joint limits / speed / acceleration and MuJoCo contacts with the scene
   (``SourceContext.check_span``), then the closed-loop replay in the (obstacle-free) env, kept if it
   succeeds, tracks the detour and the held object does not slip; finally (:meth:`DemoGenMode.accept`) the
   recorded robot (surface points by FK) and held object must stay out of the obstacle's convex hull
   (``replay_collision``).

The obstacle exists only in the data: the recorded demo carries its 256 world-frame surface points
(``obstacle_points``, the env's convention) and the originals none (an empty cloud: mask 0 in training).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np
import trimesh

from detaug_gym.augment.arcs import arc_steps, peak_factor, smooth_trapezoid
from detaug_gym.augment.context import SourceContext
from detaug_gym.augment.engine import Mode, Proposal, StageConfigs
from detaug_gym.augment.obstacle_shapes import ObstacleShape, sample_shape
from detaug_gym.augment.plan import ArcSample, Plan, Replacement, splice_transits
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
from detaug_gym.augment.segment import Transit
from detaug_gym.envs.suites import SuiteSpec
from detaug_gym.rotations import quat_xyzw_to_mat, slerp

__all__ = ["MODE", "DemoGenConfig", "DemoGenMode", "TrainObstacle"]


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
    suite: SuiteSpec

    @classmethod
    def build(cls, ctx: SourceContext, config: DemoGenConfig, suite: SuiteSpec) -> DemoGenSource:
        problem = ctx.env.unwrapped.placement_problem(np.random.default_rng(0))
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
class TrainObstacle:
    """An obstacle placed for one sample; it exists only in the data (the replay runs without it).

    Attributes:
        mesh: its world-frame mesh; points: (N_POINTS, 3) world-frame surface samples; pose: 4x4.
        blocked: indices (into the segmentation's transits) of the transits whose original path hits it.
        table_top: height (m) of the support it stands on.
    """

    shape: ObstacleShape
    mesh: trimesh.Trimesh
    points: np.ndarray
    pose: np.ndarray
    blocked: list[int]
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


def sample_obstacle(src: DemoGenSource, rng: np.random.Generator, config: DemoGenConfig) -> TrainObstacle | None:
    """An obstacle that blocks at least one transit and leaves the scene objects and unchanged frames clear."""
    ctx = src.ctx
    transits = [i for i, ok in ctx.bendable.items() if ok]
    for _ in range(config.placement_tries):
        shape = sample_shape(rng, src.suite, config.shapes, config.half_width, config.half_height)
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
        return TrainObstacle(shape, mesh, points, pose, blocked, support)
    return None


@dataclass
class Detour:
    transit: Transit
    pos: np.ndarray  # (n + 1, 3) targets, rows 0 and n the source's endpoints
    quat: np.ndarray  # (n + 1, 4) xyzw
    length: float
    raw_nodes: int


def plan_detour(src: DemoGenSource, obstacle: TrainObstacle, i: int, rng: np.random.Generator,
                config: DemoGenConfig) -> Detour | str:
    """RRT-Connect + shortcut + smoothing + retiming for transit ``i``; a rejection reason on failure."""
    ctx = src.ctx
    tr = ctx.segmentation.transits[i]
    parts = src.parts(i) if tr.kind == "carry" else src.hand
    start, goal = ctx.pos[tr.start], ctx.pos[tr.end]
    r0, r1 = src.rots[tr.start], src.rots[tr.end]
    probe = ProxyWorld(obstacle.mesh, obstacle.table_top, parts)
    table_top = min(obstacle.table_top, probe.lowest_point(start, r0), probe.lowest_point(goal, r1)) - 0.005
    world = ProxyWorld(obstacle.mesh, table_top, parts)
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


# ---------------------------------------------------------------------------------------------- the mode
class DemoGenMode(Mode):
    """Train-time obstacles and planned detours (see the module docstring). DemoGen demos carry no label
    (``label_size`` 0): the obstacle cloud is their conditioning."""

    name = "demogen"
    config_cls = DemoGenConfig

    def prepare(self, ctx: SourceContext, config: DemoGenConfig, suite: SuiteSpec) -> DemoGenSource:
        return DemoGenSource.build(ctx, config, suite)

    def skip_reason(self, source: DemoGenSource) -> str | None:
        ctx = source.ctx
        return None if ctx.segmentation.grasps and any(ctx.bendable.values()) else "no_transit"

    def propose(self, source: DemoGenSource, rng: np.random.Generator, config: DemoGenConfig) -> Proposal | str:
        """An obstacle on a transit's path and a detour for every transit it blocks."""
        obstacle = sample_obstacle(source, rng, config)
        if obstacle is None:
            return "no_placement"
        detours = []
        for i in obstacle.blocked:
            detour = plan_detour(source, obstacle, i, rng, config)
            if isinstance(detour, str):
                return detour
            detours.append(detour)
        plan = build_detour_plan(source.ctx, detours)
        ordered = sorted(detours, key=lambda d: d.transit.start)  # the plan's spans are in time order
        spans = [{"path_length": s.arc_len, "rrt_nodes": d.raw_nodes} for s, d in zip(plan.spans, ordered)]
        pose, bounds = obstacle.pose, obstacle.mesh.bounds
        attrs = {"obstacle_kind": obstacle.shape.kind,
                 "obstacle_pose": pose[:3, 3].tolist() + [float(np.arctan2(pose[1, 0], pose[0, 0]))],
                 "obstacle_size": (0.5 * (bounds[1] - bounds[0])).tolist()}
        return Proposal(plan, np.zeros(0), attrs, spans, obstacle_points=obstacle.points, detail=obstacle)

    def accept(self, source: DemoGenSource, proposal: Proposal, recording, config: DemoGenConfig) -> str | None:
        """``replay_collision`` when the recorded robot or held object reaches into the obstacle."""
        carried = sorted({h.body for h in source.ctx.held.values() if h is not None})
        depth = replay_penetration(source.ctx, np.asarray(recording.states), proposal.detail.mesh, carried)
        return "replay_collision" if depth > config.replay_tolerance else None

    def add_arguments(self, group) -> None:
        group.add_argument("--shapes", choices=("all", "safelibero", "primitives"), default="all",
                           help="obstacle shapes: SafeLIBERO's six and random boxes/cylinders (all, default)")
        group.add_argument("--placement-tries", type=int, default=60, help="obstacle placements per sample (60)")
        group.add_argument("--clearance", type=float, default=0.01, help="hand proxy inflation, m (default 0.01)")
        group.add_argument("--rrt-iters", type=int, default=2000, help="RRT-Connect iterations (default 2000)")

    def make_config(self, ns, stages: dict) -> DemoGenConfig:
        if ns.placement_tries < 1:
            raise SystemExit("error: --placement-tries must be >= 1")
        return DemoGenConfig(**stages, shapes=ns.shapes, placement_tries=ns.placement_tries,
                             proxy_margin=ns.clearance, planner=PlannerConfig(max_iters=ns.rrt_iters))


MODE = DemoGenMode()
