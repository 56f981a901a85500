"""LeRobot dataset v3.0 interop: export the store's episodes, import trajectories back, validate the layout.

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

LeRobot itself is not a dependency (it pins older torch / numpy / PyAV); :func:`validate_dataset` checks
an exported directory against the documented schema instead.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from studio.data.episode import Episode, EpisodeMeta, new_episode_id, nominal_fps, read_arrays, read_meta
from studio.data.store import EpisodeStore
from studio.data.video import read_video
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


# ====================================================================== export
@dataclass
class ExportReport:
    episodes: int
    frames: int
    tasks: list[str]
    skipped: list[str] = field(default_factory=list)

    def summary(self) -> str:
        text = f"exported {self.episodes} episodes ({self.frames} frames, {len(self.tasks)} tasks)"
        if self.skipped:
            text += f"; skipped {len(self.skipped)} episodes without per-step arrays (human videos)"
        return text


class _VideoFile:
    """One MP4 of back-to-back episodes at a constant frame rate."""

    def __init__(self, path: Path, fps: int, height: int, width: int, crf: int) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.container = av.open(str(path), mode="w", format="mp4", options={"movflags": "+faststart"})
        self.stream = self.container.add_stream("libx264", rate=Fraction(fps))
        self.stream.width, self.stream.height = width + width % 2, height + height % 2
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": str(crf), "preset": "veryfast"}
        self.frames = 0

    def append(self, frames: np.ndarray) -> None:
        if frames.shape[1] % 2 or frames.shape[2] % 2:
            frames = np.pad(
                frames, ((0, 0), (0, frames.shape[1] % 2), (0, frames.shape[2] % 2), (0, 0)), mode="edge"
            )
        for f in frames:
            for packet in self.stream.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                self.container.mux(packet)
        self.frames += len(frames)

    def size_mb(self) -> float:
        return self.path.stat().st_size / 2**20

    def close(self) -> None:
        for packet in self.stream.encode():
            self.container.mux(packet)
        self.container.close()


def _next_file(chunk: int, file: int, chunks_size: int) -> tuple[int, int]:
    return (chunk + 1, 0) if file == chunks_size - 1 else (chunk, file + 1)


def _stats(values: np.ndarray) -> dict:
    v = values.astype(np.float64).reshape(len(values), -1)
    return {
        "min": v.min(0).tolist(),
        "max": v.max(0).tolist(),
        "mean": v.mean(0).tolist(),
        "std": v.std(0).tolist(),
        "count": [len(v)],
    }


def _image_stats(frames: np.ndarray) -> dict:
    """Per-channel stats of frames scaled to [0, 1], shaped (3, 1, 1) as LeRobot stores image stats."""
    x = frames.astype(np.float64) / 255.0
    per = lambda a: [[[float(c)]] for c in a]  # noqa: E731
    return {
        "min": per(x.min(axis=(0, 1, 2))),
        "max": per(x.max(axis=(0, 1, 2))),
        "mean": per(x.mean(axis=(0, 1, 2))),
        "std": per(x.std(axis=(0, 1, 2))),
        "count": [len(frames)],
    }


def _aggregate(stats: list[dict]) -> dict:
    """Combine per-episode stats: min of mins, max of maxes, count-weighted mean, pooled std."""
    out = {}
    for key in stats[0]:
        n = np.array([s[key]["count"][0] for s in stats], dtype=np.float64)
        mean = np.array([s[key]["mean"] for s in stats], dtype=np.float64)
        std = np.array([s[key]["std"] for s in stats], dtype=np.float64)
        w = n.reshape(-1, *([1] * (mean.ndim - 1))) / n.sum()
        total_mean = (w * mean).sum(0)
        total_var = (w * (std**2 + (mean - total_mean) ** 2)).sum(0)
        out[key] = {
            "min": np.min([s[key]["min"] for s in stats], axis=0).tolist(),
            "max": np.max([s[key]["max"] for s in stats], axis=0).tolist(),
            "mean": total_mean.tolist(),
            "std": np.sqrt(total_var).tolist(),
            "count": [int(n.sum())],
        }
    return out


def _column(values: np.ndarray, dtype: str) -> pa.Array:
    """A parquet column for a feature: a scalar column for shape (1,), a fixed-size list otherwise."""
    arr = np.asarray(values).astype(dtype)
    if arr.ndim == 1:
        return pa.array(arr)
    flat = pa.array(arr.reshape(-1))
    return pa.FixedSizeListArray.from_arrays(flat, type=pa.list_(flat.type, arr.shape[1]))


def _full_rate_frames(
    frames: np.ndarray, frame_steps: np.ndarray, num_steps: int
) -> tuple[np.ndarray, np.ndarray]:
    """Indices into ``frames`` for every step (the latest rendered frame) and the rendered-step mask."""
    which = np.searchsorted(frame_steps, np.arange(num_steps), side="right") - 1
    which = np.maximum(which, 0)
    rendered = np.zeros(num_steps, dtype=bool)
    rendered[frame_steps] = True
    return which, rendered


def _features(sample: Episode, fps: int, shared_camera: CameraModel | None) -> dict:
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


def _episode_rows(ep: Episode, episode_index: int, first_index: int, task_index: int, fps: int) -> dict:
    a = ep.arrays
    T = ep.meta.num_steps
    nxt = np.concatenate([a["ee_pos_world"][1:], a["ee_pos_world"][-1:]], axis=0)
    _, rendered = _full_rate_frames(ep.frames, ep.frame_steps, T)
    frame_index = np.arange(T, dtype=np.int64)
    return {
        "observation.state": np.concatenate([a["ee_pos_world"], a["gripper_opening"][:, None]], axis=1),
        "action": np.concatenate([nxt, a["gripper_cmd"][:, None]], axis=1),
        **{
            key: a[name].reshape(T, -1) if a[name].ndim > 1 else a[name]
            for key, name in ARRAY_FEATURES.items()
        },
        RENDERED: rendered,
        "timestamp": frame_index / fps,
        "frame_index": frame_index,
        "episode_index": np.full(T, episode_index, dtype=np.int64),
        "index": first_index + frame_index,
        "task_index": np.full(T, task_index, dtype=np.int64),
    }


def export_lerobot(
    store: EpisodeStore,
    out: str | Path,
    *,
    tasks: Sequence[str] | None = None,
    episode_ids: Sequence[str] | None = None,
    role: str | None = None,
    embodiment: str | None = None,
    source: str | Sequence[str] | None = None,
    robot_type: str | None = None,
    chunks_size: int = 1000,
    data_files_size_in_mb: int = 100,
    video_files_size_in_mb: int = 500,
    crf: int = 18,
) -> ExportReport:
    """Write the selected episodes (those with per-step arrays) as a LeRobot v3.0 dataset in ``out``.

    ``out`` must not exist or be empty. All exported episodes must share control rate, frame size,
    joint count and object count (LeRobot features have one shape); filter by ``embodiment`` otherwise.
    """
    out = Path(out)
    if out.exists() and any(out.iterdir()):
        raise LeRobotError(f"{out} is not empty; export into a new directory")
    if episode_ids is not None:
        metas = [store.get(i) for i in episode_ids]
    else:
        metas = store.episodes(
            tasks=list(tasks) if tasks else None, role=role, embodiment=embodiment, source=source
        )
    skipped = [m.id for m in metas if not m.has_arrays]
    metas = [m for m in metas if m.has_arrays]
    if not metas:
        raise LeRobotError("no episodes with per-step arrays match the selection")
    _check_uniform(store, metas)
    dt = metas[0].control_dt
    fps = round(1.0 / dt)
    if abs(fps * dt - 1.0) > 1e-6:
        raise LeRobotError(f"control rate 1/{dt} s is not a whole number of frames per second")
    task_names = list(dict.fromkeys(m.task for m in metas))
    task_index = {t: i for i, t in enumerate(task_names)}
    cameras = [read_meta(store.episode_dir(m.id))[1] for m in metas]
    shared = cameras[0]
    if any(
        not (np.array_equal(c.K, shared.K) and np.array_equal(c.T_world_cam, shared.T_world_cam))
        for c in cameras
    ):
        shared = None

    out.mkdir(parents=True, exist_ok=True)
    first = store.load(metas[0].id)
    features = _features(first, fps, shared)
    data_chunk = data_file = video_chunk = video_file = 0
    data_writer: pq.ParquetWriter | None = None
    data_bytes = 0.0
    vfile: _VideoFile | None = None
    episode_rows: list[dict] = []
    all_stats: list[dict] = []
    total = 0
    for ep_index, meta in enumerate(metas):
        ep = first if ep_index == 0 else store.load(meta.id)
        rows = _episode_rows(ep, ep_index, total, task_index[meta.task], fps)
        columns = {k: _column(v, features[k]["dtype"]) for k, v in rows.items()}
        table = pa.table(columns)
        if data_writer is not None and data_bytes + table.nbytes / 2**20 > data_files_size_in_mb:
            data_writer.close()
            data_writer, data_bytes = None, 0.0
            data_chunk, data_file = _next_file(data_chunk, data_file, chunks_size)
        if data_writer is None:
            path = out / DATA_PATH.format(chunk_index=data_chunk, file_index=data_file)
            path.parent.mkdir(parents=True, exist_ok=True)
            data_writer = pq.ParquetWriter(path, table.schema)
        data_writer.write_table(table)
        data_bytes += table.nbytes / 2**20

        if vfile is not None and vfile.size_mb() > video_files_size_in_mb:
            vfile.close()
            vfile = None
            video_chunk, video_file = _next_file(video_chunk, video_file, chunks_size)
        if vfile is None:
            path = out / VIDEO_PATH.format(
                video_key=VIDEO_KEY, chunk_index=video_chunk, file_index=video_file
            )
            vfile = _VideoFile(path, fps, meta.height, meta.width, crf)
        which, _ = _full_rate_frames(ep.frames, ep.frame_steps, meta.num_steps)
        from_ts = vfile.frames / fps
        vfile.append(ep.frames[which])
        to_ts = vfile.frames / fps

        stats = {k: _stats(np.asarray(v)) for k, v in rows.items()}
        stats[VIDEO_KEY] = _image_stats(ep.frames)
        all_stats.append(stats)
        cam = cameras[ep_index]
        row = {
            "episode_index": ep_index,
            "tasks": [meta.task],
            "length": meta.num_steps,
            "data/chunk_index": data_chunk,
            "data/file_index": data_file,
            "dataset_from_index": total,
            "dataset_to_index": total + meta.num_steps,
            f"videos/{VIDEO_KEY}/chunk_index": video_chunk,
            f"videos/{VIDEO_KEY}/file_index": video_file,
            f"videos/{VIDEO_KEY}/from_timestamp": from_ts,
            f"videos/{VIDEO_KEY}/to_timestamp": to_ts,
            "meta/episodes/chunk_index": 0,
            "meta/episodes/file_index": 0,
            **_osvi_columns(meta, cam),
        }
        for feat, st in stats.items():
            for name, value in st.items():
                row[f"stats/{feat}/{name}"] = value
        episode_rows.append(row)
        total += meta.num_steps
    data_writer.close()
    vfile.close()

    ep_path = out / EPISODES_PATH.format(chunk_index=0, file_index=0)
    ep_path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pylist(episode_rows), ep_path)
    _write_tasks(out, task_names)
    (out / STATS_PATH).write_text(json.dumps(_aggregate(all_stats), indent=2))
    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type or ",".join(sorted({m.embodiment for m in metas})),
        "total_episodes": len(metas),
        "total_frames": total,
        "total_tasks": len(task_names),
        "chunks_size": chunks_size,
        "data_files_size_in_mb": data_files_size_in_mb,
        "video_files_size_in_mb": video_files_size_in_mb,
        "fps": fps,
        "splits": {"train": f"0:{len(metas)}"},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH,
        "features": features,
    }
    (out / INFO_PATH).write_text(json.dumps(info, indent=4))
    return ExportReport(episodes=len(metas), frames=total, tasks=task_names, skipped=skipped)


def _check_uniform(store: EpisodeStore, metas: list[EpisodeMeta]) -> None:
    def describe(key) -> set:
        return {key(m) for m in metas}

    problems = []
    for label, key in (
        ("control_dt", lambda m: m.control_dt),
        ("frame size", lambda m: (m.height, m.width)),
        ("object count", lambda m: len(m.object_names)),
    ):
        values = describe(key)
        if len(values) > 1:
            problems.append(f"{label} differs: {sorted(values, key=str)}")
    joints = {read_arrays(store.episode_dir(m.id))[2]["qpos"].shape[1] for m in metas}
    if len(joints) > 1:
        problems.append(f"joint count differs: {sorted(joints)}")
    if problems:
        raise LeRobotError(
            "episodes cannot share one LeRobot dataset ("
            + "; ".join(problems)
            + "); filter by embodiment or task"
        )


def _osvi_columns(meta: EpisodeMeta, cam: CameraModel) -> dict:
    return {
        "osvi/id": meta.id,
        "osvi/scene": meta.scene,
        "osvi/embodiment": meta.embodiment,
        "osvi/role": meta.role,
        "osvi/source": meta.source,
        "osvi/seed": meta.seed,
        "osvi/success": meta.success,
        "osvi/created": meta.created,
        "osvi/control_dt": meta.control_dt,
        "osvi/object_names": list(meta.object_names),
        "osvi/extra_json": json.dumps(
            {**meta.extra, "collect_seed": meta.collect_seed, "collect_index": meta.collect_index},
            sort_keys=True,
        ),
        "osvi/camera_width": cam.width,
        "osvi/camera_height": cam.height,
        "osvi/camera_K": cam.K.reshape(-1).tolist(),
        "osvi/camera_T_world_cam": cam.T_world_cam.reshape(-1).tolist(),
    }


def _write_tasks(out: Path, task_names: list[str]) -> None:
    import pandas as pd

    df = pd.DataFrame(
        {"task_index": np.arange(len(task_names), dtype=np.int64)}, index=pd.Index(task_names, name="task")
    )
    (out / TASKS_PATH).parent.mkdir(parents=True, exist_ok=True)
    df.to_parquet(out / TASKS_PATH)


# ====================================================================== validation
_NUMPY_DTYPES = {
    "bool",
    "int8",
    "int16",
    "int32",
    "int64",
    "uint8",
    "uint16",
    "uint32",
    "uint64",
    "float16",
    "float32",
    "float64",
}
_INFO_KEYS = (
    "codebase_version",
    "robot_type",
    "total_episodes",
    "total_frames",
    "total_tasks",
    "chunks_size",
    "data_files_size_in_mb",
    "video_files_size_in_mb",
    "fps",
    "splits",
    "data_path",
    "video_path",
    "features",
)
_EPISODE_COLUMNS = (
    "episode_index",
    "tasks",
    "length",
    "data/chunk_index",
    "data/file_index",
    "dataset_from_index",
    "dataset_to_index",
    "meta/episodes/chunk_index",
    "meta/episodes/file_index",
)


def _read_table(paths: list[Path]) -> pa.Table:
    return pa.concat_tables([pq.read_table(p) for p in paths]) if paths else pa.table({})


def _as_matrix(col: pa.ChunkedArray) -> np.ndarray:
    arr = col.combine_chunks()
    if (
        pa.types.is_fixed_size_list(arr.type)
        or pa.types.is_list(arr.type)
        or pa.types.is_large_list(arr.type)
    ):
        n = len(arr)
        flat = np.asarray(arr.flatten().to_numpy(zero_copy_only=False))
        return flat.reshape(n, -1)
    return np.asarray(arr.to_numpy(zero_copy_only=False))


def validate_dataset(root: str | Path) -> list[str]:
    """Problems of a directory as a LeRobot v3.0 dataset (empty when it follows the documented schema)."""
    root = Path(root)
    problems: list[str] = []
    info_path = root / INFO_PATH
    if not info_path.is_file():
        return [f"missing {INFO_PATH}"]
    try:
        info = json.loads(info_path.read_text())
    except json.JSONDecodeError as e:
        return [f"{INFO_PATH} is not JSON: {e}"]
    missing = [k for k in _INFO_KEYS if k not in info]
    if missing:
        return [f"{INFO_PATH} lacks {missing}"]
    if info["codebase_version"] != CODEBASE_VERSION:
        problems.append(f"codebase_version is {info['codebase_version']!r}, expected {CODEBASE_VERSION!r}")
    fps = info["fps"]
    if not isinstance(fps, int) or fps <= 0:
        problems.append(f"fps must be a positive integer, got {fps!r}")
        fps = 1
    features: dict = info["features"]
    for name, ft in features.items():
        if "/" in name:
            problems.append(f"feature name {name!r} contains '/'")
        if not {"dtype", "shape", "names"} <= set(ft):
            problems.append(f"feature {name!r} lacks dtype/shape/names")
            continue
        if ft["dtype"] not in _NUMPY_DTYPES | {"video", "image", "string"}:
            problems.append(f"feature {name!r} has unknown dtype {ft['dtype']!r}")
        if not (isinstance(ft["shape"], list) and all(isinstance(s, int) and s > 0 for s in ft["shape"])):
            problems.append(f"feature {name!r} has a bad shape {ft['shape']!r}")
        elif (
            ft["names"] is not None
            and ft["dtype"] not in ("video", "image")
            and len(ft["names"]) != ft["shape"][-1]
        ):
            problems.append(f"feature {name!r} has {len(ft['names'])} names for shape {ft['shape']}")
    for name, ft in DEFAULT_FEATURES.items():
        if (
            name not in features
            or features[name]["dtype"] != ft["dtype"]
            or list(features[name]["shape"]) != [1]
        ):
            problems.append(f"default feature {name!r} missing or not {ft['dtype']} (1,)")
    video_keys = [k for k, ft in features.items() if ft.get("dtype") == "video"]
    if video_keys and not info["video_path"]:
        problems.append("video features but no video_path")
    if problems:
        return problems

    # tasks
    try:
        import pandas as pd

        tasks = pd.read_parquet(root / TASKS_PATH)
    except (OSError, ValueError) as e:
        return [f"cannot read {TASKS_PATH}: {e}"]
    if tasks.index.name != "task" or "task_index" not in tasks.columns:
        problems.append(f"{TASKS_PATH} must have index 'task' and column 'task_index'")
        return problems
    if sorted(tasks["task_index"].tolist()) != list(range(len(tasks))):
        problems.append("task_index values are not 0..n-1")
    if len(tasks) != info["total_tasks"]:
        problems.append(f"total_tasks is {info['total_tasks']} but tasks.parquet has {len(tasks)}")
    task_names = set(tasks.index)

    # episodes
    ep_files = sorted((root / "meta/episodes").glob("chunk-*/file-*.parquet"))
    if not ep_files:
        return [*problems, "no meta/episodes/chunk-XXX/file-XXX.parquet"]
    eps = _read_table(ep_files)
    need = list(_EPISODE_COLUMNS)
    for key in video_keys:
        need += [f"videos/{key}/{c}" for c in ("chunk_index", "file_index", "from_timestamp", "to_timestamp")]
    lacking = [c for c in need if c not in eps.column_names]
    if lacking:
        return [*problems, f"episodes parquet lacks columns {lacking}"]
    ep = {c: eps.column(c).to_pylist() for c in need}
    n_eps = len(ep["episode_index"])
    if ep["episode_index"] != list(range(n_eps)):
        problems.append("episode_index is not 0..n-1 in order")
    if n_eps != info["total_episodes"]:
        problems.append(f"total_episodes is {info['total_episodes']} but the episodes table has {n_eps}")
    expected_from = 0
    for i in range(n_eps):
        f, t, length = ep["dataset_from_index"][i], ep["dataset_to_index"][i], ep["length"][i]
        if f != expected_from or t - f != length:
            problems.append(f"episode {i}: rows [{f}, {t}) do not follow on / match length {length}")
        expected_from = t
        if not set(ep["tasks"][i]) <= task_names:
            problems.append(f"episode {i}: tasks {ep['tasks'][i]} not in tasks.parquet")
    if expected_from != info["total_frames"]:
        problems.append(f"total_frames is {info['total_frames']} but episodes cover {expected_from} rows")

    # data
    data_files = sorted({(c, f) for c, f in zip(ep["data/chunk_index"], ep["data/file_index"])})
    paths = [root / info["data_path"].format(chunk_index=c, file_index=f) for c, f in data_files]
    absent = [str(p.relative_to(root)) for p in paths if not p.is_file()]
    if absent:
        return [*problems, f"missing data files {absent}"]
    data = _read_table(paths)
    columns = [k for k, ft in features.items() if ft["dtype"] not in ("video", "image")]
    if sorted(data.column_names) != sorted(columns):
        problems.append(
            f"data columns {sorted(data.column_names)} differ from the non-video features {sorted(columns)}"
        )
        return problems
    for name in columns:
        ft = features[name]
        col = data.column(name)
        if ft["shape"] == [1]:
            if pa.types.is_list(col.type) or pa.types.is_fixed_size_list(col.type):
                problems.append(f"column {name!r} of shape (1,) must be a scalar column")
            elif col.type != pa.from_numpy_dtype(np.dtype(ft["dtype"])):
                problems.append(f"column {name!r} is {col.type}, feature says {ft['dtype']}")
        else:
            size = math.prod(ft["shape"])
            if not pa.types.is_fixed_size_list(col.type) and not pa.types.is_list(col.type):
                problems.append(f"column {name!r} of shape {ft['shape']} must be a list column")
            elif pa.types.is_fixed_size_list(col.type) and col.type.list_size != size:
                problems.append(f"column {name!r} has lists of {col.type.list_size}, shape says {size}")
            elif col.type.value_type != pa.from_numpy_dtype(np.dtype(ft["dtype"])):
                problems.append(f"column {name!r} holds {col.type.value_type}, feature says {ft['dtype']}")
    if data.num_rows != info["total_frames"]:
        problems.append(f"data has {data.num_rows} rows, total_frames is {info['total_frames']}")
    if problems:
        return problems
    index = _as_matrix(data.column("index"))
    if not np.array_equal(index, np.arange(data.num_rows)):
        problems.append("index column is not 0..total_frames-1")
    episode_index = _as_matrix(data.column("episode_index"))
    frame_index = _as_matrix(data.column("frame_index"))
    timestamp = _as_matrix(data.column("timestamp"))
    task_index = _as_matrix(data.column("task_index"))
    for i in range(n_eps):
        f, t = ep["dataset_from_index"][i], ep["dataset_to_index"][i]
        if not np.all(episode_index[f:t] == i):
            problems.append(f"episode {i}: episode_index column disagrees with its row range")
        if not np.array_equal(frame_index[f:t], np.arange(t - f)):
            problems.append(f"episode {i}: frame_index is not 0..length-1")
        if np.abs(timestamp[f:t] - np.arange(t - f) / fps).max(initial=0) > 1e-4:
            problems.append(f"episode {i}: timestamps are not frame_index / fps")
    if task_index.size and (task_index.min() < 0 or task_index.max() >= len(tasks)):
        problems.append("task_index column refers to unknown tasks")

    # videos
    for key in video_keys:
        ft = features[key]
        h, w = ft["shape"][0], ft["shape"][1]
        per_file: dict[tuple[int, int], float] = {}
        for i in range(n_eps):
            c, f = ep[f"videos/{key}/chunk_index"][i], ep[f"videos/{key}/file_index"][i]
            a, b = ep[f"videos/{key}/from_timestamp"][i], ep[f"videos/{key}/to_timestamp"][i]
            if abs((b - a) * fps - ep["length"][i]) > 1e-3:
                problems.append(f"episode {i}: video span {a}..{b} s is not length/fps")
            per_file[(c, f)] = max(per_file.get((c, f), 0.0), b)
        for (c, f), end in per_file.items():
            path = root / info["video_path"].format(video_key=key, chunk_index=c, file_index=f)
            if not path.is_file():
                problems.append(f"missing video {path.relative_to(root)}")
                continue
            with av.open(str(path)) as container:
                stream = container.streams.video[0]
                if (stream.codec_context.height, stream.codec_context.width) != (h + h % 2, w + w % 2):
                    problems.append(f"{path.relative_to(root)} is not {h}x{w}")
                n_frames = stream.frames or sum(1 for _ in container.demux(stream) if _.size)
            if n_frames < round(end * fps):
                problems.append(
                    f"{path.relative_to(root)} has {n_frames} frames, episodes need {round(end * fps)}"
                )
    if not (root / STATS_PATH).is_file():
        problems.append(f"missing {STATS_PATH}")
    return problems


# ====================================================================== import
def _parse_task_map(items: Sequence[str] | None) -> dict[str, str]:
    out = {}
    for item in items or []:
        if item.endswith(".json") and Path(item).is_file():
            out.update(json.loads(Path(item).read_text()))
            continue
        if "=" not in item:
            raise LeRobotError(
                f"task map entries look like 'DATASET TASK=studio/task' or a JSON file, got {item!r}"
            )
        src, dst = item.rsplit("=", 1)
        out[src] = dst
    return out


def import_lerobot(
    store: EpisodeStore,
    root: str | Path,
    *,
    task_map: dict[str, str] | None = None,
    role: str | None = None,
    embodiment: str | None = None,
    known_tasks: Sequence[str] | None = None,
    min_frames: int = 20,
) -> list[EpisodeMeta]:
    """Bring a LeRobot v3.0 dataset's trajectories into the store (source ``import``).

    The dataset must carry the studio's per-step features (as written by :func:`export_lerobot`).
    ``task_map`` maps the dataset's task strings to studio task names (identity for unmapped ones).
    Role and embodiment come from the dataset's ``osvi/*`` columns unless given (default role ``agent``).
    Everything is read and checked before the first episode is stored.
    """
    root = Path(root)
    problems = validate_dataset(root)
    if problems:
        raise LeRobotError(f"{root} is not a valid LeRobot v3.0 dataset: " + "; ".join(problems[:5]))
    info = json.loads((root / INFO_PATH).read_text())
    features = info["features"]
    lacking = [k for k in ARRAY_FEATURES if k not in features]
    if lacking:
        raise LeRobotError(f"{root}: the dataset lacks the per-step features the studio needs: {lacking}")
    video_keys = [k for k, ft in features.items() if ft["dtype"] == "video"]
    key = VIDEO_KEY if VIDEO_KEY in video_keys else (video_keys[0] if video_keys else None)
    if key is None:
        raise LeRobotError(f"{root}: the dataset has no video feature")
    fps = info["fps"]
    task_map = dict(task_map or {})
    eps = _read_table(sorted((root / "meta/episodes").glob("chunk-*/file-*.parquet"))).to_pylist()
    mapped = {t: task_map.get(t, t) for e in eps for t in e["tasks"]}
    bad = sorted(
        {d for d in mapped.values() if known_tasks is not None and d not in known_tasks}
        | {d for d in mapped.values() if "/" not in d}
    )
    if bad:
        raise LeRobotError(
            f"tasks {bad} are not studio tasks; map them with --task-map 'DATASET TASK=scene/task'"
        )

    data_files = sorted({(e["data/chunk_index"], e["data/file_index"]) for e in eps})
    data = _read_table([root / info["data_path"].format(chunk_index=c, file_index=f) for c, f in data_files])
    cols = {
        name: _as_matrix(data.column(name))
        for name in [*ARRAY_FEATURES, "index"] + ([RENDERED] if RENDERED in features else [])
    }
    row_of_index = {int(v): i for i, v in enumerate(cols["index"])}
    shared_cam = features[key].get("info", {})

    # Decode each video file once, keeping the frames of rendered rows.
    episodes: list[Episode] = []
    by_file: dict[tuple[int, int], list[dict]] = {}
    for e in eps:
        by_file.setdefault((e[f"videos/{key}/chunk_index"], e[f"videos/{key}/file_index"]), []).append(e)
    for (c, f), file_eps in sorted(by_file.items()):
        h, w = features[key]["shape"][0], features[key]["shape"][1]
        decoded = read_video(
            root / info["video_path"].format(video_key=key, chunk_index=c, file_index=f), size=(h, w)
        )
        for e in file_eps:
            episodes.append(
                _episode_from_rows(
                    e,
                    cols,
                    row_of_index,
                    decoded.frames,
                    fps,
                    key,
                    shared_cam,
                    mapped,
                    features,
                    role,
                    embodiment,
                    min_frames,
                )
            )
    return [store.add_episode(ep) for ep in episodes]


def _episode_from_rows(
    e, cols, row_of_index, file_frames, fps, key, shared_cam, mapped, features, role, embodiment, min_frames
) -> Episode:
    lo, hi = row_of_index[e["dataset_from_index"]], row_of_index[e["dataset_to_index"] - 1] + 1
    T = hi - lo
    arrays = {}
    for feat, name in ARRAY_FEATURES.items():
        v = np.asarray(cols[feat][lo:hi], dtype=np.float64)
        if name == "object_poses":
            v = v.reshape(T, -1, 7)
        elif features[feat]["shape"] == [1]:
            v = v.reshape(T)
        arrays[name] = v
    if RENDERED in cols:
        steps = np.flatnonzero(np.asarray(cols[RENDERED][lo:hi], dtype=bool)).astype(np.int64)
    else:
        steps = np.unique(np.round(np.linspace(0, T - 1, min(T, min_frames))).astype(np.int64))
    first_frame = round(e[f"videos/{key}/from_timestamp"] * fps)
    if first_frame + T > len(file_frames):
        raise LeRobotError(
            f"episode {e['episode_index']}: its video has {len(file_frames) - first_frame} frames, needs {T}"
        )
    frames = np.ascontiguousarray(file_frames[first_frame + steps])
    if "osvi/camera_K" in e:
        camera = CameraModel(
            e["osvi/camera_width"],
            e["osvi/camera_height"],
            np.reshape(e["osvi/camera_K"], (3, 3)),
            np.reshape(e["osvi/camera_T_world_cam"], (4, 4)),
        )
    elif "camera.K" in shared_cam:
        camera = CameraModel(
            frames.shape[2],
            frames.shape[1],
            np.asarray(shared_cam["camera.K"]),
            np.asarray(shared_cam["camera.T_world_cam"]),
        )
    else:
        raise LeRobotError(f"episode {e['episode_index']}: no camera parameters (osvi/camera_K or camera.K)")
    extra = json.loads(e.get("osvi/extra_json") or "{}")
    extra.pop("collect_seed", None)
    extra.pop("collect_index", None)
    extra.update(
        original_id=e.get("osvi/id"),
        original_source=e.get("osvi/source"),
        lerobot_episode_index=e["episode_index"],
    )
    task = mapped[e["tasks"][0]]
    dt = e.get("osvi/control_dt") or 1.0 / fps
    n_objects = arrays["object_poses"].shape[1]
    names = e.get("osvi/object_names") or [
        n.split(".")[0] for n in features["observation.environment_state"]["names"][::7]
    ]
    meta = EpisodeMeta(
        id=new_episode_id(),
        task=task,
        scene=e.get("osvi/scene") or task.split("/", 1)[0],
        embodiment=embodiment or e.get("osvi/embodiment") or "panda",
        role=role or e.get("osvi/role") or "agent",
        source="import",
        seed=e.get("osvi/seed"),
        success=e.get("osvi/success"),
        created=e.get("osvi/created") or time.time(),
        num_frames=len(frames),
        num_steps=T,
        height=frames.shape[1],
        width=frames.shape[2],
        fps=nominal_fps(steps, dt),
        control_dt=float(dt),
        object_names=tuple(names[:n_objects]),
        extra=extra,
    )
    return Episode(meta, camera, frames, arrays["time"][steps], steps, arrays)


# ====================================================================== CLI helpers (used by export/import commands)
def add_export_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="new directory for the dataset")
    parser.add_argument("--tasks", nargs="+", default=None, help="only these tasks")
    parser.add_argument("--role", choices=("expert", "agent"), default=None, help="only this role")
    parser.add_argument("--embodiment", default=None, help="only this embodiment (sawyer, panda)")
    parser.add_argument("--source", nargs="+", default=None, help="only these sources")


def run_export(args: argparse.Namespace, store: EpisodeStore) -> int:
    try:
        report = export_lerobot(
            store, args.out, tasks=args.tasks, role=args.role, embodiment=args.embodiment, source=args.source
        )
    except LeRobotError as e:
        print(f"studio export lerobot: {e}", file=sys.stderr)
        return 2
    problems = validate_dataset(args.out)
    print(report.summary() + f" to {args.out}")
    for p in problems:
        print(f"  schema problem: {p}", file=sys.stderr)
    return 1 if problems else 0


def add_import_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", help="LeRobot v3.0 dataset directory")
    parser.add_argument(
        "--task-map",
        nargs="+",
        default=None,
        metavar="MAP",
        help="'DATASET TASK=scene/task' pairs or a JSON file {dataset task: studio task}",
    )
    parser.add_argument(
        "--role", choices=("expert", "agent"), default=None, help="override the role (default: agent)"
    )
    parser.add_argument("--embodiment", default=None, help="override the embodiment")


def run_import(args: argparse.Namespace, store: EpisodeStore) -> int:
    from studio.sim.tasks import list_tasks

    try:
        metas = import_lerobot(
            store,
            args.dir,
            task_map=_parse_task_map(args.task_map),
            role=args.role,
            embodiment=args.embodiment,
            known_tasks=list_tasks(),
        )
    except LeRobotError as e:
        print(f"studio import lerobot: {e}", file=sys.stderr)
        return 2
    print(f"imported {len(metas)} episodes from {args.dir}")
    return 0
