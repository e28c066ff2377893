"""AEGIS: a control-barrier-function QP that filters every executed action of another policy.

The wrapped policy (default: the obstacle-blind ``base`` flow policy of the suite) proposes an action; the
filter keeps it unless it would drive the end effector towards the obstacle faster than the barrier
allows, in which case the position part of the action is changed as little as possible.

Geometry (all in the world frame, from the observation only):

- **Obstacle**: the minimum-volume enclosing ellipsoid (Khachiyan, :func:`~detaug_gym.geometry.min_volume_ellipsoid`)
  of ``obstacle_points``. It is fitted once per obstacle shape in the obstacle's own frame (from
  ``obstacle_pose``) and moved with the pose, so a pushed obstacle costs no new fit (the fit lives in the shared
  shape cache of :mod:`~detaug_gym.geometry.obstacle_view`, next to the SDF grids of the same shape). What the
  obstacle stands on (a pedestal or base, ``obstacle_support_points``) gets its own MVEE and barrier row: the
  QP keeps every barrier (option ``support``).
- **End effector**: an ellipsoid fixed to the grip site (``eef_pos`` / ``eef_quat``): semi-axes 0.12 m along
  the finger travel (grip-site x: the palm is ~0.2 m wide), 0.06 m along the palm normal (y) and 0.11 m
  along the tool axis (z), centred 0.056 m from the grip site towards the wrist, so it covers the hand
  body and the fingertips.

Barrier (conservative, smooth almost everywhere, convex in the end-effector centre): with both ellipsoids
written as ``{x : (x - c)^T Q^-1 (x - c) <= 1}``, their Minkowski sum is enclosed by every ellipsoid
``Q_p = (1 + 1/p) Q_obs + (1 + p) Q_ee``, ``p > 0`` (and is the intersection of them all). The two
ellipsoids are disjoint when the centre difference ``d = c_ee - c_obs`` lies outside one of them, so

    h = max_p sqrt(d^T Q_p^-1 d) - 1    (h >= 0  =>  no contact)

with the maximum over a fixed grid of 97 values of ``p`` (log-spaced over [0.01, 100]): each member is
a norm of a linear map of ``d``, so ``h`` is a maximum of convex functions, convex in the end-effector
centre, and its linearisation is a lower bound (see below). Over a dense grid ``h >= 0`` is almost
exactly "the ellipsoids do not overlap" (exact for two spheres of equal radius: ``h = D / (r1 + r2) - 1``);
a single fixed member (e.g. the smallest-trace one) would be a much more conservative test.

Constraint: ``dh/dt >= -alpha h`` in discrete time with ``dt = CONTROL_DT`` (20 Hz). The commanded
end-effector velocity is ``v = POS_SCALE a[:3] / dt`` (OSC_POSE, :func:`~detaug_gym.actions.action_to_goal`:
``goal = eef_pos + POS_SCALE a[:3]``); the commanded rotation ``R' = exp(ROT_SCALE a[3:6]) R`` is kept as
proposed and enters exactly (``h_r``, ``g`` = value and gradient of ``h`` at the rotated pose), the
translation linearly::

    h_r + g . (v dt)  >=  (1 - alpha dt) h

Because ``h`` is convex in the centre, the left side never exceeds the true barrier after the commanded
motion, so an action that satisfies the linear constraint keeps the commanded pose at
``h' >= (1 - alpha dt) h``: never a new violation from a safe pose, and a shrinking violation from an
unsafe one. The QP

    min ||x - a[:3]||^2   s.t.   g . x >= b  (the constraint above),   -1 <= x <= 1

has four constraints (barrier + box), solved with OSQP (one persistent workspace, :class:`BarrierQP`).
An action that already satisfies the constraint passes unchanged (the same array, bit for bit); when the
box leaves no feasible point the action that increases ``h`` the most (``x = sign(g)``) is taken and the
step is flagged.

Per-step diagnostics (:class:`FilterStep` in ``policy.diagnostics``): whether the filter changed the
action, ``h``, the correction size ``||x - a[:3]||`` and whether the QP was feasible.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from detaug_gym.actions import CONTROL_DT, POS_SCALE, action_to_goal
from detaug_gym.geometry.ellipsoid import min_volume_ellipsoid
from detaug_gym.geometry.obstacle_view import obstacle_frame, obstacle_parts, obstacle_shape
from detaug_gym.policies.base import make_policy, policy_class, share_planner
from detaug_gym.policies.options import AegisOptions
from detaug_gym.rotations import quat_xyzw_to_mat

EE_SEMI_AXES = (0.12, 0.06, 0.11)  # m, grip-site frame: finger travel x, palm normal y, tool axis z
EE_OFFSET = 0.056  # m from the grip site towards the wrist (along -z of the grip site)


@dataclass(frozen=True)
class FilterStep:
    """What the filter did to one action.

    Attributes:
        active: the action was changed.
        h: barrier value at the current pose (``inf`` without an obstacle).
        correction: ``||filtered - nominal||`` over the position part (action units).
        feasible: the QP had a solution inside the action box.
    """

    active: bool
    h: float
    correction: float
    feasible: bool = True


@dataclass(frozen=True)
class EndEffectorEllipsoid:
    """The end effector as an ellipsoid fixed to the grip site.

    Attributes:
        semi_axes: ``(3,)`` m along the grip-site axes (x finger travel, y palm normal, z tool axis).
        offset: m from the grip site towards the wrist along the tool axis.
    """

    semi_axes: tuple[float, float, float] = EE_SEMI_AXES
    offset: float = EE_OFFSET

    def placed(self, eef_pos: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Centre ``(3,)`` and covariance form ``Q`` ``(3, 3)`` for a grip site at ``eef_pos`` / ``rotation``."""
        centre = np.asarray(eef_pos, np.float64) - self.offset * rotation[:, 2]
        scaled = rotation * np.asarray(self.semi_axes, np.float64)  # columns: axis * semi-axis
        return centre, scaled @ scaled.T


def _local_ellipsoid(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre ``(3,)`` and covariance form ``Q`` ``(3, 3)`` of the MVEE of ``(N, 3)`` points."""
    fit = min_volume_ellipsoid(points)
    return fit.centre, np.linalg.inv(fit.shape)


MINKOWSKI_P = np.logspace(-2.0, 2.0, 97)  # members of the enclosing family; p = 1 (equal sizes) included


def barrier(ee_centre: np.ndarray, ee_q: np.ndarray, obs_centre: np.ndarray, obs_q: np.ndarray
            ) -> tuple[float, np.ndarray]:
    """``h`` and a (sub)gradient in the end-effector centre (see the module doc).

    ``h = max_p sqrt(d^T Q_p^-1 d) - 1`` over :data:`MINKOWSKI_P` with ``Q_p = (1 + 1/p) Q_obs + (1 + p) Q_ee``.
    Computed in coordinates where ``Q_ee = I`` and ``Q_obs`` is diagonal, so every member costs a few flops.
    """
    chol_inv = np.linalg.inv(np.linalg.cholesky(ee_q))  # maps Q_ee to I
    lam, rot = np.linalg.eigh(chol_inv @ obs_q @ chol_inv.T)
    to_diag = rot.T @ chol_inv  # d -> coordinates where Q_ee = I, Q_obs = diag(lam)
    d = to_diag @ (np.asarray(ee_centre, np.float64) - obs_centre)
    denom = (1.0 + 1.0 / MINKOWSKI_P)[:, None] * lam + (1.0 + MINKOWSKI_P)[:, None]  # (G, 3): Q_p's diagonal
    level = (d * d / denom).sum(axis=1)
    best = int(np.argmax(level))
    scaled = float(np.sqrt(max(level[best], 1e-18)))
    return scaled - 1.0, to_diag.T @ (d / denom[best]) / scaled


class CBFFilter:
    """The CBF-QP safety filter on single OSC_POSE actions.

    Args:
        alpha: class-K gain of ``dh/dt >= -alpha h`` (1/s).
        dt: control period (s); ``alpha * dt`` must lie in (0, 1].
        end_effector: the end-effector ellipsoid.

    Actions are read with the package's OSC_POSE convention (:mod:`detaug_gym.actions`).
    """

    def __init__(self, alpha: float = 10.0, dt: float = CONTROL_DT,
                 end_effector: EndEffectorEllipsoid | None = None, support: bool = True) -> None:
        if not (alpha > 0 and dt > 0 and alpha * dt <= 1.0):
            raise ValueError(f"need alpha > 0, dt > 0 and alpha * dt <= 1, got alpha={alpha}, dt={dt}")
        self.end_effector = end_effector or EndEffectorEllipsoid()
        if len(self.end_effector.semi_axes) != 3 or min(self.end_effector.semi_axes) <= 0:
            raise ValueError(f"end-effector semi-axes must be 3 positive lengths, got {self.end_effector.semi_axes}")
        self.alpha, self.dt, self.support = float(alpha), float(dt), bool(support)
        self._qp = BarrierQP()

    def reset(self) -> None:
        """A fresh QP workspace: OSQP warm-starts each solve from the last one, so a workspace kept from the
        previous episode would make this episode's actions depend (at solver tolerance) on which episode ran
        before it in the process."""
        self._qp = BarrierQP()

    # ------------------------------------------------------------------ obstacle
    def obstacle_ellipsoids(self, obs: Mapping[str, np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """World centre ``(3,)`` and covariance form ``(3, 3)`` of the MVEE of each part of the obstacle view:
        the obstacle, then (with ``support``) what it stands on; empty without an obstacle. Each is fitted once
        per shape in its own frame (the shared shape cache), then posed."""
        parts = obstacle_parts(obs)
        out = []
        for part in parts if self.support else parts[:1]:
            position, rotation = obstacle_frame(obs, part)
            centre, q_local = obstacle_shape(obs, part=part).product("mvee", _local_ellipsoid)
            out.append((rotation @ centre + position, rotation @ q_local @ rotation.T))
        return out

    # ------------------------------------------------------------------ filtering
    def constraint(self, action: np.ndarray, obs: Mapping[str, np.ndarray], obstacle
                   ) -> tuple[float, np.ndarray, float]:
        """``(h, g, b)``: barrier now, and the linear constraint ``g . a[:3] >= b`` on the position part."""
        rotation = quat_xyzw_to_mat(obs["eef_quat"])
        eef = np.asarray(obs["eef_pos"], np.float64)
        h, _ = barrier(*self.end_effector.placed(eef, rotation), *obstacle)
        _, turned = action_to_goal(eef, rotation, action)
        h_turned, grad = barrier(*self.end_effector.placed(eef, turned), *obstacle)
        # h_r + g . (POS_SCALE a) >= (1 - alpha dt) h   <=>   (POS_SCALE g) . a >= (1 - alpha dt) h - h_r
        return h, POS_SCALE * grad, (1.0 - self.alpha * self.dt) * h - h_turned

    def __call__(self, action: np.ndarray, obs: Mapping[str, np.ndarray]) -> tuple[np.ndarray, FilterStep]:
        """The filtered action (the same object when it is already safe) and what was done: one barrier
        constraint per ellipsoid of :meth:`obstacle_ellipsoids`, ``h`` the smallest barrier."""
        obstacles = self.obstacle_ellipsoids(obs)
        if not obstacles:
            return action, FilterStep(False, float("inf"), 0.0)
        rows = [self.constraint(action, obs, obstacle) for obstacle in obstacles]
        h = min(r[0] for r in rows)
        g, b = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
        nominal = np.asarray(action[:3], np.float64)
        if np.all(g @ nominal >= b):
            return action, FilterStep(False, h, 0.0)
        position, feasible = self.solve(nominal, g, b)
        filtered = np.array(action, copy=True)
        filtered[:3] = position
        return filtered, FilterStep(True, h, float(np.linalg.norm(position - nominal)), feasible)

    def solve(self, nominal: np.ndarray, g: np.ndarray, b: np.ndarray | float) -> tuple[np.ndarray, bool]:
        """``argmin ||x - nominal||^2`` s.t. ``G x >= b`` (``g`` ``(3,)`` or ``(M, 3)``, ``b`` scalar or ``(M,)``),
        ``-1 <= x <= 1``, and whether it was feasible. Infeasible: increase ``h`` as fast as allowed, up the
        gradient of the row that is violated most."""
        g, b = np.atleast_2d(np.asarray(g, np.float64)), np.atleast_1d(np.asarray(b, np.float64))
        reach = np.abs(g).sum(axis=1) - b  # < 0: the box holds no x meeting that row
        if reach.min() < 0.0:
            return _escape(nominal, g[int(np.argmin(reach))]), False
        x = self._qp(nominal, g, b)
        if x is None:
            return _escape(nominal, g[int(np.argmax(b - g @ nominal))]), False
        # OSQP meets constraints to ~1e-9; nudge along the worst row (staying in the box) until G x >= b exactly.
        for _ in range(3 * len(b)):
            gaps = b - g @ x
            row = int(np.argmax(gaps))
            if gaps[row] <= 0.0:
                break
            free = (np.abs(x) < 1.0) | (np.sign(g[row]) != np.sign(x))
            step = np.where(free, g[row], 0.0)
            x = np.clip(x + (gaps[row] + 1e-12) * step / max(step @ g[row], 1e-18), -1.0, 1.0)
        return x, True


def _escape(nominal: np.ndarray, g: np.ndarray) -> np.ndarray:
    """The infeasible case's action: full speed up the barrier's gradient ``g`` (the nominal where a component of
    ``g`` is 0). At the ellipsoid's centre ``g`` vanishes and no direction is better than another: then straight
    up, the one direction that cannot run into the table."""
    if not np.any(g != 0.0):
        return np.array([0.0, 0.0, 1.0])
    return np.where(g != 0.0, np.sign(g), np.clip(nominal, -1.0, 1.0))


class BarrierQP:
    """``min ||x - nominal||^2`` s.t. ``G x >= b`` (``M`` barrier rows), ``-1 <= x <= 1``, with one persistent
    OSQP workspace per row count.

    For a given ``M`` the problem's sparsity never changes (3 variables; rows: the barriers, then the box), so
    OSQP is set up once and only ``q``, the barrier rows and their bounds are updated per solve: ~0.3 ms
    instead of ~3 ms for a fresh setup (what ``qpsolvers.solve_qp`` does on every call).
    """

    def __init__(self, eps: float = 1e-9) -> None:
        try:
            import osqp
        except ImportError as err:  # optional dependency: say how to get it
            raise ImportError("AEGIS solves its QP with OSQP: pip install osqp") from err
        self._osqp, self._eps = osqp, eps
        self._v1 = int(osqp.__version__.split(".")[0]) >= 1
        self._solvers: dict[int, object] = {}

    def _solver(self, rows: int):
        if rows not in self._solvers:
            from scipy import sparse

            polish = "polishing" if self._v1 else "polish"  # renamed in OSQP 1.0
            # A ((M + 3) x 3) in CSC with every barrier entry kept structurally, even when 0; column j holds
            # the M barrier rows, then box row M + j.
            indices = np.concatenate([np.r_[np.arange(rows), rows + j] for j in range(3)])
            a = sparse.csc_matrix((np.ones(3 * (rows + 1)), indices, (rows + 1) * np.arange(4)),
                                  shape=(rows + 3, 3))
            solver = self._osqp.OSQP()
            solver.setup(P=sparse.eye(3, format="csc"), q=np.zeros(3), A=a, l=np.r_[np.zeros(rows), -np.ones(3)],
                         u=np.r_[np.full(rows, np.inf), np.ones(3)], eps_abs=self._eps, eps_rel=self._eps,
                         max_iter=20_000, verbose=False, **{polish: True})
            self._solvers[rows] = solver
        return self._solvers[rows]

    def __call__(self, nominal: np.ndarray, g: np.ndarray, b: np.ndarray | float) -> np.ndarray | None:
        """The minimiser, or ``None`` when OSQP reports no solution (``g`` ``(3,)`` or ``(M, 3)``)."""
        g, b = np.atleast_2d(np.asarray(g, np.float64)), np.atleast_1d(np.asarray(b, np.float64))
        solver = self._solver(len(b))
        solver.update(q=-nominal, l=np.r_[b, -np.ones(3)], Ax=np.column_stack([g.T, np.ones(3)]).ravel())
        result = solver.solve(raise_error=False) if self._v1 else solver.solve()
        status = str(result.info.status).lower()
        if not status.startswith("solved") or result.x is None or not np.all(np.isfinite(result.x)):
            return None
        return np.asarray(result.x, np.float64)


class AegisPolicy:
    """Any registered policy behind the AEGIS CBF-QP filter.

    Args:
        suite: passed to the wrapped policy (zoo folder of flow policies).
        base: registered name of the wrapped policy (default ``"base"``).
        alpha: barrier gain (1/s); dt: control period (s).
        ee_semi_axes: end-effector semi-axes (m) along the grip-site x, y, z axes.
        ee_offset: end-effector centre, m from the grip site towards the wrist.
        support: also keep clear of what the obstacle stands on (its own ellipsoid and barrier).
        **base_options: options of the wrapped policy (``checkpoint``, ``action_steps``, ``seed``, ...).

    AEGIS's own options, their types and ranges are :class:`~detaug_gym.policies.options.AegisOptions`.
    """

    @classmethod
    def checkpoint_dirs(cls, suite: str = "spatial", base: str = "base", **base_options) -> list:
        """The checkpoint folders of the wrapped policy."""
        dirs = getattr(policy_class(base), "checkpoint_dirs", None)
        return dirs(suite, **base_options) if callable(dirs) else []

    def __init__(self, suite: str = "spatial", base: str = "base", alpha: float = 10.0, dt: float = CONTROL_DT,
                 ee_semi_axes: tuple[float, float, float] = EE_SEMI_AXES, ee_offset: float = EE_OFFSET,
                 support: bool = True, **base_options) -> None:
        opts = AegisOptions(suite=suite, base=base, alpha=alpha, dt=dt, ee_semi_axes=ee_semi_axes,
                            ee_offset=ee_offset, support=support)
        self.filter = CBFFilter(opts.alpha, opts.dt, EndEffectorEllipsoid(opts.ee_semi_axes, opts.ee_offset),
                                opts.support)
        self.policy = make_policy(opts.base, suite=opts.suite, **base_options)
        self.diagnostics: list[FilterStep] = []

    def reset(self, seed: int | None = None, context=None) -> None:
        from detaug_gym.rollout import reset_policy

        reset_policy(self.policy, seed, context)
        self.filter.reset()
        self.diagnostics = []

    def share_planner(self, batcher) -> None:
        """Hand a shared plan batcher to the wrapped policy (when it plans with a network)."""
        share_planner(self.policy, batcher)

    def episode_summary(self) -> dict:
        """Filtered steps, how many the filter changed (interventions), infeasible QPs, and the wrapped
        policy's own summary."""
        inner = getattr(self.policy, "episode_summary", None)
        return {"steps": len(self.diagnostics), "interventions": sum(d.active for d in self.diagnostics),
                "infeasible": sum(not d.feasible for d in self.diagnostics),
                **({"base": inner()} if callable(inner) else {})}

    def belief(self, obs: Mapping[str, np.ndarray] | None = None) -> dict:
        """The wrapped policy's belief (its plan) and whether the filter changed the last action."""
        inner = getattr(self.policy, "belief", None)
        belief = dict(inner(obs)) if callable(inner) else {}
        if self.diagnostics:
            belief["filter_active"] = self.diagnostics[-1].active
        return belief

    def act(self, obs: Mapping[str, np.ndarray]) -> np.ndarray:
        action, step = self.filter(self.policy.act(obs), obs)
        self.diagnostics.append(step)
        return action
