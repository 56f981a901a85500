"""LeRobot dataset v3.0 schema: the directory layout, the path templates, and the features the studio writes.

The layout follows LeRobot's ``CODEBASE_VERSION = "v3.0"`` (``src/lerobot/datasets/utils.py``)::

    meta/info.json                                   codebase_version, fps, features, totals, path templates
    meta/stats.json                                  min / max / mean / std / count per feature
    meta/tasks.parquet                               index "task" (the studio task name), column task_index
    meta/episodes/chunk-000/file-000.parquet         one row per episode (ranges, video timestamps, stats,
                                                     and the studio's own metadata under "osvi/...")
    data/chunk-000/file-000.parquet                  one row per control step of every episode
    videos/observation.images.external/chunk-000/file-000.mp4   episodes' frames back to back

Rows are control steps at ``fps = 1 / control_dt``, so every per-step array keeps its full rate. The
video has one frame per row: the most recent rendered frame (episodes render only some steps), and the
boolean column ``observation.frame_rendered`` marks the rows whose frame was freshly rendered, which is
how an import recovers exactly the stored frames. Per-step features (float64, nothing rounded):
``observation.qpos``, ``observation.ee_pos_world``, ``observation.ee_pos_cam``, ``observation.gripper_cmd``,
``observation.gripper_opening``, ``observation.environment_state`` (object poses, K×7) and
``observation.time``; for LeRobot policies also the float32 ``observation.state`` (end-effector xyz in
the world + gripper opening) and ``action`` (the end-effector position at the next step — the recording
keeps no commanded target — and the gripper command).

Camera parameters are not part of LeRobot's schema; they are kept per episode in the episodes table
(``osvi/camera_K``, ``osvi/camera_T_world_cam``, OpenCV axes) and, when all episodes share one camera, also
in the video feature's ``info`` (``camera.K``, ``camera.T_world_cam``), which LeRobot preserves.

LeRobot itself is not a dependency (it pins older torch / numpy / PyAV);
:func:`studio.data.lerobot.validate.validate_dataset` checks a directory against this schema instead.

Everything here is the shared vocabulary of ``writer`` (export), ``validate`` and ``reader`` (import).
"""

from __future__ import annotations

from studio.data.episode import Episode
from studio.sim.camera import CameraModel

CODEBASE_VERSION = "v3.0"
CHUNK_FILE = "chunk-{chunk_index:03d}/file-{file_index:03d}"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
TASKS_PATH = "meta/tasks.parquet"
EPISODES_PATH = "meta/episodes/" + CHUNK_FILE + ".parquet"
DATA_PATH = "data/" + CHUNK_FILE + ".parquet"
VIDEO_PATH = "videos/{video_key}/" + CHUNK_FILE + ".mp4"
VIDEO_KEY = "observation.images.external"
DEFAULT_FEATURES = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}
#: The studio's per-step features and the recording array each one carries.
ARRAY_FEATURES = {
    "observation.qpos": "qpos",
    "observation.ee_pos_world": "ee_pos_world",
    "observation.ee_pos_cam": "ee_pos_cam",
    "observation.gripper_cmd": "gripper_cmd",
    "observation.gripper_opening": "gripper_opening",
    "observation.environment_state": "object_poses",
    "observation.time": "time",
}
RENDERED = "observation.frame_rendered"
POSE_FIELDS = ("px", "py", "pz", "qw", "qx", "qy", "qz")


class LeRobotError(ValueError):
    """A dataset that cannot be exported, imported, or does not follow the v3.0 schema."""


def studio_features(sample: Episode, fps: int, shared_camera: CameraModel | None) -> dict:
    """The ``features`` of ``meta/info.json`` for episodes shaped like ``sample``: LeRobot's defaults, the
    video, ``observation.state`` / ``action`` for LeRobot policies and the studio's full-rate arrays."""
    J = sample.arrays["qpos"].shape[1]
    names = list(sample.meta.object_names) or [
        f"object{k}" for k in range(sample.arrays["object_poses"].shape[1])
    ]
    h, w = sample.meta.height, sample.meta.width
    video_info = {
        "video.height": h,
        "video.width": w,
        "video.codec": "h264",
        "video.pix_fmt": "yuv420p",
        "video.is_depth_map": False,
        "video.fps": fps,
        "video.channels": 3,
        "has_audio": False,
        "camera.convention": "opencv: x right, y down, z forward; T_world_cam maps camera to world",
    }
    if shared_camera is not None:
        video_info["camera.K"] = shared_camera.K.tolist()
        video_info["camera.T_world_cam"] = shared_camera.T_world_cam.tolist()
    return {
        VIDEO_KEY: {
            "dtype": "video",
            "shape": [h, w, 3],
            "names": ["height", "width", "channels"],
            "info": video_info,
        },
        "observation.state": {
            "dtype": "float32",
            "shape": [4],
            "names": ["ee_x", "ee_y", "ee_z", "gripper_opening"],
        },
        "action": {
            "dtype": "float32",
            "shape": [4],
            "names": ["ee_x_next", "ee_y_next", "ee_z_next", "gripper_cmd"],
        },
        "observation.qpos": {"dtype": "float64", "shape": [J], "names": [f"q{j}" for j in range(J)]},
        "observation.ee_pos_world": {"dtype": "float64", "shape": [3], "names": ["x", "y", "z"]},
        "observation.ee_pos_cam": {"dtype": "float64", "shape": [3], "names": ["x", "y", "z"]},
        "observation.gripper_cmd": {"dtype": "float64", "shape": [1], "names": None},
        "observation.gripper_opening": {"dtype": "float64", "shape": [1], "names": None},
        "observation.environment_state": {
            "dtype": "float64",
            "shape": [7 * len(names)],
            "names": [f"{o}.{c}" for o in names for c in POSE_FIELDS],
        },
        "observation.time": {"dtype": "float64", "shape": [1], "names": None},
        RENDERED: {"dtype": "bool", "shape": [1], "names": None},
        **DEFAULT_FEATURES,
    }
