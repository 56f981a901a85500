"""Meta-World scenes behind the simulator interface the rest of the studio uses (:class:`MetaWorldEnv`).

Each of the 50 tasks (:mod:`studio.sim.metaworld_tasks`) is the installed ``metaworld`` package's own
environment — its MJCF, its seeded initial-state sampler and its success computation — driven by our
stepping, so the waypoint controller, the recorder, rollouts and teleop work on it as on a tabletop
:class:`~studio.sim.env.SimEnv`:

* **Reset by seed, bit for bit.** Meta-World draws an episode's random vector from the env's
  ``np_random``; we hand it a ``numpy.random.default_rng(seed)`` of our own (so the env's rejection
  sampling, e.g. pick-place keeping object and goal apart, draws from it too) and restore the model
  fields reset writes (body and site positions) before every reset, so the state depends on the seed
  alone, not on the episodes before.
* **Our own stepping.** Meta-World's ``step()`` counts to ``max_path_length`` (500) and then raises or
  truncates, and wrappers around it auto-reset — the re-planning bug of the reference evaluation. We
  never call it: one control tick moves the mocap body welded to the hand (at most 1 cm per axis, the
  bound of Meta-World's own actions), sets the fingers and runs ``frame_skip`` (5) physics steps of
  2.5 ms — a 12.5 ms tick, as in Meta-World. :meth:`MetaWorldEnv.step` steers the mocap by the hand's
  remaining error (Meta-World's scripted-policy control law), so the hand reaches its target even
  while pressing a button or a door; :meth:`MetaWorldEnv.step_action` applies a Meta-World action
  as such. MuJoCo's automatic reset on divergence is disabled too; a diverged simulation raises
  :class:`SimulationDiverged` instead of silently starting over.
* **The env's own success signal.** After every tick the env's ``evaluate_state`` judges the state
  (with the action that tick amounted to). :meth:`MetaWorldEnv.success` is latched — the task
  succeeded at some tick since reset, as in the paper's evaluation — and :meth:`MetaWorldEnv.stages`
  maps the env's info onto reached / grasped / placed.
* **The paper's camera.** ``"external"`` is Meta-World's ``corner`` camera turned upright (its MJCF
  definition renders upside down) and zoomed to a 30° vertical field of view, the ``corner_zoom`` view
  of the reference data, at 224×224 by default: the box x ∈ [−0.3, 0.3], y ∈ [0.4, 0.95],
  z ∈ [0, 0.3] m just fills the image. Shadows, reflections, skybox and multisampling are off.
  Meta-World's site markers (goals, fingertips) stay visible: for tasks such as pick-place the goal
  marker is the only thing in the image that says where to go.
* **A wrist depth camera.** ``"wrist"`` is Meta-World's ``behindGripper`` camera re-mounted on the hand
  exactly where our tabletop Sawyer carries its wrist camera (4 cm behind the hand origin, looking along
  the gripper axis, 75° field of view), so grasp correction runs on Meta-World as on the tabletop scenes,
  as in the paper (the reference code's Meta-World evaluation hands every grasp to its wrist-camera grasp
  policy too).

The end-effector point is the hand body's origin — Meta-World's own ``hand_pos`` observation, the
point its scripted policies steer and the mocap target (the grasp site of our tabletop Sawyer is the
same point). Object poses are the env's own object points (``_get_pos_objects``) with their
orientations converted to (w, x, y, z): Meta-World reports some as MuJoCo quaternions and some in
SciPy's (x, y, z, w) order; parts that report none (sliding handles, windows) get the identity.
"""

from __future__ import annotations

import inspect
import os
import re
import warnings
from typing import Any

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np

from studio.sim import rendering, robots
from studio.sim.camera import CameraModel
from studio.sim.metaworld_tasks import SCENE, MetaWorldTask, get_metaworld_task
from studio.sim.physics_state import STATE_SPEC, check_states
from studio.sim.scenes import SceneInfo

#: Default image size of the external camera (the paper's Meta-World resolution).
IMAGE_SIZE = (224, 224)
#: The Meta-World camera the external view is made from, and its vertical field of view, degrees.
EXTERNAL_SOURCE = "corner"
EXTERNAL_FOVY = 30.0
#: The Meta-World camera re-mounted as the wrist depth camera ``"wrist"``, at the tabletop Sawyer's wrist camera
#: pose (``robots.SAWYER_WRIST_*``: Meta-World's hand is the same model).
WRIST_SOURCE = "behindGripper"
#: Seconds per control tick (Meta-World's frame_skip 5 × 2.5 ms) and largest mocap move per tick and axis, m.
CONTROL_DT = 0.0125
MAX_STEP = 0.01
#: Fraction of the hand's remaining error the mocap moves per tick in :meth:`MetaWorldEnv.step` (the
#: proportional gain 25 of Meta-World's pressing and door policies, times its 1 cm action scale).
HAND_GAIN = 0.25
#: The hand orientation Meta-World holds the mocap at (gripper pointing down).
HAND_QUAT = np.array([1.0, 0.0, 1.0, 0.0])
#: Names of the objects in :meth:`MetaWorldEnv.object_poses`, in Meta-World's observation order.
OBJECT_NAMES = ("object0", "object1")

_QUAT_TOKEN = re.compile(
    r"as_quat\(|xquat|np\.zeros\(4\)|np\.array\(\s*\[\s*[01]\.0\s*,\s*0\.0\s*,\s*0\.0\s*,\s*0\.0\s*,?\s*\]\s*\)"
)


def _quat_from_xyaxes(xyaxes) -> np.ndarray:
    """The (w, x, y, z) orientation whose frame has the given orthonormal x and y axes (MJCF's ``xyaxes``)."""
    x, y = np.asarray(xyaxes, dtype=np.float64).reshape(2, 3)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.column_stack([x, y, np.cross(x, y)]).reshape(-1))
    return quat


class SimulationDiverged(RuntimeError):
    """The physics became non-finite; the episode cannot go on (and is never silently reset)."""


def quaternion_orders(env_cls: type[Any]) -> tuple[str, ...]:
    """The order of each quaternion the Meta-World env class reports: ``"wxyz"`` or ``"xyzw"``.

    Read from the source of its ``_get_quat_objects``: SciPy's ``as_quat()`` gives (x, y, z, w),
    MuJoCo's ``xquat`` and literal constants (w, x, y, z).
    """
    src = inspect.getsource(env_cls._get_quat_objects)
    return tuple("xyzw" if t.startswith("as_quat") else "wxyz" for t in _QUAT_TOKEN.findall(src))


def metaworld_env_class(env_name: str) -> type[Any]:
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    return ALL_V3_ENVIRONMENTS[env_name]


class MetaWorldEnv:
    """One Meta-World task at a time, with :class:`~studio.sim.env.SimEnv`'s interface.

    The compiled model belongs to the task: :meth:`reset` with another task loads that task's model,
    so ``model`` and ``data`` may change at a reset (never during an episode).

    Args:
        scene: must be ``"metaworld"``.
        robot: must be ``"sawyer"`` (Meta-World has no other arm).
        image_size: (height, width) of the external camera's images.
        depth_size: (height, width) of depth images from the hand cameras.
    """

    def __init__(
        self,
        scene: str = SCENE,
        robot: str = "sawyer",
        *,
        image_size: tuple[int, int] = IMAGE_SIZE,
        depth_size: tuple[int, int] = (64, 64),
    ):
        if scene != SCENE:
            raise ValueError(f"MetaWorldEnv serves the {SCENE!r} scene, not {scene!r}")
        if robot != "sawyer":
            raise ValueError(
                f"Meta-World scenes have only the Sawyer, got robot {robot!r} "
                "(expert and agent come from the same Sawyer pool)"
            )
        self.scene, self.robot = scene, robot
        self.robot_info = robots.SAWYER
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.depth_size = (int(depth_size[0]), int(depth_size[1]))
        self.task: MetaWorldTask | None = None
        self.seed: int | None = None
        self.gripper_cmd = 0.0
        self.target = np.zeros(3)
        self.steps = 0
        self.info: dict = {}
        self.control_dt = CONTROL_DT
        self.max_step = MAX_STEP
        # The loaded task's metaworld env (a SawyerXYZEnv subclass that depends on the task); we call its
        # private helpers, which metaworld does not type, hence Any.
        self._mw: Any = None
        self._renderers: rendering.Renderers | None = None  # of the loaded task's model
        self._vis = mujoco.MjvOption()
        self._cameras: dict[tuple[str, int, int], CameraModel] = {}
        self._ever = {"success": False, "near_object": False, "grasp_success": False}
        self._last_action = np.zeros(4)
        self._prev_obs: np.ndarray | None = None
        self._cur_obs: np.ndarray | None = None
        rendering.track(self)

    # ------------------------------------------------------------------ task loading
    def _load(self, task: MetaWorldTask) -> None:
        """Build the Meta-World env of ``task`` (its own model), unless it is already loaded."""
        if self._mw is not None and self.task is not None and self.task.env_name == task.env_name:
            return
        self.close()
        if self._mw is not None:
            self._mw.close()
        cls = metaworld_env_class(task.env_name)
        mw = cls()
        mw._set_task_called = True  # we set the random vector ourselves (see reset)
        mw._partially_observable = False  # the goal is part of the observation the scripted policies read
        m = mw.model
        m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_AUTORESET
        cam = m.camera(EXTERNAL_SOURCE).id
        upright = np.zeros(4)
        mujoco.mju_mulQuat(upright, m.cam_quat[cam].copy(), np.array([0.0, 0.0, 0.0, 1.0]))
        m.cam_quat[cam] = upright
        m.cam_fovy[cam] = EXTERNAL_FOVY
        wrist = m.camera(WRIST_SOURCE).id
        m.cam_mode[wrist] = mujoco.mjtCamLight.mjCAMLIGHT_FIXED
        m.cam_bodyid[wrist] = m.body("hand").id
        m.cam_pos[wrist] = robots.SAWYER_WRIST_POS
        m.cam_quat[wrist] = _quat_from_xyaxes(robots.SAWYER_WRIST_XYAXES)
        m.cam_fovy[wrist] = robots.SAWYER_WRIST_FOVY
        m.vis.quality.offsamples = 0
        self._mw = mw
        self._renderers = rendering.Renderers(m)
        self._external_id = cam
        self._wrist_id = wrist
        self._pristine = {"body_pos": m.body_pos.copy(), "site_pos": m.site_pos.copy()}
        self._robot_qadr = np.array(
            [m.jnt_qposadr[m.joint(j).id] for j in self.robot_info.arm_joints + self.robot_info.finger_joints]
        )
        self._finger_qadr = self._robot_qadr[-2:]
        self._hand = m.body("hand").id
        self._mocap = m.body_mocapid[m.body("mocap").id]
        self._quat_orders = quaternion_orders(cls)
        self.control_dt = mw.frame_skip * m.opt.timestep
        self.max_step = float(mw.action_scale)
        self.workspace = np.stack([np.asarray(mw.mocap_low, float), np.asarray(mw.mocap_high, float)])
        self._cameras.clear()

    @property
    def model(self) -> mujoco.MjModel:
        if self._mw is None:
            raise RuntimeError("MetaWorldEnv has no model before the first reset(task, seed)")
        return self._mw.model

    @property
    def data(self) -> mujoco.MjData:
        if self._mw is None:
            raise RuntimeError("MetaWorldEnv has no data before the first reset(task, seed)")
        return self._mw.data

    @property
    def metaworld_env(self):
        """The underlying ``metaworld`` environment (for its success computation and scripted policies)."""
        return self._mw

    @property
    def scene_info(self) -> SceneInfo:
        return SceneInfo(SCENE, objects=self.object_names)

    @property
    def object_names(self) -> tuple[str, ...]:
        return OBJECT_NAMES[: len(self._mw._get_pos_objects()) // 3]

    # ------------------------------------------------------------------ episode
    def reset(self, task: str | MetaWorldTask, seed: int) -> None:
        """Start an episode of ``task`` from the initial state drawn with ``seed``."""
        task = get_metaworld_task(task) if isinstance(task, str) else task
        if task.scene != SCENE:
            raise ValueError(f"task {task.name!r} belongs to scene {task.scene!r}, this env is {SCENE!r}")
        self._load(task)
        self.task, self.seed = task, int(seed)
        mw, m, d = self._mw, self._mw.model, self._mw.data
        m.body_pos[:] = self._pristine["body_pos"]
        m.site_pos[:] = self._pristine["site_pos"]
        mw._freeze_rand_vec = False
        mw.seeded_rand_vec = True
        mw.np_random = np.random.default_rng(self.seed)
        mujoco.mj_resetData(m, d)
        mw.curr_path_length = 0
        mw.reset_model()  # moves the hand home (Meta-World's 50 settling ticks) and places the objects
        d.ctrl[:] = self.robot_info.finger_ctrl(0.0)
        mujoco.mj_forward(m, d)
        d.time = 0.0
        self.steps = 0
        self.gripper_cmd = 0.0
        self.target = self.ee_pos.copy()
        self._last_action = np.array([0.0, 0.0, 0.0, -1.0])
        self._ever = dict.fromkeys(self._ever, False)
        self._cur_obs = mw._get_curr_obs_combined_no_goal()
        self._prev_obs = self._cur_obs.copy()
        self._evaluate()

    def restore(self, task: str | MetaWorldTask, seed: int, states: np.ndarray, gripper_cmd: float) -> None:
        """Continue a recorded episode from its last tick (see :meth:`studio.sim.env.SimEnv.restore`): the
        task is reset with ``seed``, each recorded integration state is set in turn so that the success
        signals latch as they did, and the observation history follows the last two ticks."""
        task = get_metaworld_task(task) if isinstance(task, str) else task
        self._load(task)
        check_states(self.model, states)
        self.reset(task, seed)
        m, d = self.model, self.data
        for s in np.asarray(states, dtype=np.float64):
            mujoco.mj_setState(m, d, s, STATE_SPEC)
            mujoco.mj_forward(m, d)
            self._prev_obs, self._cur_obs = self._cur_obs, self._mw._get_curr_obs_combined_no_goal()
            self._evaluate()
        # mj_forward rewrote the warm-start accelerations; the next step must start from the recorded ones.
        mujoco.mj_setState(m, d, np.asarray(states[-1], dtype=np.float64), STATE_SPEC)
        if len(states) == 1:
            self._prev_obs = self._cur_obs.copy() if self._cur_obs is not None else None
        self.steps = len(states) - 1
        self.gripper_cmd = float(np.clip(gripper_cmd, 0.0, 1.0))
        self.target = self.ee_pos.copy()

    def step(self, target_pos: np.ndarray, gripper: float) -> None:
        """One control tick: steer the hand towards ``target_pos`` (clamped to the task's mocap box) with
        the gripper commanded to ``gripper`` (0 open … 1 closed).

        The mocap moves by :data:`HAND_GAIN` × (target − hand), at most :attr:`max_step` per axis — the
        control law of Meta-World's own scripted policies. It acts on the hand's error, so the hand gets
        to the target even when it pushes against something (a button, a door): the mocap runs ahead
        and the weld presses harder, as in Meta-World.
        """
        if self.task is None:
            raise RuntimeError("MetaWorldEnv.step called before reset()")
        target = np.asarray(target_pos, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(target)):
            target = self.target  # ignore a non-finite command, keep the last good one
        self.target = np.clip(target, self.workspace[0], self.workspace[1])
        g = float(gripper) if np.isfinite(gripper) else self.gripper_cmd
        mocap = self.data.mocap_pos[self._mocap]
        self._advance(mocap + HAND_GAIN * (self.target - self.ee_pos), float(np.clip(g, 0.0, 1.0)))

    def step_action(self, action: np.ndarray) -> None:
        """One control tick from a Meta-World action (dx, dy, dz, grab effort), each in [-1, 1].

        Exactly what Meta-World's ``step`` does to the simulation (mocap moved by action × 1 cm, finger
        controls ± effort), without its episode bookkeeping.
        """
        if self.task is None:
            raise RuntimeError("MetaWorldEnv.step_action called before reset()")
        a = np.clip(np.asarray(action, dtype=np.float64).reshape(4), -1.0, 1.0)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"Meta-World action must be finite, got {action}")
        mocap = self.data.mocap_pos[self._mocap]
        self.target = np.clip(mocap + a[:3] * self.max_step, self.workspace[0], self.workspace[1])
        self._advance(self.target, (a[3] + 1.0) / 2.0)

    def _advance(self, target: np.ndarray, gripper: float) -> None:
        """Move the mocap towards ``target`` (at most max_step per axis, inside the mocap box) and simulate."""
        m, d = self.model, self.data
        mocap = d.mocap_pos[self._mocap].copy()
        new = np.clip(
            mocap + np.clip(target - mocap, -self.max_step, self.max_step),
            self.workspace[0],
            self.workspace[1],
        )
        self.gripper_cmd = gripper
        ctrl = self.robot_info.finger_ctrl(gripper)
        self._last_action = np.append((new - mocap) / self.max_step, ctrl[0])
        d.mocap_pos[self._mocap] = new
        d.mocap_quat[self._mocap] = HAND_QUAT
        d.ctrl[:] = ctrl
        mujoco.mj_step(m, d, nstep=self._mw.frame_skip)
        mujoco.mj_forward(m, d)  # positions, contacts and forces of the new state, as Meta-World judges them
        if not np.all(np.isfinite(d.qpos)):
            name = "?" if self.task is None else self.task.name  # step() and step_action() checked it is set
            raise SimulationDiverged(f"{name} seed {self.seed}: physics diverged at tick {self.steps + 1}")
        self.steps += 1
        self._prev_obs, self._cur_obs = self._cur_obs, self._mw._get_curr_obs_combined_no_goal()
        self._evaluate()

    def observation(self) -> np.ndarray:
        """Meta-World's fully observable 39-D observation of the current state (what its policies read):
        hand position, gripper distance, object poses (padded), the previous tick's copy, the goal."""
        if self._cur_obs is None or self._prev_obs is None:
            raise RuntimeError("MetaWorldEnv has no observation before the first reset(task, seed)")
        return np.hstack([self._cur_obs, self._prev_obs, self._mw._get_pos_goal()])

    def _evaluate(self) -> None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _, info = self._mw.evaluate_state(self.observation(), self._last_action.astype(np.float32))
        self.info = info
        for key in self._ever:
            self._ever[key] = self._ever[key] or bool(info.get(key, 0.0) > 0)

    # ------------------------------------------------------------------ state
    @property
    def ee_pos(self) -> np.ndarray:
        return self.data.xpos[self._hand].copy()

    def gripper_opening(self) -> float:
        q = self.data.qpos[self._finger_qadr]
        return float(0.088 + q[1] - q[0])

    def object_poses(self) -> dict[str, np.ndarray]:
        """Object name -> (7,) position and quaternion (w, x, y, z), in Meta-World's observation order."""
        pos = np.asarray(self._mw._get_pos_objects(), dtype=np.float64).reshape(-1, 3)
        quat = np.asarray(self._mw._get_quat_objects(), dtype=np.float64).reshape(-1, 4)
        out = {}
        for k, name in enumerate(self.object_names):
            q = quat[k] if k < len(quat) else np.zeros(4)
            if k < len(self._quat_orders) and self._quat_orders[k] == "xyzw":
                q = q[[3, 0, 1, 2]]
            n = float(np.linalg.norm(q))
            q = q / n if n > 1e-9 else np.array([1.0, 0.0, 0.0, 0.0])
            out[name] = np.concatenate([pos[k], q])
        return out

    def success_now(self) -> bool:
        """The env's success signal for the current state."""
        return bool(self.info.get("success", 0.0) > 0)

    def success(self) -> bool:
        """True once the env's success signal has been on at any tick since reset (latched)."""
        return self._ever["success"]

    def stages(self) -> dict[str, bool]:
        """The breakdown since reset, from the env's info: ``reached`` = the hand came near the task's
        object (``near_object``), ``grasped`` = reached and the env's ``grasp_success`` was on
        (for pressing, pushing and sliding tasks the env defines it loosely, so it follows ``reached``),
        ``placed`` = success. Each stage is latched and implied by the later ones."""
        placed = self._ever["success"]
        reached = self._ever["near_object"] or placed
        grasped = (reached and self._ever["grasp_success"]) or placed
        return {"reached": reached, "grasped": grasped, "placed": placed}

    @property
    def camera_names(self) -> tuple[str, ...]:
        """The cameras :meth:`render` takes: ``"external"``, ``"wrist"``, then Meta-World's others (the two
        re-mounted ones are not offered under their Meta-World names)."""
        names = [self.model.camera(i).name for i in range(self.model.ncam)]
        return ("external", "wrist", *(n for n in names if n and n not in (EXTERNAL_SOURCE, WRIST_SOURCE)))

    def camera_model(self, camera: str = "external", size: tuple[int, int] | None = None) -> CameraModel:
        h, w = size or (self.image_size if camera == "external" else self.depth_size)
        key = (camera, h, w)
        cam = self._cameras.get(key)
        if cam is None:
            cid = self._camera_id(camera)
            cam = CameraModel.from_mujoco(self.model, self.data, cid, w, h)
            if (
                self.model.cam_mode[cid] == mujoco.mjtCamLight.mjCAMLIGHT_FIXED
                and self.model.cam_bodyid[cid] == 0
            ):
                self._cameras[key] = cam  # cameras fixed to the world never move; the others are recomputed
        return cam

    def state(self) -> dict[str, np.ndarray | float]:
        """One step's worth of the arrays a recording holds (see :data:`studio.sim.recording.ARRAY_FIELDS`)."""
        ee = self.ee_pos
        poses = self.object_poses()
        return {
            "time": float(self.data.time),
            "qpos": self.data.qpos[self._robot_qadr].copy(),
            "ee_pos_world": ee,
            "ee_pos_cam": self.camera_model("external").world_to_cam(ee),
            "gripper_cmd": self.gripper_cmd,
            "gripper_opening": self.gripper_opening(),
            "object_poses": np.stack([poses[o] for o in self.object_names]),
        }

    # ------------------------------------------------------------------ rendering
    def _camera_id(self, camera: str) -> int:
        if camera == "external":
            return self._external_id
        if camera == "wrist":
            return self._wrist_id
        if camera in (EXTERNAL_SOURCE, WRIST_SOURCE):
            raise ValueError(
                f"Meta-World's {camera!r} camera is re-mounted here: ask for 'external' or 'wrist'"
            )
        cam = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if cam < 0:
            raise ValueError(
                f"no camera {camera!r} in Meta-World scenes; choose from {list(self.camera_names)}"
            )
        return cam

    def _loaded_renderers(self) -> rendering.Renderers:
        if self._renderers is None:
            raise RuntimeError("MetaWorldEnv cannot render before the first reset(task, seed)")
        return self._renderers

    def render(self, camera: str = "external", size: tuple[int, int] | None = None) -> np.ndarray:
        """RGB image (H, W, 3) uint8 from ``"external"`` or one of Meta-World's cameras."""
        size = size or (self.image_size if camera == "external" else self.depth_size)
        return self._loaded_renderers().render(
            self.data, self._camera_id(camera), size, scene_option=self._vis
        )

    def render_depth(self, camera: str = "external", size: tuple[int, int] | None = None) -> np.ndarray:
        """Depth image (H, W) float32, metres along the camera's optical axis."""
        size = size or (self.image_size if camera == "external" else self.depth_size)
        return self._loaded_renderers().render(
            self.data, self._camera_id(camera), size, depth=True, scene_option=self._vis
        )

    def close(self) -> None:
        if self._renderers is not None:
            self._renderers.close()

    def __enter__(self) -> MetaWorldEnv:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
