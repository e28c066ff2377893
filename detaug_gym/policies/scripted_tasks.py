"""What the scripted expert knows about the task objects: grasp geometry, place rules and task recipes.

Everything here was measured once on the compiled LIBERO / Newton scenes (collision-geom bounds in each
body's frame, site sizes from the bddl regions) and is expressed relative to the poses that the
observation carries (``object_poses``: the task-relevant bodies and sites in bddl goal order, deduplicated),
so the expert needs nothing but the observation.

Conventions: heights are metres along world z from a body origin (objects rest upright in every scene);
horizontal offsets are in the body frame. The hand's default orientation (yaw 0) points the fingers down
with the fingers closing along world y.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detaug_gym.envs.suites import SUITES


@dataclass(frozen=True)
class GraspSpec:
    """How to hold one object.

    Attributes:
        style: ``"rim"`` pinches one wall of a cup-like shell (bowl, mug), ``"body"`` closes across the
            whole object.
        height: grip-site height above the body origin at the grasp (``rim``: below the rim top, where
            the finger pads reach the wall; ``body``: around the upper middle, pads clear of the support).
        bottom: depth of the object's lowest point below its origin (negative: bottom above the origin).
        axes: body-frame axes the fingers may close along (``body``); the one needing the least hand yaw
            is used.
        rim_center: body-frame xy of the cup axis (``rim``).
        rim_radius: distance of the wall from the cup axis (``rim``).
        rim_dirs: body-frame angles (rad) of the wall points that may be grasped (``rim``; mugs: away
            from the handle); the one facing the robot's midline (world y = 0) is used.
    """

    style: str
    height: float
    bottom: float
    axes: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0),)
    rim_center: tuple[float, float] = (0.0, 0.0)
    rim_radius: float = 0.0
    rim_dirs: tuple[float, ...] = tuple(np.arange(8) * np.pi / 4)


X, Y, Z = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)

# Heights and bottoms from the collision geoms' bounds at rest; rim radii from the wall pieces of the
# shell meshes (bowl wall mid-surface at r = 0.046 + 0.27 h, 2.7 mm thick, rim top 0.052 above the origin;
# the mugs' cup axes sit off the body origin, on the side away from the handle).
OBJECTS: dict[str, GraspSpec] = {
    "bowl": GraspSpec("rim", height=0.030, bottom=-0.0016, rim_center=(0.0, 0.0), rim_radius=0.048),
    "porcelain_mug": GraspSpec("rim", height=0.090, bottom=-0.0024, rim_center=(0.017, 0.0), rim_radius=0.045,
                                   rim_dirs=(0.0,)),
    "white_yellow_mug": GraspSpec("rim", height=0.085, bottom=0.0001, rim_center=(-0.019, 0.0),
                                  rim_radius=0.046, rim_dirs=(np.pi,)),
    "carton": GraspSpec("body", height=0.025, bottom=0.0698, axes=(X, Z)),  # orange juice, milk (lying frame)
    "pudding": GraspSpec("body", height=0.002, bottom=0.0131, axes=(Y,)),
    "bbq_sauce": GraspSpec("body", height=0.025, bottom=0.0546, axes=(Y, X)),
    "cream_cheese": GraspSpec("body", height=0.002, bottom=0.0089, axes=(Y,)),
    "can": GraspSpec("body", height=0.012, bottom=0.0384, axes=(X, Z)),  # alphabet soup, tomato sauce
    "cube": GraspSpec("body", height=0.004, bottom=0.02, axes=(X, Y)),  # Newton
}


@dataclass(frozen=True)
class PlaceSpec:
    """Where a held object goes, relative to the target pose from the observation.

    Attributes:
        surface: height of the supporting surface above the target's origin; the object is released with
            its bottom ``clearance`` above it.
        clearance: release gap (m) between the object's bottom and ``surface``.
        offset: body-frame xy offset of the place point from the target origin.
        rim: height above the target's origin that the object's bottom must clear before the final descent
            (container walls); ``None``: the surface.
        world_offset: world-frame xy shift of the place point (for targets whose frame is tilted).
        hand_floor: lowest grip-site height above the target's origin at the release (a container whose
            opening is narrower than the 0.21 m hand: the object is let go above it and drops in).
    """

    surface: float
    clearance: float = 0.008
    offset: tuple[float, float] = (0.0, 0.0)
    rim: float | None = None
    world_offset: tuple[float, float] = (0.0, 0.0)
    hand_floor: float | None = None


TARGETS: dict[str, PlaceSpec] = {
    "plate": PlaceSpec(surface=0.0164),
    "cabinet_top": PlaceSpec(surface=0.0),  # wooden_cabinet_1_top_side is the top face
    "stove": PlaceSpec(surface=0.0),  # flat_stove_1_cook_region: the burner plate
    # Drawer floor / walls around the site. The site is the drawer's centre; opened 0.15 m, the part outside the
    # cabinet is y in [-0.166, -0.022] (world), so the bowl (rim radius 0.061) goes 0.012 m in front of the
    # site; +x keeps the fingers (on the bowl's -x side) off the drawer's left wall.
    "drawer": PlaceSpec(surface=-0.027, clearance=0.012, rim=0.065, world_offset=(0.015, 0.012)),
    # region centre; wicker rim 0.074 above; the hand's underside sits 0.024 above the grip site
    "basket": PlaceSpec(surface=-0.045, clearance=0.02, rim=0.074, hand_floor=0.074 - 0.024 + 0.012),
    "bowl": PlaceSpec(surface=0.012, clearance=0.02, rim=0.052),  # cream cheese into the bowl
    "table_region": PlaceSpec(surface=0.0268, offset=(0.0, 0.02)),  # plate-right region of Long task 3
    "disc": PlaceSpec(surface=0.0),  # Newton target disc (origin on the table top)
}

# Top drawer of LIBERO's wooden cabinet, in the frame of the site ``wooden_cabinet_1_top_region`` (which
# rides on the drawer): the handle bar's centre and the drawer's opening direction, and how far it opens.
DRAWER_HANDLE = np.array([0.0017, -0.1129, -0.0061])
DRAWER_OPEN_DIR = np.array([0.0, -1.0, 0.0])
DRAWER_TRAVEL = 0.15
# Opened, the drawer's front reaches y = -0.016 and its left wall x = -0.09: its corner sits within 2-3 cm of
# the bowl's start (x -0.104..-0.075, y -0.014..0.015), where any top-down rim grasp puts the 0.21 m wide hand.
# So the bowl is first moved here (world xy, relative to the closed drawer's site): clear of the drawer, the
# wine bottle (x < -0.166, y < -0.013), the stove and the cream cheese (x > -0.11, y > 0.089).
DRAWER_STAGE = np.array([-0.171, 0.307])


@dataclass(frozen=True)
class Step:
    """One pick-and-place of a recipe: slots index ``object_poses``.

    ``rim_away`` (rim grasps) favours wall points facing away from the target, for targets that crowd the
    object's near side. ``rim_prefer`` (world xy direction from the cup axis) picks the wall point on that
    side whatever the wrist turn, and ``rim_jitter`` scales the per-demo rim-angle jitter (tight scenes).
    ``place_shift`` (world xy) moves the place point, so two objects put in one container do not land on
    each other.
    """

    obj_slot: int
    obj: str
    target_slot: int
    target: str
    rim_away: float = 0.0
    rim_prefer: tuple[float, float] | None = None
    rim_jitter: float = 1.0
    place_shift: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class Recipe:
    """The expert's plan for one task: optionally open the top drawer first, then the pick-and-places.

    ``tempo`` scales the demo's transit speed and ``lead`` (steps) runs the servo target ahead of the
    minimum-jerk profile, so moves end sooner (the drawer task has three stages in LIBERO's 300 steps).
    """

    key: str
    steps: tuple[Step, ...]
    open_drawer: bool = False
    tempo: float = 1.0
    lead: int = 0


def _single(key: str, obj: str, target: str, **kw) -> Recipe:
    return Recipe(key, (Step(0, obj, 1, target),), **kw)


RECIPES: dict[str, Recipe] = {
    "bowl_on_plate": _single("bowl_on_plate", "bowl", "plate"),
    # Goal scene: the cabinet front is 0.1 m on the bowl's -y side; a hand on that side hits it in the carry
    "goal_bowl_on_plate": Recipe("goal_bowl_on_plate", (Step(0, "bowl", 1, "plate", rim_prefer=(0.0, 1.0)),)),
    "bowl_on_cabinet": _single("bowl_on_cabinet", "bowl", "cabinet_top"),
    "bowl_on_stove": _single("bowl_on_stove", "bowl", "stove"),
    # after the drawer is open the bowl is grasped on its -x side: the fingers then stay clear of the drawer walls
    "drawer_bowl": Recipe("drawer_bowl", (Step(0, "bowl", 1, "drawer", rim_prefer=(-1.0, 0.0), rim_jitter=0.3),),
                          open_drawer=True, tempo=1.3, lead=2),
    "cream_cheese_in_bowl": _single("cream_cheese_in_bowl", "cream_cheese", "bowl"),
    "orange_juice": _single("orange_juice", "carton", "basket"),
    "chocolate_pudding": _single("chocolate_pudding", "pudding", "basket"),
    "milk": _single("milk", "carton", "basket"),
    "bbq_sauce": _single("bbq_sauce", "bbq_sauce", "basket"),
    # two objects into the basket (contain region +-0.061 m): the first to the far side, the second near
    "soup_cheese_basket": Recipe("soup_cheese_basket", (
        Step(0, "can", 1, "basket", place_shift=(0.03, 0.0)),
        Step(2, "cream_cheese", 1, "basket", place_shift=(-0.025, 0.0)))),
    "soup_sauce_basket": Recipe("soup_sauce_basket", (
        Step(0, "can", 1, "basket", place_shift=(0.03, 0.0)),
        Step(2, "can", 1, "basket", place_shift=(-0.03, 0.0)))),
    "mugs_on_plates": Recipe("mugs_on_plates", (Step(0, "porcelain_mug", 1, "plate"),
                                                Step(2, "white_yellow_mug", 3, "plate"))),
    "mug_plate_pudding": Recipe("mug_plate_pudding", (Step(0, "porcelain_mug", 1, "plate"),
                                                      Step(2, "pudding", 3, "table_region"))),
    "newton_cube": _single("newton_cube", "cube", "disc"),
}

# Tasks whose recipe is not named by their key: every Spatial task moves a black bowl onto the same plate
# (the tasks differ in where the bowl starts), and Goal's plate stands elsewhere than Spatial's.
RECIPE_OF_TASK = {("goal", "bowl_on_plate"): "goal_bowl_on_plate"} | {
    ("spatial", task.key): "bowl_on_plate" for task in SUITES["spatial"].tasks}


def recipe_for(suite: str, task_key: str) -> str:
    """The recipe name of a suite's task (its key in the suite registry); ``ValueError`` if there is none."""
    name = RECIPE_OF_TASK.get((suite, task_key), task_key)
    if name not in RECIPES:
        raise ValueError(f"no scripted recipe for {suite} task {task_key!r}; recipes: {', '.join(sorted(RECIPES))}")
    return name


def _quat_close(q: np.ndarray, ref: tuple[float, float, float, float], tol: float = 0.05) -> bool:
    return abs(float(np.dot(q, ref))) > 1.0 - tol


def identify_task(obs: dict[str, np.ndarray]) -> str:
    """Name of the recipe for the episode that ``obs`` (a first observation) belongs to.

    Uses only the observation: the Newton env has one task; the Long suite has four object slots; the
    Object suite's scene is LIBERO's floor scene (objects near z = 0); the kitchen scenes (Spatial, Goal)
    are told apart by the target's pose, which is fixed per task (cabinet top, stove, drawer region) or by
    the object to pick (the cream cheese lies at yaw 180 deg, the bowls at 90 deg); the plate's place tells
    Goal's bowl-on-plate from Spatial's.

    Raises:
        ValueError: the observation matches no known task.
    """
    task_id = np.asarray(obs["task_id"]).ravel()
    index = int(np.argmax(task_id))
    poses = np.asarray(obs["object_poses"], dtype=np.float64)
    if task_id.size == 1:
        return "newton_cube"
    if poses.shape[0] == 4:
        return SUITES["long"].tasks[index].key
    obj, target = poses[0], poses[1]
    if obj[2] < 0.3:
        return SUITES["object"].tasks[index].key
    if obj[2] < 0.8:
        raise ValueError(f"no scripted recipe for a scene with objects at z = {obj[2]:.3f}")
    if _quat_close(target[3:], (-0.7071, 0.0, 0.7071, 0.0)):
        return "drawer_bowl"
    if target[2] > 1.05:
        return "bowl_on_cabinet"
    if _quat_close(target[3:], (0.0, 0.0, 0.0, 1.0)):
        return "bowl_on_stove"
    if _quat_close(obj[3:], (0.0, 0.0, 1.0, 0.0)):
        return "cream_cheese_in_bowl"
    if target[1] < 0.1:  # Goal's plate stands in front of the cabinet (y ~ -0.02); Spatial's at y ~ 0.2
        return "goal_bowl_on_plate"
    return "bowl_on_plate"
