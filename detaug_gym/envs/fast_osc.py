"""robosuite 1.4's OSC_POSE control step, computed straight from MuJoCo's arrays.

Stock robosuite spends most of a 20 Hz control step outside the physics: at every 2 ms substep it runs
``mj_forward`` twice (once in ``env.step``, once more in ``Controller.update``), builds the Jacobians and
the full mass matrix through Python wrappers, inverts three operational-space matrices by SVD and updates
every observable. :class:`FastStepper` reproduces the same control law and the same physics with

- one pass of MuJoCo's pipeline per substep: ``mj_step1`` (positions, velocities, mass matrix, bias
  forces), the controller, then ``mj_step2`` (actuation, constraints, Euler integration). With the Euler
  integrator this is exactly what ``mj_forward`` + ``mj_step`` compute, without the repeated passes;
- the whole control law of a substep in one compiled (numba) call, with the operational-space algebra
  written as a Cholesky solve with the mass matrix and three small SPD solves instead of robosuite's
  ``inv`` + three ``pinv`` (equal in exact arithmetic for a non-singular arm; ``pinv`` stays the fallback);
- no observables, reward or observation dictionaries (our env builds its own observation).

Only the compiled algebra changes rounding: torques agree with robosuite's to ~5e-15 relative and
200-step random-action trajectories to ~1e-14 (worst seen 2e-8, after 120 steps); see
``tests/test_fast_control.py``. Kept bit for bit: the goal update (``set_goal``: input clipping, output
scaling, the goal orientation only changes when a rotation component is non-zero, the rotation built with
robosuite's own ``axisangle2quat``/``quat2mat``, which round through float32), clipping to the actuator
ranges, and the Panda gripper's stateful command ramp (0.01 per substep towards open or closed).
"""

from __future__ import annotations

import mujoco
import numba
import numpy as np

NULLSPACE_KP = 10.0  # robosuite's ``nullspace_torques`` default gain; kv = 2 sqrt(kp)
PANDA_GRIPPER_RAMP = np.array([-1.0, 1.0])  # PandaGripper.format_action: finger 1 opens down, finger 2 up


class FastStepper:
    """One 20 Hz OSC_POSE control step of a robosuite single-arm Panda scene, without robosuite's loop.

    Reads gains, limits, indices and the nullspace posture from the robot's robosuite controller, so it
    follows whatever LIBERO configured. Raises ``ValueError`` at construction for configurations it does
    not reproduce (other controllers, variable impedance, interpolators, goal limits, other grippers,
    non-Euler integrators); use ``controller="stock"`` for those.
    """

    def __init__(self, scene) -> None:
        self.sim_env = scene.sim_env
        self.robot = scene.robot
        self.model: mujoco.MjModel = scene.model
        self.data: mujoco.MjData = scene.data
        controller = self.robot.controller
        _check_supported(self.robot, controller, self.model)
        m = self.model
        self.site = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, controller.eef_name)
        self.qpos_index = np.asarray(controller.qpos_index, dtype=np.int64)
        self.qvel_index = np.asarray(controller.qvel_index, dtype=np.int64)
        self.arm_actuators = np.asarray(self.robot._ref_joint_actuator_indexes, dtype=np.int64)
        self.control_dim = controller.control_dim
        self.input_min, self.input_max = controller.input_min, controller.input_max
        self.output_min, self.output_max = controller.output_min, controller.output_max
        # Same expressions as Controller.scale_action, so the scaled deltas are identical.
        self.action_scale = abs(self.output_max - self.output_min) / abs(self.input_max - self.input_min)
        self.action_output_transform = (self.output_max + self.output_min) / 2.0
        self.action_input_transform = (self.input_max + self.input_min) / 2.0
        self._gains = np.array([controller.kp, controller.kd], dtype=np.float64)  # (2, 6): kp, kd
        self._torque_limits = np.array(self.robot.torque_limits, dtype=np.float64)  # (2, n): low, high
        self.gripper = self.robot.gripper
        self.gripper_actuators = np.array([m.actuator(name).id for name in self.gripper.actuators], dtype=np.int64)
        ctrl_range = m.actuator_ctrlrange[self.gripper_actuators]
        # robosuite's grip_action: ctrl = bias + weight * ramped action
        self._gripper_map = np.array([0.5 * (ctrl_range[:, 1] + ctrl_range[:, 0]),
                                      0.5 * (ctrl_range[:, 1] - ctrl_range[:, 0])])
        self.gripper_speed = self.gripper.speed
        self._gripper_delta = np.zeros(len(self.gripper_actuators))
        self.substeps = int(self.sim_env.control_timestep / self.sim_env.model_timestep)
        # MjData's arrays are views on memory that lives as long as ``data``; fetch them once.
        d = self.data
        self._qpos, self._qvel, self._qfrc_bias, self._ctrl = d.qpos, d.qvel, d.qfrc_bias, d.ctrl
        self._ee_pos, self._ee_xmat = d.site_xpos[self.site], d.site_xmat[self.site]
        nv = m.nv
        self._jacp = np.zeros((3, nv))
        self._jacr = np.zeros((3, nv))
        self._mass_full = np.zeros((nv, nv))
        self._torques = np.zeros(len(self.qvel_index))
        self._scratch = np.zeros(6 + len(self.qvel_index))  # task-space command, posture term
        self.reset()

    # ------------------------------------------------------------------ stepper protocol
    def reset(self) -> None:
        """Start an episode from the state now in ``data`` (loaded and forwarded by the env).

        The goal orientation restarts at the controller's initial end-effector orientation (the arm's
        ``init_qpos``), which is what a freshly reset LIBERO env holds: a step whose rotation delta is zero
        keeps the previous goal orientation, so without this the first steps of an episode would depend
        on the previous episode.
        """
        controller = self.robot.controller
        self.sim_env.timestep = 0
        self.sim_env.done = False
        self.initial_joint = np.array(controller.initial_joint, dtype=np.float64)
        self.goal_ori = np.array(controller.initial_ee_ori_mat, dtype=np.float64)
        self.goal_pos = np.array(self.data.site_xpos[self.site])
        ramp = np.asarray(self.gripper.current_action, dtype=np.float64)
        self.gripper_action = np.array(np.broadcast_to(ramp, self._gripper_delta.shape))
        self.tracked_states = list(getattr(self.sim_env, "tracking_object_states_change", ()))

    def step(self, action: np.ndarray) -> None:
        """One control step: ``substeps`` x (kinematics, OSC torques, gripper ramp, dynamics + integration)."""
        m, d = self.model, self.data
        step1, step2, controls = mujoco.mj_step1, mujoco.mj_step2, self._substep_controls
        self._gripper_delta[:] = PANDA_GRIPPER_RAMP * self.gripper_speed * np.sign(action[self.control_dim:])
        step1(m, d)
        self.set_goal(action[: self.control_dim])  # the goal is set once per control step, from this state
        controls()
        step2(m, d)
        for _ in range(self.substeps - 1):
            step1(m, d)
            controls()
            step2(m, d)
        self._after_step()

    # ------------------------------------------------------------------ control law
    def set_goal(self, arm_action: np.ndarray) -> None:
        """robosuite's ``OperationalSpaceController.set_goal`` for fixed impedance, delta pose control.

        Needs the kinematics of the current state (after ``mj_step1`` or ``mj_forward``).
        """
        from robosuite.utils.transform_utils import axisangle2quat, quat2mat

        d = self.data
        clipped = np.clip(arm_action, self.input_min, self.input_max)
        delta = (clipped - self.action_input_transform) * self.action_scale + self.action_output_transform
        ee_ori = d.site_xmat[self.site].reshape(3, 3)
        if np.any(delta[3:] != 0.0):  # robosuite: any(not math.isclose(x, 0.0)), i.e. exactly non-zero
            self.goal_ori = np.dot(quat2mat(axisangle2quat(delta[3:])), ee_ori)
        self.goal_pos = d.site_xpos[self.site] + delta[:3]

    def arm_torques(self) -> np.ndarray:
        """Unclipped OSC_POSE joint torques for the current goal and the kinematics now in ``data``.

        Same quantity as robosuite's ``OperationalSpaceController.run_controller()``; touches no control.
        """
        self._jacobian_and_mass()
        torques = np.zeros(len(self.qvel_index))
        if not _osc_torques(self._jacp, self._jacr, self._mass_full, self._qpos, self._qvel, self._qfrc_bias,
                            self._ee_pos, self._ee_xmat, self.qpos_index, self.qvel_index, self.goal_pos,
                            self.goal_ori, self._gains, self.initial_joint, torques, self._scratch):
            torques = self._pseudo_inverse_torques()
        return torques

    def _jacobian_and_mass(self) -> None:
        mujoco.mj_jacSite(self.model, self.data, self._jacp, self._jacr, self.site)
        mujoco.mj_fullM(self.model, self.data, self._mass_full)

    def _substep_controls(self) -> None:
        """Arm torques (clipped) and the gripper ramp into ``ctrl``, as robosuite's ``robot.control`` does."""
        self._jacobian_and_mass()
        if not _osc_substep(self._jacp, self._jacr, self._mass_full, self._qpos, self._qvel, self._qfrc_bias,
                            self._ee_pos, self._ee_xmat, self.qpos_index, self.qvel_index, self.goal_pos,
                            self.goal_ori, self._gains, self.initial_joint, self._torques, self._scratch,
                            self._torque_limits, self.arm_actuators, self.gripper_action, self._gripper_delta,
                            self._gripper_map, self.gripper_actuators, self._ctrl):
            _apply_controls(self._pseudo_inverse_torques(), self._torque_limits, self.arm_actuators,
                            self.gripper_action, self._gripper_delta, self._gripper_map, self.gripper_actuators,
                            self._ctrl)

    def _pseudo_inverse_torques(self) -> np.ndarray:
        """robosuite's own route, explicit ``inv`` and ``pinv``, for an arm at a singularity (rare, so numpy).

        Uses the task-space command and posture term the kernel left in ``_scratch``.
        """
        dofs = self.qvel_index
        mass = self._mass_full[np.ix_(dofs, dofs)]
        jac = np.vstack([self._jacp[:, dofs], self._jacr[:, dofs]])
        command, posture = self._scratch[:6], self._scratch[6:]
        minv = np.linalg.inv(mass)
        lam_full = np.linalg.pinv(jac @ minv @ jac.T)
        lam_pos = np.linalg.pinv(jac[:3] @ minv @ jac[:3].T)
        lam_ori = np.linalg.pinv(jac[3:] @ minv @ jac[3:].T)
        nullspace = np.eye(len(dofs)) - minv @ jac.T @ lam_full @ jac
        wrench = np.concatenate([lam_pos @ command[:3], lam_ori @ command[3:]])
        return jac.T @ wrench + self._qfrc_bias[dofs] + nullspace.T @ (mass @ posture)

    # ------------------------------------------------------------------ bookkeeping
    def _after_step(self) -> None:
        """What robosuite's ``env.step`` does after the substeps that matters to later steps or to LIBERO."""
        env = self.sim_env
        env.timestep += 1
        env.cur_time += env.control_timestep
        # LIBERO's _post_process: objects that change visually (e.g. a stove turning on) update their state.
        for object_state in self.tracked_states:
            object_state.update_state()
        # Keep robosuite's own view consistent, so switching to its step or inspecting it stays valid.
        self.gripper.current_action = self.gripper_action.copy()
        controller = self.robot.controller
        controller.goal_pos = self.goal_pos.copy()
        controller.goal_ori = self.goal_ori.copy()


# ---------------------------------------------------------------------- numba kernels
# One call per substep instead of ~40 small numpy calls: at 7 x 7 the numpy call overhead, not the
# arithmetic, is what costs (about 0.4 ms per substep in numpy vs tens of microseconds here). Plain loops,
# no numba BLAS/LAPACK bindings: those would add ~10 s to the one-off compile.


@numba.njit(cache=True)
def _osc_torques(jacp, jacr, mass_full, qpos, qvel, qfrc_bias, ee_pos, ee_xmat, qpos_index, qvel_index,
                 goal_pos, goal_ori, gains, initial_joint, torques, scratch):
    """robosuite's ``run_controller`` (fixed impedance, uncoupled pos/ori, nullspace posture), into ``torques``.

    ``tau = J^T [L_pos F; L_ori T] + bias + N^T M x`` with ``L = (J M^-1 J^T)^-1`` (per block),
    ``N = I - M^-1 J^T L_full J`` and ``x = kp_null (q0 - q) - kv_null qdot``. As ``N^T M x = M x -
    J^T L_full J x``, it needs one Cholesky solve with ``M`` and three small ones; robosuite's explicit
    ``inv``/``pinv`` agree with these to rounding for a non-singular arm.

    Writes the task-space command ``[F, T]`` and ``x`` to ``scratch[:6]``, ``scratch[6:]`` first. Returns
    False, with ``torques`` untouched, when a matrix is not numerically positive definite (a singular arm);
    the caller then takes robosuite's pseudo-inverse route.
    """
    n = qvel_index.shape[0]
    jac = np.empty((6, n))
    mass = np.empty((n, n))
    for j in range(n):
        dof = qvel_index[j]
        for r in range(3):
            jac[r, j] = jacp[r, dof]
            jac[3 + r, j] = jacr[r, dof]
        for k in range(n):
            mass[j, k] = mass_full[dof, qvel_index[k]]
    _task_space_command(jacp, jacr, qpos, qvel, ee_pos, ee_xmat, qpos_index, qvel_index, goal_pos, goal_ori,
                        gains, initial_joint, scratch)
    posture = scratch[6:]

    minv_jt = jac.T.copy()  # becomes M^-1 J^T, (n, 6)
    if not _cholesky_solve(mass, minv_jt):
        return False
    lam_inv = np.zeros((6, 6))  # J M^-1 J^T
    for r in range(6):
        for c in range(6):
            for k in range(n):
                lam_inv[r, c] += jac[r, k] * minv_jt[k, c]
    pos_part = scratch[:3].copy().reshape(3, 1)
    ori_part = scratch[3:6].copy().reshape(3, 1)
    projected = np.zeros((6, 1))  # J x, becomes L_full J x
    for r in range(6):
        for k in range(n):
            projected[r, 0] += jac[r, k] * posture[k]
    if not (_cholesky_solve(lam_inv[:3, :3].copy(), pos_part) and _cholesky_solve(lam_inv[3:, 3:].copy(), ori_part)
            and _cholesky_solve(lam_inv, projected)):
        return False
    wrench = np.empty(6)  # [L_pos F; L_ori T] - L_full J x
    for r in range(3):
        wrench[r] = pos_part[r, 0] - projected[r, 0]
        wrench[3 + r] = ori_part[r, 0] - projected[3 + r, 0]
    for j in range(n):
        acc = 0.0
        for r in range(6):
            acc += jac[r, j] * wrench[r]
        mx = 0.0
        for k in range(n):
            mx += mass[j, k] * posture[k]
        torques[j] = acc + qfrc_bias[qvel_index[j]] + mx
    return True


@numba.njit(cache=True)
def _task_space_command(jacp, jacr, qpos, qvel, ee_pos, ee_xmat, qpos_index, qvel_index, goal_pos, goal_ori,
                        gains, initial_joint, out):
    """``out[:6]``: the PD wrench command ``[F, T]`` of robosuite's OSC; ``out[6:]``: the posture term ``x``."""
    nv = qvel.shape[0]
    # end-effector twist from the full-width Jacobian, as robosuite's get_site_xvel{p,r}
    twist = np.zeros(6)
    for r in range(3):
        for k in range(nv):
            twist[r] += jacp[r, k] * qvel[k]
            twist[3 + r] += jacr[r, k] * qvel[k]
    # orientation error: 0.5 * sum_i current[:, i] x desired[:, i]  (robosuite's orientation_error)
    ori_err = np.zeros(3)
    for i in range(3):
        c0, c1, c2 = ee_xmat[i], ee_xmat[3 + i], ee_xmat[6 + i]
        d0, d1, d2 = goal_ori[0, i], goal_ori[1, i], goal_ori[2, i]
        ori_err[0] += c1 * d2 - c2 * d1
        ori_err[1] += c2 * d0 - c0 * d2
        ori_err[2] += c0 * d1 - c1 * d0
    for r in range(3):
        out[r] = (goal_pos[r] - ee_pos[r]) * gains[0, r] + (-twist[r]) * gains[1, r]
        out[3 + r] = (0.5 * ori_err[r]) * gains[0, 3 + r] + (-twist[3 + r]) * gains[1, 3 + r]
    kv_null = np.sqrt(NULLSPACE_KP) * 2.0
    for j in range(qvel_index.shape[0]):
        out[6 + j] = NULLSPACE_KP * (initial_joint[j] - qpos[qpos_index[j]]) - kv_null * qvel[qvel_index[j]]


@numba.njit(cache=True)
def _cholesky_solve(a, b):
    """Overwrite ``b`` with ``a^-1 b`` for symmetric positive-definite ``a``; False (``b`` unusable) if it is not."""
    n = a.shape[0]
    low = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            acc = a[i, j]
            for k in range(j):
                acc -= low[i, k] * low[j, k]
            if i == j:
                if not acc > 1e-300:
                    return False
                low[i, i] = np.sqrt(acc)
            else:
                low[i, j] = acc / low[j, j]
    for c in range(b.shape[1]):
        for i in range(n):  # L y = b
            acc = b[i, c]
            for k in range(i):
                acc -= low[i, k] * b[k, c]
            b[i, c] = acc / low[i, i]
        for i in range(n - 1, -1, -1):  # L^T x = y
            acc = b[i, c]
            for k in range(i + 1, n):
                acc -= low[k, i] * b[k, c]
            b[i, c] = acc / low[i, i]
    return True


@numba.njit(cache=True)
def _apply_controls(torques, torque_limits, arm_actuators, gripper_action, gripper_delta, gripper_map,
                    gripper_actuators, ctrl):
    """The tail of robosuite's ``robot.control``: clipped arm torques and the stateful gripper ramp into ``ctrl``."""
    for j in range(arm_actuators.shape[0]):
        ctrl[arm_actuators[j]] = min(max(torques[j], torque_limits[0, j]), torque_limits[1, j])
    for g in range(gripper_actuators.shape[0]):
        gripper_action[g] = min(max(gripper_action[g] + gripper_delta[g], -1.0), 1.0)
        ctrl[gripper_actuators[g]] = gripper_map[0, g] + gripper_map[1, g] * gripper_action[g]


@numba.njit(cache=True)
def _osc_substep(jacp, jacr, mass_full, qpos, qvel, qfrc_bias, ee_pos, ee_xmat, qpos_index, qvel_index, goal_pos,
                 goal_ori, gains, initial_joint, torques, scratch, torque_limits, arm_actuators, gripper_action,
                 gripper_delta, gripper_map, gripper_actuators, ctrl):
    """One substep of robosuite's ``robot.control`` in one call; False (nothing written) on a singular arm."""
    if not _osc_torques(jacp, jacr, mass_full, qpos, qvel, qfrc_bias, ee_pos, ee_xmat, qpos_index, qvel_index,
                        goal_pos, goal_ori, gains, initial_joint, torques, scratch):
        return False
    _apply_controls(torques, torque_limits, arm_actuators, gripper_action, gripper_delta, gripper_map,
                    gripper_actuators, ctrl)
    return True


def _check_supported(robot, controller, model: mujoco.MjModel) -> None:
    from robosuite.controllers.osc import OperationalSpaceController
    from robosuite.models.grippers.panda_gripper import PandaGripper

    problems = []
    if not isinstance(controller, OperationalSpaceController):
        problems.append(f"controller is {type(controller).__name__}, not OSC")
    else:
        if not (controller.use_ori and controller.use_delta):
            problems.append("only delta OSC_POSE (position and orientation) is reproduced")
        if controller.impedance_mode != "fixed":
            problems.append(f"impedance_mode {controller.impedance_mode!r} (only 'fixed')")
        if controller.interpolator_pos is not None or controller.interpolator_ori is not None:
            problems.append("interpolators are not reproduced")
        if controller.position_limits is not None or controller.orientation_limits is not None:
            problems.append("goal position/orientation limits are not reproduced")
        if not controller.uncoupling:
            problems.append("only uncouple_pos_ori=True is reproduced")
    if type(robot.gripper) is not PandaGripper:
        problems.append(f"gripper is {type(robot.gripper).__name__}, not PandaGripper")
    if model.opt.integrator != mujoco.mjtIntegrator.mjINT_EULER:
        problems.append("mj_step1/mj_step2 match mj_step only for the Euler integrator")
    if problems:
        raise ValueError("the fast controller cannot reproduce this configuration (use controller='stock'): "
                         + "; ".join(problems))
