"""Controllers that make the grasp site track a Cartesian target, for the arms and the hand.

* :class:`PandaIK` — mink differential IK on a robot-only copy of the model (so the QP never sees the
  objects' free joints): a frame task on the grasp site (position + top-down orientation), a light
  posture task for the null space, configuration and velocity limits. Its joint velocities are
  integrated into the joint position actuators' set-points.
* :class:`SawyerMocap` — moves the mocap body welded to the Sawyer's hand, with a bounded speed.
* :class:`HandMocap` — the same for the human hand (:mod:`studio.sim.hand`), whose mocap body is welded to the
  hand body on its slide joints.

Both bound how fast the target may move, so a target dragged far away, out of reach or into the table
makes the arm move there at a safe speed and stop at the closest reachable pose, never a NaN.
"""

from __future__ import annotations

import mink
import mujoco
import numpy as np

from studio.sim import hand, robots
from studio.sim.scenes import build_robot_model

#: Largest grasp-site speed a controller will command, m/s.
MAX_EE_SPEED = 0.6
#: Largest joint speed of the Panda's IK, rad/s.
MAX_JOINT_SPEED = 2.0


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    return q


# Sawyer hand orientation: its gripper axis (hand x) down, pads closing along world y like the Panda's.
_SAWYER_QUAT = _quat_from_matrix(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]))


def _rate_limit(current: np.ndarray, target: np.ndarray, max_step: float) -> np.ndarray:
    delta = target - current
    n = float(np.linalg.norm(delta))
    return target if n <= max_step else current + delta * (max_step / n)


class PandaIK:
    """Differential IK for the Panda; writes joint set-points into ``data.ctrl``."""

    def __init__(self, sim_model: mujoco.MjModel):
        self.info = robots.PANDA
        self.model = build_robot_model("panda")
        self.configuration = mink.Configuration(self.model)
        self.sim_qadr = np.array([sim_model.jnt_qposadr[sim_model.joint(j).id] for j in self.info.arm_joints])
        self.ik_qadr = np.array(
            [self.model.jnt_qposadr[self.model.joint(j).id] for j in self.info.arm_joints]
        )
        self.act_ids = np.array([sim_model.actuator(f"panda0_joint{i}").id for i in range(1, 8)])
        self.frame_task = mink.FrameTask(
            frame_name=self.info.grasp_site,
            frame_type="site",
            position_cost=1.0,
            orientation_cost=1.0,
            lm_damping=1e-3,
        )
        self.posture_task = mink.PostureTask(self.model, cost=1e-3)
        self.limits = [
            mink.ConfigurationLimit(self.model),
            mink.VelocityLimit(self.model, {j: MAX_JOINT_SPEED for j in self.info.arm_joints}),
        ]
        self.rotation = mink.SO3.from_matrix(robots.TOP_DOWN)
        self.q_cmd = np.zeros(len(self.info.arm_joints))
        self.home_q = self.solve_static(np.array([0.0, 0.30, 0.25]))

    def solve_static(self, target: np.ndarray, iterations: int = 300) -> np.ndarray:
        """Arm joint angles putting the grasp site at ``target`` (top-down), by iterating the IK."""
        q = self.model.qpos0.copy()
        q[self.ik_qadr] = [0.0, 0.0, 0.0, -1.8, 0.0, 0.3, 0.0]
        self.configuration.update(q)
        self.posture_task.set_target(q)
        self.frame_task.set_target(mink.SE3.from_rotation_and_translation(self.rotation, target))
        for _ in range(iterations):
            v = mink.solve_ik(
                self.configuration,
                [self.frame_task, self.posture_task],
                0.05,
                "daqp",
                damping=1e-3,
                limits=self.limits[:1],
            )
            self.configuration.integrate_inplace(v, 0.05)
        return self.configuration.q[self.ik_qadr].copy()

    def reset(self, data: mujoco.MjData) -> None:
        data.qpos[self.sim_qadr] = self.home_q
        data.ctrl[self.act_ids] = self.home_q
        self.q_cmd = self.home_q.copy()
        q = self.model.qpos0.copy()
        q[self.ik_qadr] = self.home_q
        self.posture_task.set_target(q)

    def sync(self, data: mujoco.MjData) -> None:
        """Take over from a restored physics state: the joint command is what the actuators hold."""
        self.q_cmd = data.ctrl[self.act_ids].copy()

    def command(self, data: mujoco.MjData, target: np.ndarray, dt: float) -> None:
        measured = data.qpos[self.sim_qadr]
        # If the arm is blocked (contact), re-anchor on the measured joints instead of winding up.
        if np.max(np.abs(self.q_cmd - measured)) > 0.25:
            self.q_cmd = measured.copy()
        q = self.model.qpos0.copy()
        q[self.ik_qadr] = self.q_cmd
        self.configuration.update(q)
        ee = self.configuration.get_transform_frame_to_world(self.info.grasp_site, "site").translation()
        goal = _rate_limit(ee, target, MAX_EE_SPEED * dt)
        self.frame_task.set_target(mink.SE3.from_rotation_and_translation(self.rotation, goal))
        try:
            v = mink.solve_ik(
                self.configuration,
                [self.frame_task, self.posture_task],
                dt,
                "daqp",
                damping=1e-3,
                limits=self.limits,
            )
        except mink.exceptions.NoSolutionFound:
            v = np.zeros(self.model.nv)
        self.configuration.integrate_inplace(v, dt)
        self.q_cmd = self.configuration.q[self.ik_qadr].copy()
        data.ctrl[self.act_ids] = self.q_cmd


class SawyerMocap:
    """Moves the Sawyer's hand by its welded mocap body."""

    def __init__(self, sim_model: mujoco.MjModel):
        self.info = robots.SAWYER
        self.mocap_id = sim_model.body("mocap").mocapid[0]
        self.site_id = sim_model.site(self.info.grasp_site).id
        self.hand_id = sim_model.body("hand").id
        self.home = np.array([0.0, 0.30, 0.25])
        self.cmd = self.home.copy()

    def reset(self, data: mujoco.MjData) -> None:
        # Start the hand at home: a few weld-driven settling steps happen in SimEnv.reset.
        self.cmd = self.home.copy()
        data.mocap_pos[self.mocap_id] = self.home
        data.mocap_quat[self.mocap_id] = _SAWYER_QUAT

    def sync(self, data: mujoco.MjData) -> None:
        """Take over from a restored physics state: the hand command is where the mocap body is."""
        self.cmd = data.mocap_pos[self.mocap_id].copy()

    def command(self, data: mujoco.MjData, target: np.ndarray, dt: float) -> None:
        self.cmd = _rate_limit(self.cmd, np.asarray(target, dtype=np.float64), MAX_EE_SPEED * dt)
        # The grasp site sits at the hand origin, so the mocap target is the site target.
        data.mocap_pos[self.mocap_id] = self.cmd
        data.mocap_quat[self.mocap_id] = _SAWYER_QUAT


class HandMocap:
    """Moves the human hand by its welded mocap body; owns the hand's scripted pinch (``pinch``)."""

    def __init__(self, sim_model: mujoco.MjModel):
        self.info = robots.HAND
        self.mocap_id = sim_model.body(hand.MOCAP_BODY).mocapid[0]
        self.root_qadr = np.array([sim_model.jnt_qposadr[sim_model.joint(j).id] for j in hand.ROOT_JOINTS])
        self.pinch = hand.PinchGrasp(sim_model)
        self.home = hand.HOME.copy()
        self.cmd = self.home.copy()

    def reset(self, data: mujoco.MjData) -> None:
        # The hand body's origin is the grasp site, so its slide joints are the grasp site's world position.
        self.cmd = self.home.copy()
        data.qpos[self.root_qadr] = self.home
        data.mocap_pos[self.mocap_id] = self.home
        data.mocap_quat[self.mocap_id] = [1.0, 0.0, 0.0, 0.0]

    def command(self, data: mujoco.MjData, target: np.ndarray, dt: float) -> None:
        self.cmd = _rate_limit(self.cmd, np.asarray(target, dtype=np.float64), MAX_EE_SPEED * dt)
        data.mocap_pos[self.mocap_id] = self.cmd

    def sync(self, data: mujoco.MjData) -> None:
        """Take over from a restored state: continue from its mocap position, re-apply its grasp."""
        self.cmd = data.mocap_pos[self.mocap_id].copy()
        self.pinch.refresh(data)


def make_controller(robot: str, sim_model: mujoco.MjModel) -> PandaIK | SawyerMocap | HandMocap:
    if robot == "panda":
        return PandaIK(sim_model)
    if robot == "hand":
        return HandMocap(sim_model)
    return SawyerMocap(sim_model)
