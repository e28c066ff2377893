"""Scripted expert (``scripted``): privileged-state pick-and-place demonstrations from the observation alone.

The expert reads the task-relevant object poses, the task one-hot and its own end-effector and gripper
state from the env's observation (``object_poses`` holds the bddl goal's objects and targets in order), so
``make_policy("scripted")`` drives any SafeLibero or Newton env without access to the simulator. Which
task it faces is recognised from the first observation (:func:`~detaug_gym.policies.scripted_tasks.
identify_task`); the recipes and the object geometry live in :mod:`detaug_gym.policies.scripted_tasks`.

Per pick-and-place: move above the grasp, descend, close, lift (and check the object came along, else
retry), carry to above the place point keeping the grasp offset, descend, release, retreat. A descent
that stops on the object (the open fingers get pushed together, or the hand ends well above or beside the
grasp point: a finger on the rim of the bowl propped on the ramekin) backs off and comes again at another
rim point instead of closing, which would squeeze the object away. Near the edge of the arm's reach (the
bowl on the cabinet) the rim point nearest the arm's base is taken and the hand leans outwards, so the elbow
stays clear of its stretched, singular pose. A rim-held object is let go with the outer finger held in place
(the hand moves inwards as the fingers open: a pad can wedge in the bowl's faceted wall and drag it along). The drawer
task pulls the top drawer open first (grasping its handle with the hand pitched towards the cabinet; a grasp
that missed the bar or lost it in the pull is let go and tried again). ``fumble`` makes a share of the grasps
(handle and picks) miss first on purpose, for recovery demos.
Motions are straight lines with a minimum-jerk speed profile, tracked by a proportional servo on the
end-effector pose, so transits look like teleoperation rather than bang-bang control.

Per-demo variation (all from the ``reset`` seed): overall speed, approach and lift heights, grasp point
(rim angle, height, along the object), place jitter (well inside the success tolerance) and small
via-point jitter on the transits. The expert ignores obstacles: on L1/L2 it drives straight through.

    >>> from detaug_gym.policies import make_policy
    >>> expert = make_policy("scripted")
    >>> expert.reset(seed=0); action = expert.act(obs)
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from detaug_gym.actions import ACTION_DIM, GRIPPER_CLOSE, GRIPPER_OPEN, goal_to_action
from detaug_gym.policies.options import ScriptedOptions
from detaug_gym.policies.scripted_math import bezier, min_jerk, rot_x, rot_z, wrap_yaw
from detaug_gym.policies.scripted_tasks import (
    DRAWER_HANDLE,
    DRAWER_OPEN_DIR,
    DRAWER_STAGE,
    DRAWER_TRAVEL,
    OBJECTS,
    RECIPES,
    TARGETS,
    Recipe,
    Step,
    identify_task,
    recipe_for,
)
from detaug_gym.rotations import quat_xyzw_to_mat, rotation_error

# End of the descent to a grasp: a hand this far above (or beside) the grasp point did not get there (good grasps
# close within ~2 cm: the servo stops short of pads resting on the wall).
BLOCKED_DZ, BLOCKED_DXY = 0.028, 0.035
SQUEEZED = 0.012  # open fingers pushed this much closer together: one came down on something
TRANSIT_Z = 1.21  # kitchen scenes: grip-site height that keeps the hand above the drawer and the wine bottle
# Reach: LIBERO mounts the Panda with its base 0.45 m behind (-x) the grip site's start pose. With the hand pointing
# down, a grip site ~0.73 m (horizontally) from the base at table-top grasp height needs the elbow stretched to its
# singular pose (joint 4 ~ -0.47 rad): the servo stalls there, 2 cm above the grasp (Spatial task 3, the bowl on
# the cabinet). So rim points beyond REACH_SOFT are penalised, and a far rim grasp leans the approach axis outwards
# (fingertips towards the cup's axis, up to MAX_PITCH; this also tilts the pads towards the slope of its flared wall):
# the wrist then stays ~5 cm nearer the base.
BASE_FROM_HOME = np.array([-0.45, 0.0])
REACH_SOFT, REACH_WEIGHT = 0.70, 30.0  # m, score per m beyond
PITCH_FROM, PITCH_FULL, MAX_PITCH = 0.66, 0.71, 0.26  # reach (m) where the lean starts / is full; rad
LET_GO_SHIFT = 0.03  # letting go of a rim-held object: the hand moves at most this far towards the cup's axis
LET_GO_GAIN = 1.0  # hand shift per m of finger opening (the outer pad moves half of it; the rest covers the servo lag)
# Grip-site orientation with the fingers pointing down and closing along world y (xyzw 0.7071, 0.7071, 0, 0).
R_DOWN = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
# The drawer handle: finger gap (m) of a grasp closed on the bar (below: shut on nothing; above: stopped open on
# the drawer front), how far the drawer may lag the pulling hand before the bar counts as lost, how far out it
# counts as opened, and how many grasps are tried.
HANDLE_GRIP = (0.002, 0.025)
DRAWER_LAG, DRAWER_OPENED, HANDLE_ATTEMPTS = 0.02, 0.10, 3
# A deliberate first miss (``fumble``): the grasp point this far (m) in front of, above or below the bar. Nearer
# misses, and any too deep (the fingertips stop on the drawer front with the bar between them), still open it.
HANDLE_MISS = (0.035, 0.05)
# An object pick's deliberate first miss (not of rim-held objects): the descent goes this far (m) beside the grasp
# point, in a random horizontal direction (a finger lands on the object, or the fingers straddle air beside it), as
# a policy's grasps miss (Long's base: 3-6 cm). The expert's own checks then back off and grasp again.
PICK_MISS = (0.025, 0.04)
FUMBLE_CLOSE_STEPS = 12  # the fumbled grasp's fingers close this many steps (the command ramps in 8)

Actions = Generator[np.ndarray, None, None]


@dataclass(frozen=True)
class DemoStyle:
    """The per-demo variation drawn from the seed.

    Attributes:
        speed: average transit speed (m per 20 Hz step).
        approach: height of the pre-grasp point above the grasp.
        lift: lift height above the grasp before the carry.
        place_approach: height above the release point where the final descent starts.
        rim_angle: angle (rad) of the rim grasp point around the cup, from the side facing the robot.
        grasp_dz: added to the grasp height.
        grasp_along: shift (m) of a body grasp along the fingers' free axis.
        place_jitter: xy shift (m) of the release point.
        via: xy offset (m) of the transit via-point from the segment midpoint (0 = straight).
    """

    speed: float
    approach: float
    lift: float
    place_approach: float
    rim_angle: float
    grasp_dz: float
    grasp_along: float
    place_jitter: tuple[float, float]
    via: tuple[float, float]

    @staticmethod
    def sample(rng: np.random.Generator, variation: float = 1.0) -> DemoStyle:
        u = lambda lo, hi: float(rng.uniform(lo, hi))  # noqa: E731
        v = variation
        return DemoStyle(
            speed=0.016 + v * u(-0.004, 0.004),
            approach=0.09 + v * u(-0.03, 0.03),
            lift=0.12 + v * u(-0.03, 0.03),
            place_approach=0.07 + v * u(-0.02, 0.02),
            rim_angle=v * u(-0.25, 0.25),
            grasp_dz=v * u(-0.004, 0.004),
            grasp_along=v * u(-0.004, 0.004),
            place_jitter=(v * u(-0.006, 0.006), v * u(-0.006, 0.006)),
            via=(v * u(-0.03, 0.03), v * u(-0.03, 0.03)),
        )


class ScriptedExpert:
    """Privileged scripted expert for the SafeLibero suites and the Newton pick-and-place.

    Args:
        task: recipe name (a key of :data:`~detaug_gym.policies.scripted_tasks.RECIPES`); default: the
            episode context's task (``reset(context=...)``), else recognised from the first observation.
        variation: scale of the per-demo variation (0 = the same nominal motion every episode).
        seed: default seed when ``reset`` gets none.
        fumble: chance that a grasp's first try (the drawer handle's, each pick's) misses on purpose (see
            :attr:`sent`).
        suite: accepted (the bench passes it to every policy) and ignored.

    Attributes:
        sent: while a fumble is acted out, the action (7,) to send the env instead of the returned one (which
            stays the correct command, the demo's label); ``None`` otherwise. ``python -m detaug_gym.collect``
            sends it (:class:`~detaug_gym.collect.ActedOutHook`). A rollout that sends the returned actions
            instead takes the hand to the grasp point without closing it there, and the expert grasps again
            (about 45 steps lost): ``fumble`` is a collection option.
    """

    def __init__(self, task: str | None = None, variation: float = 1.0, seed: int | None = None,
                 fumble: float = 0.0, suite: str | None = None) -> None:
        options = ScriptedOptions(task=task, variation=variation, seed=seed, fumble=fumble)
        self.task = options.task
        self.variation = options.variation
        self.fumble = options.fumble
        self._default_seed = options.seed
        self.reset(options.seed)

    # ------------------------------------------------------------------ policy protocol
    def reset(self, seed: int | None = None, context=None) -> None:
        self._context_recipe = None if context is None else recipe_for(context.suite, context.task_key)
        self._rng = np.random.default_rng(self._default_seed if seed is None else seed)
        self.style = DemoStyle.sample(self._rng, self.variation)
        # the fumble draws come from a stream of their own, so the demo's style is the same with or without them
        self._fumble_rng = np.random.default_rng(self._rng.bit_generator.seed_seq.spawn(1)[0])
        self.handle_miss = self._draw_handle_miss()
        self._acting: tuple[np.ndarray, float | None] | None = None  # (miss, gripper) while acting out a fumble
        self.sent: np.ndarray | None = None
        self.recipe: Recipe | None = None
        self._script: Actions | None = None
        self._obs: dict[str, np.ndarray] = {}
        self._yaw = 0.0
        self._pitch = 0.0
        self._grip = GRIPPER_OPEN
        self._last = np.zeros(ACTION_DIM, dtype=np.float32)
        self._home = np.zeros(3)
        self._start_poses = np.zeros((0, 7))
        self.trace: list[tuple[str, int, bool]] = []  # (primitive, steps, reached) for debugging

    def _draw_handle_miss(self) -> np.ndarray:
        """With probability ``fumble``, a first handle grasp point off the bar (drawer-site frame, m): in front of
        it (the fingers shut on nothing or on its edge), above or below it."""
        rng = self._fumble_rng
        if not self.fumble or rng.uniform() >= self.fumble:
            return np.zeros(3)
        way = ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0), (0.0, 0.0, -1.0))[rng.integers(3)]  # -y: out of the cabinet
        return rng.uniform(*HANDLE_MISS) * np.array(way)

    def _draw_pick_miss(self, step: Step) -> np.ndarray:
        """With probability ``fumble``, a pick's first descent point off the grasp point (world frame, m):
        :data:`PICK_MISS` away in a random horizontal direction. Never for a rim-held object (a mug, a bowl):
        fingers coming down beside or inside its rim tip it over, and its demos taught worse grasps."""
        rng = self._fumble_rng
        if not self.fumble or OBJECTS[step.obj].style == "rim" or rng.uniform() >= self.fumble:
            return np.zeros(3)
        angle = rng.uniform(-np.pi, np.pi)
        return rng.uniform(*PICK_MISS) * np.array([np.cos(angle), np.sin(angle), 0.0])

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        self._obs = obs
        if self._script is None:
            self.recipe = RECIPES[self.task or self._context_recipe or identify_task(obs)]
            self.style = replace(self.style, speed=self.style.speed * self.recipe.tempo)
            self._yaw = self._current_yaw()
            self._home = self._eef()
            self._start_poses = np.array(obs["object_poses"], dtype=np.float64)
            self._script = self._run(self.recipe)
        try:
            self._last = next(self._script)
        except StopIteration:
            self._last = self._servo(self._eef(), self._grip)
        return self._last

    # ------------------------------------------------------------------ the script
    def _run(self, recipe: Recipe) -> Actions:
        if recipe.open_drawer:
            yield from self._stage_for_drawer(recipe.steps[0])
            yield from self._open_drawer(recipe.steps[0].target_slot)
        transit_z = TRANSIT_Z if recipe.open_drawer else None
        for step in recipe.steps:
            miss = self._draw_pick_miss(step)
            for _ in range(3):  # the object can slip out in the carry: pick it up again
                offset = yield from self._pick(step, transit_z=transit_z, miss=miss)
                miss = np.zeros(3)
                if (yield from self._place(step, offset)):
                    break
            # leaving a container: arc over its rim (the servo lags the curve, hence the margin)
            transit_z = self._eef()[2] + 0.06 if TARGETS[step.target].rim is not None else None
        while True:  # hold still, gripper open, until the env ends the episode
            yield self._servo(self._eef(), GRIPPER_OPEN)

    def _pick(self, step: Step, lift: float | None = None, transit_z: float | None = None,
              miss: np.ndarray | None = None) -> Generator[np.ndarray, None, np.ndarray]:
        """Grasp the object in ``step.obj_slot`` and lift it; returns the grasp offset (eef - object).

        ``lift`` (m above the grasp) replaces the default lift to the carry height (short hops);
        ``transit_z``: first go over the pre-grasp point at this height, turning the hand there, then down;
        ``miss`` (3,): the first descent and close are acted out this far beside the grasp point (``fumble``).
        """
        style = self.style
        for attempt in range(4):
            grasp, yaw = self._grasp_pose(step, attempt)
            pitch = self._reach_pitch(grasp, yaw) if OBJECTS[step.obj].style == "rim" else 0.0
            start_z = self._pose(step.obj_slot)[2]
            pre = grasp + [0, 0, style.approach]
            # with a transit height: arc over, staying high until above the object
            over = None if transit_z is None else np.r_[pre[:2], max(transit_z, self._eef()[2])]
            yield from self._move(pre, yaw, GRIPPER_OPEN, style.speed, tol=0.01, via=over is None, pitch=pitch,
                                  mid=over)
            grasp, yaw = self._grasp_pose(step, attempt)
            # a finger landing on the object gets pushed in: stop pressing at once (pressing on, the wedged
            # finger flings a light object away when it comes free)
            squeezed = partial(lambda width: self._width() < width - SQUEEZED, self._width())
            if attempt == 0 and miss is not None and miss.any():
                yield from self._act_out_miss(grasp, miss, yaw, pitch, 0.6 * style.speed, check=squeezed)
            else:
                yield from self._move(grasp, yaw, GRIPPER_OPEN, 0.6 * style.speed, tol=0.004, check=squeezed)
            if attempt < 3 and self._blocked(step, attempt):
                # a finger came down on the rim, or the touch knocked the object away: closing would squeeze
                # it out of reach, so back off and come again (the next attempt turns the rim point)
                self.trace.append(("regrasp", 0, False))
                yield from self._move(self._eef() + [0, 0, 0.04], yaw, GRIPPER_OPEN, style.speed, tol=0.02)
                continue
            yield from self._gripper(GRIPPER_CLOSE)
            offset = self._eef() - self._pose(step.obj_slot)[:3]
            if lift is None:
                lift_z = max(grasp[2] + style.lift, self._above_place(step, offset)[2])
            else:
                lift_z = grasp[2] + lift
            slipped = partial(self._slipped, step.obj_slot, offset[2])
            closed_z = self._eef()[2]
            yield from self._move(np.r_[grasp[:2], lift_z], yaw, GRIPPER_CLOSE, 0.8 * style.speed,
                                  tol=0.02 if lift is None else 0.006, check=slipped)
            # judged against how far the hand actually rose: a short hop ends up to ``tol`` below its goal
            hand_rise = self._eef()[2] - closed_z
            if (hand_rise > 0.01 and self._pose(step.obj_slot)[2] - start_z > 0.6 * min(hand_rise, 0.05)
                    and not slipped()):
                return offset
            yield from self._gripper(GRIPPER_OPEN)
            yield from self._move(self._eef() + [0, 0, 0.06], yaw, GRIPPER_OPEN, style.speed, tol=0.02)
        return self._eef() - self._pose(step.obj_slot)[:3]

    def _reach_pitch(self, grasp: np.ndarray, yaw: float) -> float:
        """Hand pitch that leans the approach axis away from the arm's base for a grasp near the edge of reach."""
        out = grasp[:2] - (self._home[:2] + BASE_FROM_HOME)
        reach = float(np.linalg.norm(out))
        amount = MAX_PITCH * float(np.clip((reach - PITCH_FROM) / (PITCH_FULL - PITCH_FROM), 0.0, 1.0))
        lean = np.array([np.sin(yaw), -np.cos(yaw)])  # where a positive pitch leans the approach axis at this yaw
        return amount * float(lean @ out) / max(reach, 1e-9)

    def _blocked(self, step: Step, attempt: int) -> bool:
        """After the descent: the hand stopped well above the grasp point, or the object is no longer there."""
        grasp, _ = self._grasp_pose(step, attempt)
        error = self._eef() - grasp
        return bool(error[2] > BLOCKED_DZ or np.linalg.norm(error[:2]) > BLOCKED_DXY)

    def _slipped(self, slot: int, offset_z: float) -> bool:
        """The held object lags more than 3 cm below where the grasp offset says it should be."""
        return self._eef()[2] - self._pose(slot)[2] - offset_z > 0.03

    def _place(self, step: Step, offset: np.ndarray) -> Generator[np.ndarray, None, bool]:
        """Carry the held object over its place point, lower, release, retreat; False if it was dropped."""
        style = self.style
        above = self._above_place(step, offset)
        slipped = partial(self._slipped, step.obj_slot, offset[2])
        yield from self._move(above, self._yaw, GRIPPER_CLOSE, style.speed, tol=0.012, via=True, check=slipped)
        if slipped():
            return False
        release = self._place_eef(step, offset)
        yield from self._move(release, self._yaw, GRIPPER_CLOSE, 0.5 * style.speed, tol=0.005)
        if OBJECTS[step.obj].style == "rim":
            yield from self._let_go(step.obj_slot)
        else:
            yield from self._gripper(GRIPPER_OPEN)
        retreat = self._eef() + [0, 0, 0.08]
        place = TARGETS[step.target]
        if place.rim is not None:  # fingertips well above the rim before moving sideways
            retreat[2] = max(retreat[2], self._pose(step.target_slot)[2] + place.rim + 0.05)
        yield from self._move(retreat, self._yaw, GRIPPER_OPEN, 0.8 * style.speed, tol=0.02)
        return True

    def _stage_for_drawer(self, step: Step) -> Actions:
        """Move the object (the bowl) from under where the drawer will open to :data:`DRAWER_STAGE`.

        Grasped on its +y side (the hand then spans y, clear of the wine bottle at -x), lifted 2.5 cm,
        carried low and put down; the release leaves the hand above the rim.
        """
        style = self.style
        hop = replace(step, rim_prefer=(0.0, 1.0), rim_away=0.0, rim_jitter=0.3)
        start_z = self._pose(step.obj_slot)[2]
        offset = yield from self._pick(hop, lift=0.025)
        stage = self._start_poses[step.target_slot][:2] + DRAWER_STAGE
        down = np.r_[stage, start_z + 0.004] + offset
        yield from self._move(down + [0, 0, 0.02], self._yaw, GRIPPER_CLOSE, 0.8 * style.speed, tol=0.01)
        yield from self._move(down, self._yaw, GRIPPER_CLOSE, 0.5 * style.speed, tol=0.006)
        yield from self._release()
        yield from self._move(self._eef() + [0, 0, 0.05], self._yaw, GRIPPER_OPEN, style.speed, tol=0.02)

    def _let_go(self, slot: int) -> Actions:
        """Open the fingers on a set-down rim-held object, moving the hand towards the cup's axis as they open.

        A wall of LIBERO's bowl is a ring of flat boxes, and the outer pad can wedge between two of them: opening
        in place, that finger dragged the bowl 4 cm along (off the plate). Moving the hand inwards as the fingers
        open (half the opening keeps the outer pad in place, the rest makes up for the servo's lag) leaves the outer
        pad about where it was; the inner one (inside the cup) moves through free space.
        """
        inward = self._pose(slot)[:2] - self._eef()[:2]
        inward /= max(float(np.linalg.norm(inward)), 1e-9)
        yield from self._gripper(GRIPPER_OPEN, drift=inward, label="let-go")

    def _release(self, gap: float = 0.03) -> Actions:
        """Open the fingers until they have moved ``gap`` apart (or are fully open)."""
        hold, start = self._eef(), self._width()
        steps = 0
        while steps < 16:
            yield self._servo(hold, GRIPPER_OPEN)
            steps += 1
            if self._width() - start > gap or self._width() > 0.075:
                break
        self.trace.append(("grip", steps, True))

    def _open_drawer(self, site_slot: int) -> Actions:
        """Grasp the top drawer's handle with the hand pitched towards the cabinet and pull it open.

        A grasp that missed the bar (the fingers shut on nothing, or stopped open with the fingertips on the
        drawer front) or lost it in the pull (the drawer stops following the hand) is let go, backed off along
        the pull and tried again, up to ``HANDLE_ATTEMPTS`` times. The first attempt goes to the bar plus
        ``self.handle_miss`` (zero unless the ``fumble`` option drew a deliberate miss for a recovery demo).
        """
        style = self.style
        opened_from = self._pose(site_slot)[:3]
        for attempt in range(HANDLE_ATTEMPTS):
            site = self._pose(site_slot)
            rot = quat_xyzw_to_mat(site[3:])
            handle = site[:3] + rot @ DRAWER_HANDLE
            pull = rot @ DRAWER_OPEN_DIR
            yield from self._move(handle + 0.07 * pull + [0, 0, 0.02], 0.0, GRIPPER_OPEN, style.speed, tol=0.015,
                                  pitch=np.pi / 2)
            grasp = handle - 0.005 * pull
            if attempt == 0 and self.handle_miss.any():
                yield from self._act_out_miss(grasp, rot @ self.handle_miss, 0.0, np.pi / 2, 0.5 * style.speed)
            else:
                yield from self._move(grasp, 0.0, GRIPPER_OPEN, 0.5 * style.speed, tol=0.005, pitch=np.pi / 2)
                yield from self._gripper(GRIPPER_CLOSE)
            if HANDLE_GRIP[0] < self._width() < HANDLE_GRIP[1]:
                lost = partial(self._drawer_lags, site_slot, pull, self._eef() @ pull,
                               self._pose(site_slot)[:3] @ pull)
                travel = DRAWER_TRAVEL - float((site[:3] - opened_from) @ pull)
                yield from self._move(handle + travel * pull, 0.0, GRIPPER_CLOSE, 0.7 * style.speed, tol=0.01,
                                      pitch=np.pi / 2, check=lost)
            if float((self._pose(site_slot)[:3] - opened_from) @ pull) > DRAWER_OPENED:
                break
            self.trace.append(("handle-retry", attempt, False))
            yield from self._release()
            yield from self._move(self._eef() + 0.05 * pull + [0, 0, 0.01], 0.0, GRIPPER_OPEN, style.speed,
                                  tol=0.015, pitch=np.pi / 2)
        yield from self._release()
        # back out along the pull, then up to the transit height turning the hand down: the fingers must not
        # sweep over the drawer front (that pushes it shut again)
        yield from self._move(self._eef() + 0.05 * pull, 0.0, GRIPPER_OPEN, style.speed, tol=0.015)
        yield from self._move(np.r_[self._eef()[:2], TRANSIT_Z], 0.0, GRIPPER_OPEN, style.speed, tol=0.03, pitch=0.0)

    def _act_out_miss(self, grasp: np.ndarray, miss: np.ndarray, yaw: float, pitch: float, speed: float,
                      check=None) -> Actions:
        """A fumbled grasp (a drawer handle or an object), acted out in :attr:`sent` only: the env is sent the
        descent to ``grasp + miss`` and the fingers closing there, while the returned actions (the demo's labels)
        are the expert's correct commands from each state reached: on to ``grasp`` with the fingers open. As with
        action noise, the demo then shows the way back, not the mistake."""
        self._acting = (miss, None)
        yield from self._move(grasp, yaw, GRIPPER_OPEN, speed, tol=0.005, pitch=pitch, check=check)
        self._acting = (miss, GRIPPER_CLOSE)
        for _ in range(FUMBLE_CLOSE_STEPS):
            yield self._servo(grasp, GRIPPER_OPEN)
        self._acting = None
        self.trace.append(("fumble", FUMBLE_CLOSE_STEPS, False))

    def _drawer_lags(self, site_slot: int, pull: np.ndarray, hand_from: float, drawer_from: float) -> bool:
        """Pulling: the hand has moved along ``pull`` more than ``DRAWER_LAG`` further than the drawer."""
        return (self._eef() @ pull - hand_from) - (self._pose(site_slot)[:3] @ pull - drawer_from) > DRAWER_LAG

    # ------------------------------------------------------------------ geometry
    def _grasp_pose(self, step: Step, attempt: int = 0) -> tuple[np.ndarray, float]:
        """Grip-site position and hand yaw for grasping the object of ``step``."""
        spec = OBJECTS[step.obj]
        pose = self._pose(step.obj_slot)
        rot = quat_xyzw_to_mat(pose[3:])
        dz = self.style.grasp_dz + (0.006 * attempt if attempt else 0.0)
        if spec.style == "rim":
            # Wall points on the rim circle at grasp height, in the cup's own (possibly tilted) frame; take
            # the one facing where the hand started (the robot's side), which keeps the reach short and
            # the hand clear of the cup's far side, without turning the wrist much.
            centre = pose[:3] + rot @ np.array([*spec.rim_center, 0.0])
            base = self._home[:2] + BASE_FROM_HOME
            home = self._home[:2] - centre[:2]
            home /= max(np.linalg.norm(home), 1e-9)
            away = centre[:2] - self._pose(step.target_slot)[:2]
            away *= step.rim_away / max(np.linalg.norm(away), 1e-9)
            jitter = step.rim_jitter * self.style.rim_angle + 0.3 * attempt
            prefer = np.zeros(2) if step.rim_prefer is None else 4.0 * np.asarray(step.rim_prefer)
            best_score, point, direction = -np.inf, None, None
            dirs = spec.rim_dirs
            if step.rim_prefer is not None and len(dirs) == 8:  # round cup: any wall point, so the preferred one
                local = rot.T @ np.array([*step.rim_prefer, 0.0])
                dirs = (float(np.arctan2(local[1], local[0])),)
            for a in dirs:
                local = np.array([np.cos(a + jitter), np.sin(a + jitter), 0.0])
                radial = rot @ local
                flat = np.array([radial[0], radial[1], 0.0]) / max(np.linalg.norm(radial[:2]), 1e-9)
                yaw = wrap_yaw(np.arctan2(flat[1], flat[0]) - np.pi / 2, self._yaw)
                candidate = centre + rot @ (spec.rim_radius * local + np.array([0.0, 0.0, spec.height + dz]))
                reach = float(np.linalg.norm(candidate[:2] - base))
                score = (float((home + away + prefer) @ flat[:2]) - abs(yaw - self._yaw)  # big turns strain the arm
                         - REACH_WEIGHT * max(0.0, reach - REACH_SOFT))  # far points: the arm cannot get down there
                if score > best_score:
                    best_score, direction, point = score, flat, candidate
            # the fingers close along the radial direction, i.e. across the wall
            return point, wrap_yaw(np.arctan2(direction[1], direction[0]) - np.pi / 2, self._yaw)
        best = None
        for axis in spec.axes:
            world = rot @ np.array(axis)
            yaw = wrap_yaw(np.arctan2(world[1], world[0]) - np.pi / 2, self._yaw)
            if best is None or abs(yaw - self._yaw) < abs(best - self._yaw):
                best = yaw
        free_axis = np.array([np.cos(best), np.sin(best), 0.0])  # fingers close along y rotated by yaw
        point = pose[:3] + self.style.grasp_along * free_axis
        point[2] = pose[2] + spec.height + dz
        return point, best

    def _above_place(self, step: Step, offset: np.ndarray) -> np.ndarray:
        """Where the final descent starts: above the release point, with the object clear of any rim."""
        place = TARGETS[step.target]
        above = self._place_eef(step, offset) + [0, 0, self.style.place_approach]
        if place.rim is not None:
            clear = self._pose(step.target_slot)[2] + place.rim + 0.03 + OBJECTS[step.obj].bottom + offset[2]
            above[2] = max(above[2], clear)
        return above

    def _place_eef(self, step: Step, offset: np.ndarray) -> np.ndarray:
        """Grip-site position that releases the held object at the place point of ``step``."""
        spec, place = OBJECTS[step.obj], TARGETS[step.target]
        target = self._pose(step.target_slot)
        rot = quat_xyzw_to_mat(target[3:])
        point = target[:3] + rot @ np.array([*place.offset, 0.0])
        point[:2] += np.asarray(place.world_offset) + np.asarray(step.place_shift) + self.style.place_jitter
        point[2] = target[2] + place.surface + place.clearance + spec.bottom
        eef = point + offset
        if place.hand_floor is not None:  # the hand cannot go into the container: drop from above its rim
            eef[2] = max(eef[2], target[2] + place.hand_floor)
        return eef

    # ------------------------------------------------------------------ motion primitives
    def _move(self, goal: np.ndarray, yaw: float, grip: float, speed: float, tol: float, via: bool = False,
              pitch: float | None = None, check=None, timeout: int = 40, mid: np.ndarray | None = None,
              ) -> Actions:
        """Straight (or gently bent) minimum-jerk line to ``goal``; ends once within ``tol`` of it.

        ``check`` (optional) is called every step; returning True aborts the move (e.g. lost object).
        ``mid``: the Bezier control point (default the midpoint: a straight line).
        """
        start = self._eef()
        goal = np.asarray(goal, dtype=np.float64)
        yaw0, pitch0 = self._yaw, self._pitch
        pitch = pitch0 if pitch is None else pitch
        dist = float(np.linalg.norm(goal - start))
        turn = max(abs(yaw - yaw0), abs(pitch - pitch0))
        steps = max(int(np.ceil(dist / speed)), int(np.ceil(turn / 0.12)), 3)
        mid = 0.5 * (start + goal) if mid is None else np.asarray(mid, dtype=np.float64)
        if via and dist > 0.15:
            mid[:2] += self.style.via
        recent: list[np.ndarray] = []
        lead = self.recipe.lead if self.recipe is not None else 0
        for t in range(1, steps + timeout + 1):
            s = min_jerk(min((t + lead) / steps, 1.0))  # a lead of a few steps offsets the servo's lag
            carrot = bezier(start, mid, goal, s)
            turn_s = min(1.0, 1.4 * s)  # finish turning the hand before arriving
            self._yaw = yaw0 + (yaw - yaw0) * turn_s
            self._pitch = pitch0 + (pitch - pitch0) * turn_s
            yield self._servo(carrot, grip)
            if t >= steps and np.linalg.norm(self._eef() - goal) < tol and self._rotation_error() < 0.15:
                self.trace.append(("move", t, True))
                return
            recent = [*recent[-3:], self._eef()]
            if (t >= steps + 3 and np.linalg.norm(recent[-1] - recent[0]) < 0.0015
                    and self._rotation_error() < 0.3):  # stalled: blocked or at the edge of the reach
                self.trace.append(("move-stall", t, False))
                return
            if check is not None and t > 4 and check():
                self.trace.append(("move-abort", t, False))
                return
        self.trace.append(("move", steps + timeout, False))

    def _gripper(self, command: float, max_steps: int = 16, drift: np.ndarray | None = None,
                 label: str = "grip") -> Actions:
        """Hold the pose and open/close the fingers until they stop moving.

        The Panda gripper's command ramps (0.25 per step from -1 to +1), so the full grip force needs at
        least 8 steps even when the fingers stop on the object earlier. With ``drift`` (a unit xy direction)
        the held position moves along it by ``LET_GO_GAIN`` per m the fingers have opened, at most
        ``LET_GO_SHIFT``.
        """
        hold, width0 = self._eef(), self._width()
        last, still = width0, 0
        for t in range(max_steps):
            target = hold
            if drift is not None:
                shift = min(LET_GO_GAIN * max(self._width() - width0, 0.0), LET_GO_SHIFT)
                target = hold + np.r_[shift * drift, 0.0]
            yield self._servo(target, command)
            width = self._width()
            still = still + 1 if abs(width - last) < 2e-4 else 0
            last = width
            if t >= 8 and still >= 2:
                break
        self.trace.append((label, t + 1, True))

    def _rotation_error(self) -> float:
        current = quat_xyzw_to_mat(np.asarray(self._obs["eef_quat"], dtype=np.float64))
        return float(np.linalg.norm(rotation_error(self._hand_rotation(), current)))

    def _servo(self, target: np.ndarray, grip: float) -> np.ndarray:
        """OSC_POSE delta that sets the controller's goal to ``target`` and the current yaw/pitch (and, while a
        fumble is acted out, :attr:`sent` with the goal moved by the miss and the fumble's gripper command)."""
        self._grip = grip
        current = quat_xyzw_to_mat(np.asarray(self._obs["eef_quat"], dtype=np.float64))
        action = goal_to_action(self._eef(), current, target, self._hand_rotation(), grip).astype(np.float32)
        self.sent = None
        if self._acting is not None:
            miss, sent_grip = self._acting
            self.sent = goal_to_action(self._eef(), current, target + miss, self._hand_rotation(),
                                       grip if sent_grip is None else sent_grip).astype(np.float32)
        return action

    # ------------------------------------------------------------------ observation access
    def _eef(self) -> np.ndarray:
        return np.asarray(self._obs["eef_pos"], dtype=np.float64).copy()

    def _width(self) -> float:
        q = np.asarray(self._obs["gripper_qpos"], dtype=np.float64)
        return float(q[0] - q[1])

    def _pose(self, slot: int) -> np.ndarray:
        return np.asarray(self._obs["object_poses"][slot], dtype=np.float64)

    def _hand_rotation(self) -> np.ndarray:
        # Pitch turns the approach axis from straight down towards world +y's opposite (into a drawer
        # front facing +y); yaw turns the fingers about world z.
        return rot_z(self._yaw) @ rot_x(-self._pitch) @ R_DOWN

    def _current_yaw(self) -> float:
        rot = quat_xyzw_to_mat(np.asarray(self._obs["eef_quat"], dtype=np.float64)) @ R_DOWN.T
        return float(np.arctan2(rot[1, 0], rot[0, 0]))
