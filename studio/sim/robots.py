"""The demonstrators and the agent: a Franka Panda, a Sawyer with its two-finger gripper, and a human hand.

The two arms are loaded from files that ship inside installed packages — the Panda from
``gymnasium_robotics``'s kitchen Franka assets, the Sawyer from ``metaworld``'s assets — and the hand is written
in :mod:`studio.sim.hand`; each is composed into a scene at load time (:mod:`studio.sim.scenes`). Nothing
third-party is copied into this repo.

* Panda: joint position actuators on the 7 arm joints (driven by differential IK, :mod:`studio.sim.ik`),
  position actuators on the two fingers, gravity compensation on every body.
* Sawyer: metaworld's arm has no joint actuators; a weld from a mocap body holds its hand, so the hand
  is commanded by moving the mocap body (this tracked best and grasped reliably in our measurements).
  Its fingers are position actuated.
* Hand (``"hand"``, embodiment ``"human"``): a capsule hand with forearm on three slide joints, welded to a
  mocap body like the Sawyer's hand; the gripper command curls its fingers into a pinch, and a grasp is a
  scripted weld (:class:`studio.sim.hand.PinchGrasp`).

The Sawyer and the hand demonstrate (role ``expert``), the Panda imitates (``agent``) and can demonstrate too.

Each robot exposes a *grasp site* at the point between its fingertips (the end-effector point used for
every target, label and recorded path) and a wrist depth camera looking along the gripper axis.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from studio.sim import hand
from studio.sim.recording import EMBODIMENT_OF_ROBOT

ROBOTS = tuple(EMBODIMENT_OF_ROBOT)


def package_dir(name: str) -> Path:
    """Where an installed package lives, without importing it (some print warnings on import)."""
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(f"package {name!r} is not installed; run ./run test or pip install -e .")
    return Path(next(iter(spec.submodule_search_locations)))


@dataclass(frozen=True)
class RobotInfo:
    """What the simulator needs to know about an arm.

    Attributes:
        name: ``"panda"``, ``"sawyer"`` or ``"hand"``.
        control: ``"joints"`` (IK → joint position actuators) or ``"mocap"`` (move the welded mocap body).
        arm_joints: names of the arm's joints, base to wrist (the hand's: its three slide joints).
        finger_joints: names of the finger joints (slides of the grippers, hinges of the hand).
        finger_actuators: names of the finger actuators.
        grasp_site: the site between the fingertips.
        wrist_camera: the depth camera on the hand.
        body_prefix: every robot body name starts with one of these (for gravity compensation / mirroring).
        max_opening: fingertip distance when fully open, metres.
    """

    name: str
    control: str
    arm_joints: tuple[str, ...]
    finger_joints: tuple[str, ...]
    finger_actuators: tuple[str, ...]
    grasp_site: str
    wrist_camera: str
    body_prefix: tuple[str, ...]
    max_opening: float

    def finger_ctrl(self, gripper: float) -> np.ndarray:
        """Actuator controls for a gripper command in [0, 1] (0 open, 1 closed)."""
        g = float(np.clip(gripper, 0.0, 1.0))
        if self.name == "hand":
            return g * hand.CLOSED_POSE
        if self.name == "panda":
            return np.array([0.04 * (1.0 - g), 0.04 * (1.0 - g)])
        a = 2.0 * g - 1.0
        return np.array([a, -a])


PANDA = RobotInfo(
    name="panda",
    control="joints",
    arm_joints=tuple(f"robot:panda0_joint{i}" for i in range(1, 8)),
    finger_joints=("robot:panda0_finger_joint1", "robot:panda0_finger_joint2"),
    finger_actuators=("r_gripper_finger_joint", "l_gripper_finger_joint"),
    grasp_site="grasp_site",
    wrist_camera="wrist",
    body_prefix=("panda0_", "robot_mount"),
    max_opening=0.08,
)

SAWYER = RobotInfo(
    name="sawyer",
    control="mocap",
    arm_joints=tuple(f"right_j{i}" for i in range(7)),
    finger_joints=("r_close", "l_close"),
    finger_actuators=("sawyer_finger_r", "sawyer_finger_l"),
    grasp_site="grasp_site",
    wrist_camera="wrist",
    body_prefix=(
        "base",
        "controller_box",
        "pedestal",
        "torso",
        "right_",
        "head",
        "screen",
        "hand",
        "rightclaw",
        "leftclaw",
        "rightpad",
        "leftpad",
        "robot_mount",
    ),
    max_opening=0.08,
)


HAND = RobotInfo(
    name="hand",
    control="mocap",
    arm_joints=hand.ROOT_JOINTS,
    finger_joints=hand.FINGER_JOINTS,
    finger_actuators=hand.FINGER_ACTUATORS,
    grasp_site=hand.GRASP_SITE,
    wrist_camera="wrist",
    body_prefix=("hand",),
    max_opening=0.11,
)


def robot_info(name: str) -> RobotInfo:
    if name == "panda":
        return PANDA
    if name == "sawyer":
        return SAWYER
    if name == "hand":
        return HAND
    raise ValueError(f"unknown robot {name!r}; choose from {ROBOTS}")


# Orientation of the grasp site for a top-down grasp with the fingers closing along world y (towards
# and away from the robot), the orientation the Sawyer's wrist reaches comfortably too: columns are
# the site's x, y (finger closing direction) and z (approach direction, pointing down).
TOP_DOWN = np.array([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])


def robot_xml(name: str) -> str:
    """An MJCF fragment set (assets, worldbody, actuators, equality) for the robot, absolute paths only."""
    if name == "hand":
        return hand.hand_xml()
    if name == "panda":
        franka = package_dir("gymnasium_robotics") / "envs/assets/kitchen_franka/franka_assets"
        return f"""
  <include file="{franka}/assets.xml"/>
  <compiler meshdir="{franka}/meshes"/>
  <worldbody>
    <body name="robot_mount" pos="0 0 0" euler="0 0 1.5707963267948966">
      <include file="{franka}/chain.xml"/>
    </body>
  </worldbody>
  <include file="{franka}/actuator.xml"/>
"""
    if name == "sawyer":
        mw = package_dir("metaworld") / "assets"
        return f"""
  <include file="{mw}/objects/assets/xyz_base_dependencies.xml"/>
  <compiler meshdir="{mw}/sawyer_xyz"/>
  <worldbody>
    <include file="{mw}/objects/assets/xyz_base.xml"/>
  </worldbody>
  <actuator>
    <position name="sawyer_finger_r" ctrllimited="true" ctrlrange="-1 1" joint="r_close" kp="400"/>
    <position name="sawyer_finger_l" ctrllimited="true" ctrlrange="-1 1" joint="l_close" kp="400"/>
  </actuator>
  <equality>
    <weld name="hand_weld" body1="mocap" body2="hand" relpose="0 0 0 1 0 0 0" solref="0.02 1"/>
  </equality>
"""
    raise ValueError(f"unknown robot {name!r}; choose from {ROBOTS}")


#: The Sawyer's wrist camera in its hand frame (the hand's +x axis is the gripper axis): 4 cm behind the hand
#: origin, looking down the gripper axis. Meta-World scenes re-mount one of their cameras here too.
SAWYER_WRIST_POS = (-0.04, 0.0, 0.0)
SAWYER_WRIST_XYAXES = (0.0, 1.0, 0.0, 0.0, 0.0, -1.0)
SAWYER_WRIST_FOVY = 75.0


def finish_spec(spec, info: RobotInfo, scene: str | None = None) -> None:
    """Edits the parsed spec before compiling: grasp site, wrist camera, gravity compensation, gains; for the
    hand its grasp welds and contacts, which depend on the ``scene`` (None: the robot alone)."""
    if info.name == "hand":
        hand.finish_spec(spec, scene)
    elif info.name == "panda":
        link7 = spec.body("panda0_link7")
        # Between the fingertip pads, on the gripper axis; x/y axes as in TOP_DOWN's convention
        # (y = finger closing direction).
        link7.add_site(
            name="grasp_site", pos=[0, 0, 0.226], quat=[0.92388, 0, 0, -0.382683], size=[0.006, 0, 0]
        )
        link7.add_camera(name="wrist", pos=[0.0, 0.0, 0.165], xyaxes=[1, 0, 0, 0, -1, 0], fovy=75)
        # The kitchen model's joint damping (100 on the shoulder, 10 on the forearm) makes the position
        # servos lag by ~0.1 s, which bends Cartesian paths by centimetres; keep damping/kp near 0.03 s.
        for i, j in enumerate(info.arm_joints):
            spec.joint(j).damping = 20.0 if i < 4 else 4.0
            spec.joint(j).armature = 0.1
        # The kitchen fingers squeeze with up to 70 N, which pops light round objects out of the grasp.
        for a in info.finger_actuators:
            act = spec.actuator(a)
            kp = 300.0
            act.gainprm[0] = kp
            act.biasprm[1] = -kp
            act.forcerange = [-20.0, 20.0]
    else:
        sawyer_hand = spec.body("hand")
        # The hand's +x axis is the gripper axis; the pads (centred on the hand origin) close along hand y.
        sawyer_hand.add_site(name="grasp_site", pos=[0.0, 0, 0], size=[0.006, 0, 0])
        sawyer_hand.add_camera(
            name="wrist", pos=list(SAWYER_WRIST_POS), xyaxes=list(SAWYER_WRIST_XYAXES), fovy=SAWYER_WRIST_FOVY
        )
    for body in spec.bodies:
        if body.name.startswith(info.body_prefix):
            body.gravcomp = 1.0
