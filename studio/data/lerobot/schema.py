"""LeRobot dataset v3.0 schema: the directory layout, the path templates, and the features the studio writes.

The layout follows LeRobot's ``CODEBASE_VERSION = "v3.0"`` (``src/lerobot/datasets/utils.py``)::

    meta/info.json                                   codebase_version, fps, features, totals, path templates
    meta/stats.json                                  min / max / mean / std / count / q01..q99 per feature
    meta/tasks.parquet                               index: the task (an instruction), column task_index
    meta/episodes/chunk-000/file-000.parquet         one row per episode (ranges, video timestamps, stats,
                                                     and the studio's own metadata under "osvi/...")
    data/chunk-000/file-000.parquet                  one row per control step of every episode
    videos/observation.images.external/chunk-000/file-000.mp4   episodes' frames back to back

Rows are control steps at ``fps = 1 / control_dt``, so every per-step array keeps its full rate. The
video has one frame per row: the most recent rendered frame (episodes render only some steps), and the
boolean column ``osvi.frame_rendered`` marks the rows whose frame was freshly rendered, which is how an
import recovers exactly the stored frames.

Every ``observation.*`` feature is a policy input, since LeRobot's policies take every one as such (a
bool there breaks their normalisation): ``observation.state`` (end-effector xyz in the world + gripper
opening), ``observation.environment_state`` (object poses, K×7), ``observation.qpos``,
``observation.ee_pos_world``, ``observation.ee_pos_cam``, ``observation.gripper_opening`` and the video.
``action`` is the end-effector position at the next step (the recording keeps no commanded target) and
the gripper command. The studio's other per-step columns are named ``osvi.*`` (``osvi.gripper_cmd``,
``osvi.time``, ``osvi.frame_rendered``), which LeRobot loads but no policy reads.

Numbers are float32: LeRobot hands float64 columns to policies as float32 anyway, so the features say
what a LeRobot user gets. The studio's recordings are float64; the exact values ride along per episode
in the episodes table (``osvi/exact/<array>``, flat float64 lists), so the studio's own export→import
round trip is exact, while the dataset's columns are those values rounded to float32.

Tasks are instructions in plain English (``pick up the bar and place it in the blue zone``), as LeRobot's
language-conditioned policies expect; the studio task name is kept per episode (``osvi/task``).

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
    "observation.gripper_opening": "gripper_opening",
    "observation.environment_state": "object_poses",
    "osvi.gripper_cmd": "gripper_cmd",
    "osvi.time": "time",
}
RENDERED = "osvi.frame_rendered"
#: Names earlier exports used, still read on import.
LEGACY_NAMES = {
    "observation.gripper_cmd": "osvi.gripper_cmd",
    "observation.time": "osvi.time",
    "observation.frame_rendered": RENDERED,
}
#: Episodes-table column prefix of the exact (float64) per-step arrays.
EXACT_PREFIX = "osvi/exact/"
#: LeRobot's video encoding defaults (``encode_video_frames`` in ``lerobot/datasets/video_utils.py``).
VIDEO_CODEC = "libsvtav1"
VIDEO_GOP = 2
VIDEO_CRF = 30
VIDEO_PRESET = 12
#: LeRobot's quantiles (``DEFAULT_QUANTILES`` in ``lerobot/datasets/compute_stats.py``) and their keys.
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
QUANTILE_KEYS = tuple(f"q{int(q * 100):02d}" for q in QUANTILES)
POSE_FIELDS = ("px", "py", "pz", "qw", "qx", "qy", "qz")


class LeRobotError(ValueError):
    """A dataset that cannot be exported, imported, or does not follow the v3.0 schema."""


def studio_features(
    sample: Episode, fps: int, shared_camera: CameraModel | None, codec: str = VIDEO_CODEC
) -> dict:
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
        "video.codec": "av1" if codec == "libsvtav1" else "h264",
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
        "observation.qpos": {"dtype": "float32", "shape": [J], "names": [f"q{j}" for j in range(J)]},
        "observation.ee_pos_world": {"dtype": "float32", "shape": [3], "names": ["x", "y", "z"]},
        "observation.ee_pos_cam": {"dtype": "float32", "shape": [3], "names": ["x", "y", "z"]},
        "observation.gripper_opening": {"dtype": "float32", "shape": [1], "names": None},
        "observation.environment_state": {
            "dtype": "float32",
            "shape": [7 * len(names)],
            "names": [f"{o}.{c}" for o in names for c in POSE_FIELDS],
        },
        "osvi.gripper_cmd": {"dtype": "float32", "shape": [1], "names": None},
        "osvi.time": {"dtype": "float32", "shape": [1], "names": None},
        RENDERED: {"dtype": "bool", "shape": [1], "names": None},
        **DEFAULT_FEATURES,
    }


_BOX_DIRECTION = {"forward": "forward, away from the robot", "backward": "backward, towards the robot"}


def task_instruction(task: str) -> str:
    """The plain-English instruction of a studio task (its name when the studio has no wording for it)."""
    scene, _, what = task.partition("/")
    if scene == "pick_place" and "->" in what:
        obj, target = what.split("->", 1)
        return f"pick up the {obj} and place it in the {target} zone"
    if scene == "push" and "-" in what:
        box, direction = what.split("-", 1)
        if direction in _BOX_DIRECTION:
            return f"push the {box} box {_BOX_DIRECTION[direction]}"
    if scene == "metaworld" and what:
        return "Meta-World: " + what.removesuffix("-v3").replace("-", " ")
    return task
