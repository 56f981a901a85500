"""What one simulated episode produces: rendered frames plus full-rate per-step arrays and the camera.

A :class:`Recording` is the hand-over format from the simulator to the episode store (scripted
collection, browser teleop, rollouts all produce one). It holds no metadata about why it was made
(role, source); the store adds that.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from studio.sim.camera import CameraModel

#: The simulated robots and the embodiment their episodes are stored under (:mod:`studio.data.episode`): the
#: hand's are ``"human"``, like uploaded videos of people.
EMBODIMENT_OF_ROBOT: dict[str, str] = {"panda": "panda", "sawyer": "sawyer", "hand": "human"}


def embodiment_of(robot: str) -> str:
    """The embodiment a robot's recordings are stored under (``"human"`` for the hand)."""
    try:
        return EMBODIMENT_OF_ROBOT[robot]
    except KeyError:
        raise ValueError(f"unknown robot {robot!r}; choose from {tuple(EMBODIMENT_OF_ROBOT)}") from None


def robot_of(embodiment: str) -> str:
    """The simulated robot whose recordings have ``embodiment`` (the hand for ``"human"``)."""
    for robot, emb in EMBODIMENT_OF_ROBOT.items():
        if emb == embodiment:
            return robot
    raise ValueError(f"no simulated robot has the embodiment {embodiment!r}")


#: Names and per-step shapes of the arrays every recording carries (T = number of control steps).
ARRAY_FIELDS: dict[str, str] = {
    "time": "(T,) float64, seconds since reset",
    "qpos": "(T, J) float64, robot joint positions (arm joints then finger joints)",
    "ee_pos_world": "(T, 3) float64, end-effector (grasp point) position in the world frame",
    "ee_pos_cam": "(T, 3) float64, the same in the external camera frame (x right, y down, z forward)",
    "gripper_cmd": "(T,) float64, commanded gripper closure in [0, 1] (0 open, 1 closed)",
    "gripper_opening": "(T,) float64, distance between the fingertips, metres",
    "object_poses": "(T, K, 7) float64, free objects' position and quaternion (w, x, y, z) in the world",
}


@dataclass
class Recording:
    """One episode as recorded by the simulator.

    Attributes:
        scene: scene family, e.g. ``"pick_place"``.
        robot: ``"panda"``, ``"sawyer"`` or ``"hand"``.
        task: full task name, e.g. ``"pick_place/cube->red"``.
        seed: the seed the scene was reset with.
        success: the task's success predicate at the end of the episode.
        camera: the external camera the frames were rendered with.
        frames: (F, H, W, 3) uint8 RGB frames of the external camera.
        frame_steps: (F,) int64 index of the control step each frame was rendered at.
        arrays: per-step arrays, keys and shapes as in :data:`ARRAY_FIELDS`.
        object_names: names of the K objects in ``arrays["object_poses"]``.
        control_dt: seconds between two control steps.
    """

    scene: str
    robot: str
    task: str
    seed: int
    success: bool
    camera: CameraModel
    frames: np.ndarray
    frame_steps: np.ndarray
    arrays: dict[str, np.ndarray]
    object_names: list[str] = field(default_factory=list)
    control_dt: float = 0.02

    def __post_init__(self) -> None:
        missing = set(ARRAY_FIELDS) - set(self.arrays)
        if missing:
            raise ValueError(f"Recording.arrays lacks {sorted(missing)}")
        n = len(self.arrays["time"])
        for key in ARRAY_FIELDS:
            if len(self.arrays[key]) != n:
                raise ValueError(f"Recording.arrays[{key!r}] has {len(self.arrays[key])} steps, time has {n}")
        if self.frames.ndim != 4 or self.frames.shape[-1] != 3 or self.frames.dtype != np.uint8:
            raise ValueError(
                f"Recording.frames must be (F, H, W, 3) uint8, got {self.frames.shape} {self.frames.dtype}"
            )
        if len(self.frame_steps) != len(self.frames):
            raise ValueError("Recording.frame_steps must have one entry per frame")

    @property
    def num_steps(self) -> int:
        return len(self.arrays["time"])
