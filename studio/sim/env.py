"""The simulation environment: reset a task by seed, step with an end-effector target, render, read state.

:class:`SimEnv` is the one API every other part of the studio uses for physics — scripted collection,
browser teleop, the waypoint controller and rollouts. One control tick (:meth:`SimEnv.step`) runs the
arm controller (IK or mocap) once and then ``n_substeps`` physics steps.

Observation cameras render with shadows, reflections and multisampling off, which is 20–40× faster
than MuJoCo's defaults on a CPU.
"""

from __future__ import annotations

import os
from typing import Protocol

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np

from studio.sim import hand, rendering, robots, scenes
from studio.sim.camera import CameraModel
from studio.sim.ik import HandMocap, make_controller
from studio.sim.metaworld_tasks import MetaWorldTask
from studio.sim.physics_state import STATE_SPEC, check_states
from studio.sim.tasks import Task, get_task

#: Where targets are clamped to: (min, max) per world axis of the grasp site, metres.
WORKSPACE = np.array([[-0.45, 0.12, 0.012], [0.45, 0.95, 0.55]])

# Finger bodies whose contacts define "holding an object".
_FINGER_BODIES = {
    "panda": ("panda0_leftfinger", "panda0_rightfinger"),
    "sawyer": ("rightpad", "leftpad"),
    "hand": ("hand_index3", "hand_thumb3"),  # the hand holds by its pinch weld (SimEnv.held_object)
}


class Simulator(Protocol):
    """What :class:`SimEnv` and :class:`~studio.sim.metaworld_env.MetaWorldEnv` both provide: the
    interface the recorder and teleop sessions drive either with (see :func:`make_env`)."""

    @property
    def scene(self) -> str: ...
    @property
    def robot(self) -> str: ...
    @property
    def scene_info(self) -> scenes.SceneInfo: ...
    @property
    def image_size(self) -> tuple[int, int]: ...
    @property
    def control_dt(self) -> float: ...
    @property
    def task(self) -> Task | MetaWorldTask | None: ...
    @property
    def seed(self) -> int | None: ...
    @property
    def steps(self) -> int: ...
    @property
    def target(self) -> np.ndarray: ...
    @property
    def gripper_cmd(self) -> float: ...
    @property
    def model(self) -> mujoco.MjModel: ...
    @property
    def data(self) -> mujoco.MjData: ...
    @property
    def ee_pos(self) -> np.ndarray: ...
    @property
    def camera_names(self) -> tuple[str, ...]: ...

    def reset(self, task: str, seed: int) -> None: ...
    def restore(self, task: str, seed: int, states: np.ndarray, gripper_cmd: float) -> None: ...
    def step(self, target_pos: np.ndarray, gripper: float) -> None: ...
    def success(self) -> bool: ...
    def stages(self) -> dict[str, bool]: ...
    def object_poses(self) -> dict[str, np.ndarray]: ...
    def state(self) -> dict[str, np.ndarray | float]: ...
    def camera_model(self, camera: str = "external", size: tuple[int, int] | None = None) -> CameraModel: ...
    def render(self, camera: str = "external", size: tuple[int, int] | None = None) -> np.ndarray: ...
    def close(self) -> None: ...


class SimEnv:
    """A tabletop scene with one robot.

    Args:
        scene: ``"pick_place"`` or ``"push"``.
        robot: ``"panda"``, ``"sawyer"`` or ``"hand"``.
        image_size: (height, width) of the external camera's images.
        control_dt: seconds per control tick (one :meth:`step`).
        depth_size: (height, width) of the wrist depth camera.
    """

    def __init__(
        self,
        scene: str,
        robot: str,
        *,
        image_size: tuple[int, int] = (240, 320),
        control_dt: float = 0.02,
        depth_size: tuple[int, int] = (64, 64),
    ):
        self.scene_info = scenes.scene_info(scene)
        self.robot_info = robots.robot_info(robot)
        self.scene, self.robot = scene, robot
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.depth_size = depth_size
        self.model = scenes.build_model(scene, robot)
        self.data = mujoco.MjData(self.model)
        self.n_substeps = max(1, round(control_dt / self.model.opt.timestep))
        self.control_dt = self.n_substeps * self.model.opt.timestep
        self.controller = make_controller(robot, self.model)
        # The hand grasps by a scripted pinch instead of friction between fingers.
        self._pinch = self.controller.pinch if isinstance(self.controller, HandMocap) else None
        m = self.model
        self._site = m.site(self.robot_info.grasp_site).id
        self._finger_qadr = np.array([m.jnt_qposadr[m.joint(j).id] for j in self.robot_info.finger_joints])
        self._finger_act = np.array([m.actuator(a).id for a in self.robot_info.finger_actuators])
        arm_and_fingers = self.robot_info.arm_joints + self.robot_info.finger_joints
        self._robot_qadr = np.array([m.jnt_qposadr[m.joint(j).id] for j in arm_and_fingers])
        self._obj_qadr = {o: m.jnt_qposadr[m.joint(f"obj_{o}").id] for o in self.scene_info.objects}
        self._obj_body = {m.body(f"obj_{o}").id: o for o in self.scene_info.objects}
        self._finger_bodies = {m.body(b).id for b in _FINGER_BODIES[robot]}
        self._renderers = rendering.Renderers(self.model)
        # Observation cameras show what a real camera would: no sites, no collision-only geoms.
        self._vis = mujoco.MjvOption()
        self._vis.sitegroup[:] = 0
        self._vis.geomgroup[3:] = 0
        self.task: Task | None = None
        self.seed: int | None = None
        self.layout: scenes.Layout | None = None
        self.initial_objects: dict[str, np.ndarray] = {}
        # Stages reached at some tick of the episode (the breakdown counts what happened, not just the end state).
        self._ever = {"reached": False, "grasped": False}
        self.gripper_cmd = 0.0
        self.target = np.zeros(3)
        self.steps = 0
        rendering.track(self)

    # ------------------------------------------------------------------ episode
    def reset(self, task: str | Task, seed: int) -> None:
        """Start an episode of ``task`` from the initial state drawn with ``seed``."""
        found = get_task(task) if isinstance(task, str) else task
        if found.scene != self.scene:
            raise ValueError(
                f"task {found.name!r} belongs to scene {found.scene!r}, this env is {self.scene!r}"
            )
        # A Meta-World task's scene is "metaworld", which no SimEnv has: the check above rejected it.
        assert isinstance(found, Task)
        layout = found.sample_layout(int(seed))
        self.task, self.seed, self.layout = found, int(seed), layout
        m, d = self.model, self.data
        for name, xy in layout.target_pos.items():
            m.body(f"target_{name}").pos[:2] = xy
        mujoco.mj_resetData(m, d)
        for name, pos in layout.object_pos.items():
            a = self._obj_qadr[name]
            yaw = layout.object_yaw.get(name, 0.0)
            d.qpos[a : a + 3] = pos
            d.qpos[a + 3 : a + 7] = [np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]
        self.controller.reset(d)
        self.gripper_cmd = 0.0
        d.ctrl[self._finger_act] = self.robot_info.finger_ctrl(0.0)
        if self.robot == "panda":  # start with the fingers fully open, as the open command asks
            d.qpos[self._finger_qadr] = 0.04
        mujoco.mj_forward(m, d)
        # Let the objects and the welded hand settle before the episode starts.
        for _ in range(100):
            mujoco.mj_step(m, d)
        d.time = 0.0
        self.steps = 0
        self.target = self.ee_pos.copy()
        self.initial_objects = {o: p[:3].copy() for o, p in self.object_poses().items()}
        self._ever = {"reached": False, "grasped": False}

    def restore(self, task: str | Task, seed: int, states: np.ndarray, gripper_cmd: float) -> None:
        """Continue a recorded episode of (``task``, ``seed``) from its last recorded tick.

        ``states`` (T, S) are MuJoCo integration states (``mjSTATE_INTEGRATION``), one per tick from the
        reset on, as :class:`~studio.sim.recorder.Recorder` keeps them; ``gripper_cmd`` is the gripper
        command in force at the last one. The scene is reset (task layout, target zones), each state is
        set in turn so that the stages reached on the way count as if the episode had run, and the arm
        controller takes over from the last: stepping on with the commands the episode had continues it
        bit for bit. Raises ValueError if the states do not fit this model (the scene changed since).
        """
        check_states(self.model, states)
        self.reset(task, seed)
        for s in np.asarray(states, dtype=np.float64):
            mujoco.mj_setState(self.model, self.data, s, STATE_SPEC)
            mujoco.mj_forward(self.model, self.data)
            if not self._ever["grasped"]:
                self._stages_now()
        # mj_forward rewrote the warm-start accelerations; the next step must start from the recorded ones.
        mujoco.mj_setState(self.model, self.data, np.asarray(states[-1], dtype=np.float64), STATE_SPEC)
        self.controller.sync(self.data)
        self.steps = len(states) - 1
        self.gripper_cmd = float(np.clip(gripper_cmd, 0.0, 1.0))
        self.target = self.ee_pos.copy()

    def step(self, target_pos: np.ndarray, gripper: float) -> None:
        """One control tick: move the grasp site towards ``target_pos`` (clamped to the workspace) with
        the gripper commanded to ``gripper`` (0 open … 1 closed)."""
        if self.task is None:
            raise RuntimeError("SimEnv.step called before reset()")
        target = np.asarray(target_pos, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(target)):
            target = self.target  # ignore a non-finite command, keep the last good one
        self.target = np.clip(target, WORKSPACE[0], WORKSPACE[1])
        g = float(gripper) if np.isfinite(gripper) else self.gripper_cmd
        self.gripper_cmd = float(np.clip(g, 0.0, 1.0))
        self.controller.command(self.data, self.target, self.control_dt)
        self.data.ctrl[self._finger_act] = self.robot_info.finger_ctrl(self.gripper_cmd)
        if self._pinch is not None:
            self._pinch.update(self.data, self.gripper_cmd)
        mujoco.mj_step(self.model, self.data, nstep=self.n_substeps)
        self.steps += 1
        if not self._ever["grasped"]:  # once grasped, reached is recorded too: nothing left to track
            self._stages_now()

    # ------------------------------------------------------------------ state
    @property
    def ee_pos(self) -> np.ndarray:
        return self.data.site_xpos[self._site].copy()

    def gripper_opening(self) -> float:
        if self.robot == "hand":
            tips = [
                self.data.site_xpos[self.model.site(s).id] for s in (hand.INDEX_TIP_SITE, hand.THUMB_TIP_SITE)
            ]
            return float(np.linalg.norm(tips[0] - tips[1]))
        q = self.data.qpos[self._finger_qadr]
        if self.robot == "panda":
            return float(q[0] + q[1])
        return float(0.088 + q[1] - q[0])

    def object_poses(self) -> dict[str, np.ndarray]:
        """Object name -> (7,) position and quaternion (w, x, y, z) in the world."""
        return {o: self.data.qpos[a : a + 7].copy() for o, a in self._obj_qadr.items()}

    def held_object(self) -> str | None:
        """The object both fingers touch, if any (for the hand: the object its pinch holds)."""
        if self._pinch is not None:
            return self._pinch.held(self.data)
        touching: dict[str, set[int]] = {}
        d = self.data
        for i in range(d.ncon):
            c = d.contact[i]
            b1 = self.model.geom_bodyid[c.geom1]
            b2 = self.model.geom_bodyid[c.geom2]
            for finger, other in ((b1, b2), (b2, b1)):
                if finger in self._finger_bodies and other in self._obj_body:
                    touching.setdefault(self._obj_body[other], set()).add(finger)
        for name, fingers in touching.items():
            if len(fingers) == 2:
                return name
        return None

    def _stages_now(self) -> dict[str, bool]:
        if self.task is None or self.layout is None:
            raise RuntimeError("SimEnv.stages called before reset()")
        objects = {o: p[:3] for o, p in self.object_poses().items()}
        now = self.task.stages(objects, self.initial_objects, self.layout, self.ee_pos, self.held_object())
        for k in self._ever:
            self._ever[k] = self._ever[k] or now[k]
        return now

    def stages(self) -> dict[str, bool]:
        """The task's breakdown: ``reached`` and ``grasped`` if that happened at any tick of the episode (an
        object carried to the wrong place and let go was still grasped), ``placed`` (= success) now."""
        now = self._stages_now()
        return {"reached": self._ever["reached"], "grasped": self._ever["grasped"], "placed": now["placed"]}

    def success(self) -> bool:
        return self.stages()["placed"]

    @property
    def camera_names(self) -> tuple[str, ...]:
        """The cameras :meth:`render` takes: ``"external"`` (the observation camera), ``"wrist"``, then the rest."""
        names = [self.model.camera(i).name for i in range(self.model.ncam)]
        return ("external", "wrist", *(n for n in names if n and n not in ("external", "wrist")))

    def camera_model(self, camera: str = "external", size: tuple[int, int] | None = None) -> CameraModel:
        h, w = size or (self.image_size if camera == "external" else self.depth_size)
        return CameraModel.from_mujoco(self.model, self.data, camera, w, h)

    def state(self) -> dict[str, np.ndarray | float]:
        """One step's worth of the arrays a recording holds (see :data:`studio.sim.recording.ARRAY_FIELDS`)."""
        ee = self.ee_pos
        cam = self.camera_model("external")
        poses = self.object_poses()
        return {
            "time": float(self.data.time),
            "qpos": self.data.qpos[self._robot_qadr].copy(),
            "ee_pos_world": ee,
            "ee_pos_cam": cam.world_to_cam(ee),
            "gripper_cmd": self.gripper_cmd,
            "gripper_opening": self.gripper_opening(),
            "object_poses": np.stack([poses[o] for o in self.scene_info.objects]),
        }

    # ------------------------------------------------------------------ rendering
    def render(self, camera: str = "external", size: tuple[int, int] | None = None) -> np.ndarray:
        """RGB image (H, W, 3) uint8 from a named camera."""
        size = size or (self.image_size if camera == "external" else self.depth_size)
        return self._renderers.render(self.data, camera, size, scene_option=self._vis)

    def render_depth(self, camera: str = "wrist", size: tuple[int, int] | None = None) -> np.ndarray:
        """Depth image (H, W) float32, metres along the camera's optical axis."""
        size = size or (self.depth_size if camera != "external" else self.image_size)
        return self._renderers.render(self.data, camera, size, depth=True, scene_option=self._vis)

    def close(self) -> None:
        self._renderers.close()

    def __enter__(self) -> SimEnv:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def default_image_size(scene: str) -> tuple[int, int]:
    """The external camera's (height, width) a scene family is collected at by default."""
    if scene == "metaworld":
        from studio.sim.metaworld_env import IMAGE_SIZE

        return IMAGE_SIZE
    return (240, 320)


def make_env(scene: str, robot: str, *, image_size: tuple[int, int] | None = None, **kwargs):
    """The simulator of a scene family: a :class:`SimEnv` for the tabletop scenes, a
    :class:`~studio.sim.metaworld_env.MetaWorldEnv` for ``"metaworld"`` (same interface).

    ``image_size`` None means the scene's default (:func:`default_image_size`); other keyword
    arguments go to the environment's constructor.
    """
    size = image_size or default_image_size(scene)
    if scene == "metaworld":
        from studio.sim.metaworld_env import MetaWorldEnv

        return MetaWorldEnv(scene, robot, image_size=size, **kwargs)
    return SimEnv(scene, robot, image_size=size, **kwargs)
