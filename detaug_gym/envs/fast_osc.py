"""robosuite 1.4's OSC_POSE control step, computed straight from MuJoCo's arrays.

Stock robosuite spends most of a 20 Hz control step outside the physics: at every 2 ms substep it runs
``mj_forward`` twice (once in ``env.step``, once more in ``Controller.update``), builds the Jacobians and
the full mass matrix through Python wrappers, inverts three operational-space matrices by SVD and updates
every observable. :class:`FastStepper` reproduces the same control law and the same physics with

- one pass of MuJoCo's pipeline per substep: ``mj_step1`` (positions, velocities, mass matrix, bias
  forces), the controller, then ``mj_step2`` (actuation, constraints, Euler integration). With the Euler
  integrator this is exactly what ``mj_forward`` + ``mj_step`` compute, without the repeated passes;
- the operational-space algebra rewritten with small linear solves instead of ``inv``/``pinv`` (equal in
  exact arithmetic for a non-singular arm; the tests bound the difference);
- no observables, reward or observation dictionaries (our env builds its own observation).

What is kept bit for bit from robosuite: the goal update (``set_goal``: input clipping, output scaling,
the goal orientation only changes when a rotation component is non-zero, and the rotation is built with
robosuite's own ``axisangle2quat``/``quat2mat``, which round through float32), the end-effector velocity
``J @ qvel``, gravity compensation from ``qfrc_bias``, clipping to the actuator ranges, and the Panda
gripper's stateful command ramp (0.01 per substep towards open or closed).
"""

from __future__ import annotations

import mujoco
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
        self.qpos_index = np.asarray(controller.qpos_index)
        self.qvel_index = np.asarray(controller.qvel_index)
        self.arm_actuators = np.asarray(self.robot._ref_joint_actuator_indexes)
        # Views instead of fancy indexing when the arm's dofs are contiguous (always so for robosuite arms).
        self._qvel_slice = _as_slice(self.qvel_index)
        self._qpos_slice = _as_slice(self.qpos_index)
        self._act_slice = _as_slice(self.arm_actuators)
        self.control_dim = controller.control_dim
        self.input_min, self.input_max = controller.input_min, controller.input_max
        self.output_min, self.output_max = controller.output_min, controller.output_max
        # Same expressions as Controller.scale_action, so the scaled deltas are identical.
        self.action_scale = abs(self.output_max - self.output_min) / abs(self.input_max - self.input_min)
        self.action_output_transform = (self.output_max + self.output_min) / 2.0
        self.action_input_transform = (self.input_max + self.input_min) / 2.0
        self.kp = np.array(controller.kp, dtype=np.float64)
        self.kd = np.array(controller.kd, dtype=np.float64)
        self.torque_low, self.torque_high = (np.array(x) for x in self.robot.torque_limits)
        gripper = self.robot.gripper
        self.gripper = gripper
        self.gripper_actuators = np.array([m.actuator(name).id for name in gripper.actuators])
        ctrl_range = m.actuator_ctrlrange[self.gripper_actuators]
        self.gripper_bias = 0.5 * (ctrl_range[:, 1] + ctrl_range[:, 0])
        self.gripper_weight = 0.5 * (ctrl_range[:, 1] - ctrl_range[:, 0])
        self.gripper_speed = gripper.speed
        self.substeps = int(self.sim_env.control_timestep / self.sim_env.model_timestep)
        nv = m.nv
        self._jacp = np.zeros((3, nv))
        self._jacr = np.zeros((3, nv))
        self._mass_full = np.zeros((nv, nv))
        self._jac = np.zeros((6, len(self.qvel_index)))
        self._eye = np.eye(len(self.qvel_index))
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
        self.gripper_action = np.array(self.gripper.current_action, dtype=np.float64)
        self.tracked_states = list(getattr(self.sim_env, "tracking_object_states_change", ()))

    def step(self, action: np.ndarray) -> None:
        """One control step: ``substeps`` x (kinematics, OSC torques, gripper ramp, dynamics + integration)."""
        m, d = self.model, self.data
        arm_action = action[: self.control_dim]
        gripper_sign = np.sign(action[self.control_dim:])
        ctrl = d.ctrl
        for substep in range(self.substeps):
            mujoco.mj_step1(m, d)
            if substep == 0:
                self.set_goal(arm_action)
            torques = self.arm_torques()
            ctrl[self._act_slice] = np.clip(torques, self.torque_low, self.torque_high)
            self.gripper_action = np.clip(
                self.gripper_action + PANDA_GRIPPER_RAMP * self.gripper_speed * gripper_sign, -1.0, 1.0)
            ctrl[self.gripper_actuators] = self.gripper_bias + self.gripper_weight * self.gripper_action
            mujoco.mj_step2(m, d)
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

        robosuite computes ``tau = J^T [L_pos F; L_ori T] + bias + N^T M x`` with ``L = (J M^-1 J^T)^-1``
        (per block, by pseudo-inverse), ``N = I - M^-1 J^T L_full J`` and ``x = kp_null (q0 - q) -
        kv_null qdot``. Since ``N^T M x = M x - J^T L_full J x``, everything reduces to one Cholesky solve
        with ``M`` and three small solves, with no explicit inverse.
        """
        m, d = self.model, self.data
        site, dofs = self.site, self._qvel_slice
        jacp, jacr = self._jacp, self._jacr
        mujoco.mj_jacSite(m, d, jacp, jacr, site)
        mujoco.mj_fullM(m, d, self._mass_full)
        mass = self._mass_full[dofs, dofs]
        jac = self._jac
        jac[:3] = jacp[:, dofs]
        jac[3:] = jacr[:, dofs]
        qvel = d.qvel
        # robosuite: ee velocity = full-width Jacobian @ full qvel (same product, same rounding)
        ee_vel_pos = np.dot(jacp, qvel)
        ee_vel_ori = np.dot(jacr, qvel)
        ee_pos = d.site_xpos[site]
        ee_ori = d.site_xmat[site].reshape(3, 3)
        kp, kd = self.kp, self.kd
        force = np.multiply(self.goal_pos - ee_pos, kp[:3]) + np.multiply(-ee_vel_pos, kd[:3])
        moment = np.multiply(_orientation_error(self.goal_ori, ee_ori), kp[3:]) + np.multiply(-ee_vel_ori, kd[3:])

        chol = np.linalg.cholesky(mass)
        minv_jt = _cho_solve(chol, jac.T)  # M^-1 J^T, (7, 6)
        lam_inv = jac @ minv_jt  # J M^-1 J^T, (6, 6)
        posture = NULLSPACE_KP * (self.initial_joint - d.qpos[self._qpos_slice]) \
            - 2.0 * np.sqrt(NULLSPACE_KP) * qvel[dofs]
        rhs = np.empty((6, 3))
        rhs[:, 0] = jac @ posture
        rhs[:3, 1], rhs[3:, 1] = force, 0.0
        rhs[:3, 2], rhs[3:, 2] = 0.0, moment
        sol = np.linalg.solve(lam_inv, rhs[:, :1])[:, 0]  # L_full J x
        wrench = np.empty(6)
        wrench[:3] = np.linalg.solve(lam_inv[:3, :3], force)
        wrench[3:] = np.linalg.solve(lam_inv[3:, 3:], moment)
        return jac.T @ (wrench - sol) + d.qfrc_bias[dofs] + mass @ posture

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


def _orientation_error(desired: np.ndarray, current: np.ndarray) -> np.ndarray:
    """robosuite's ``orientation_error``: half the sum of column cross products (axis-angle for small errors)."""
    return 0.5 * (np.cross(current[:, 0], desired[:, 0]) + np.cross(current[:, 1], desired[:, 1])
                  + np.cross(current[:, 2], desired[:, 2]))


def _cho_solve(chol: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``(L L^T) x = rhs`` for a lower-triangular Cholesky factor ``L``."""
    return np.linalg.solve(chol.T, np.linalg.solve(chol, rhs))


def _as_slice(index: np.ndarray):
    """A slice equivalent to a contiguous ascending index array (a view), else the array itself."""
    index = np.asarray(index)
    if index.size and np.array_equal(index, np.arange(index[0], index[0] + index.size)):
        return slice(int(index[0]), int(index[0]) + index.size)
    return index


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
