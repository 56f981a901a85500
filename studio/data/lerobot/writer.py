"""LeRobot v3.0 export: write the store's episodes (those with per-step arrays) as a dataset.

Owns writing the files of :mod:`studio.data.lerobot.schema`: data rows at the control rate, one MP4 frame
per row (encoded as LeRobot encodes: SVT-AV1, a keyframe every 2 frames, CRF 30), per-episode and aggregated
statistics computed as LeRobot computes them (quantiles q01..q99 included), and the studio's ``osvi/*``
episode columns.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from studio.data.episode import Episode, EpisodeMeta, read_arrays, read_meta
from studio.data.lerobot.schema import (
    ARRAY_FEATURES,
    CODEBASE_VERSION,
    DATA_PATH,
    EPISODES_PATH,
    EXACT_PREFIX,
    INFO_PATH,
    QUANTILE_KEYS,
    QUANTILES,
    RENDERED,
    STATS_PATH,
    TASKS_PATH,
    VIDEO_CODEC,
    VIDEO_CRF,
    VIDEO_GOP,
    VIDEO_KEY,
    VIDEO_PATH,
    VIDEO_PRESET,
    LeRobotError,
    studio_features,
    task_instruction,
)
from studio.data.store import EpisodeStore
from studio.sim.camera import CameraModel


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


#: The encoders ``codec`` may name, and their options besides the keyframe interval and quality.
CODECS = {"libsvtav1": {"preset": str(VIDEO_PRESET)}, "libx264": {}}


class _VideoFile:
    """One MP4 of back-to-back episodes at a constant frame rate, encoded with LeRobot's settings."""

    def __init__(self, path: Path, fps: int, height: int, width: int, codec: str, crf: int) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its configuration to stderr otherwise
        self.path = path
        self.container = av.open(str(path), mode="w", format="mp4")
        options = {"g": str(VIDEO_GOP), "crf": str(crf), **CODECS[codec]}
        stream = self.container.add_stream(codec, rate=Fraction(fps), options=options)
        assert isinstance(stream, av.VideoStream)
        self.stream = stream
        self.stream.width, self.stream.height = width + width % 2, height + height % 2
        self.stream.pix_fmt = "yuv420p"
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


def _quantile(hist: np.ndarray, edges: np.ndarray, target: float) -> float:
    """One quantile from a histogram, interpolated within its bin (LeRobot's ``_compute_single_quantile``)."""
    cumsum = np.cumsum(hist)
    i = int(np.searchsorted(cumsum, target))
    if i == 0:
        return float(edges[0])
    if i >= len(cumsum):
        return float(edges[-1])
    before = cumsum[i - 1]
    inside = cumsum[i] - before
    if inside == 0:
        return float(edges[i])
    return float(edges[i] + (target - before) / inside * (edges[i + 1] - edges[i]))


def _vector_stats(v: np.ndarray, count: int) -> dict[str, np.ndarray]:
    """Stats of (N, D) samples as LeRobot's ``get_feature_stats`` makes them: min, max, mean, std, count and
    the quantiles of a 5000-bin histogram per dimension (every quantile = the mean below 2 samples)."""
    out = {"min": v.min(0), "max": v.max(0), "mean": v.mean(0), "count": np.array([count])}
    if len(v) < 2:
        out["std"] = v.std(0)
        out.update({k: out["mean"].copy() for k in QUANTILE_KEYS})
        return out
    out["std"] = np.sqrt(np.maximum(0.0, (v**2).mean(0) - out["mean"] ** 2))
    for key in QUANTILE_KEYS:
        out[key] = np.empty(v.shape[1])
    for d in range(v.shape[1]):
        edges = np.linspace(out["min"][d] - 1e-10, out["max"][d] + 1e-10, 5001)
        hist, _ = np.histogram(v[:, d], bins=edges)
        for key, q in zip(QUANTILE_KEYS, QUANTILES):
            out[key][d] = _quantile(hist, edges, q * len(v))
    return out


def _stats(values: np.ndarray, dtype: str) -> dict:
    """A per-step feature's stats over one episode, from the values as stored (``dtype``)."""
    v = np.asarray(values).astype(dtype).astype(np.float64).reshape(len(values), -1)
    return {k: a.tolist() for k, a in _vector_stats(v, len(v)).items()}


def _image_stats(frames: np.ndarray) -> dict:
    """Per-channel stats of a video feature as LeRobot samples them (evenly spaced frames, strided down when
    300 px or larger), scaled to [0, 1] and shaped (3, 1, 1). The std is the true one: LeRobot 0.4.4 squares
    uint8 pixels, which wraps, and stores 0."""
    n = len(frames)
    k = max(min(100, n), min(int(n**0.75), 10_000))
    picked = frames[np.round(np.linspace(0, n - 1, k)).astype(int)]
    h, w = picked.shape[1:3]
    if max(h, w) >= 300:
        step = int(w / 150) if w > h else int(h / 150)
        picked = picked[:, ::step, ::step]
    st = _vector_stats(picked.reshape(-1, 3).astype(np.float64), k)
    return {
        key: value.tolist() if key == "count" else (value / 255.0).reshape(3, 1, 1).tolist()
        for key, value in st.items()
    }


def _aggregate(stats: list[dict]) -> dict:
    """Combine per-episode stats as LeRobot's ``aggregate_stats`` does: min of mins, max of maxes,
    count-weighted means and quantiles, pooled std."""
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
            **{
                q: (w * np.array([s[key][q] for s in stats], dtype=np.float64)).sum(0).tolist()
                for q in QUANTILE_KEYS
            },
        }
    return out


def _column(values: np.ndarray, dtype: str) -> pa.Array:
    """A parquet column for a feature: a scalar column for shape (1,), a fixed-size list otherwise."""
    arr = np.asarray(values).astype(dtype)
    if arr.ndim == 1:
        return pa.array(arr)
    flat = pa.array(arr.reshape(-1))
    return pa.FixedSizeListArray.from_arrays(flat, type=pa.list_(flat.type, arr.shape[1]))


def _full_rate_frames(ep: Episode) -> tuple[np.ndarray, np.ndarray]:
    """Indices into ``ep.frames`` for every step (the latest rendered frame) and the rendered-step mask."""
    if ep.frame_steps is None:
        raise LeRobotError(f"episode {ep.meta.id} has no per-step arrays")
    num_steps = ep.meta.num_steps
    which = np.searchsorted(ep.frame_steps, np.arange(num_steps), side="right") - 1
    which = np.maximum(which, 0)
    rendered = np.zeros(num_steps, dtype=bool)
    rendered[ep.frame_steps] = True
    return which, rendered


def _episode_rows(ep: Episode, episode_index: int, first_index: int, task_index: int, fps: int) -> dict:
    a = ep.arrays
    T = ep.meta.num_steps
    nxt = np.concatenate([a["ee_pos_world"][1:], a["ee_pos_world"][-1:]], axis=0)
    _, rendered = _full_rate_frames(ep)
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
    video_files_size_in_mb: int = 200,
    codec: str = VIDEO_CODEC,
    crf: int = VIDEO_CRF,
) -> ExportReport:
    """Write the selected episodes (those with per-step arrays) as a LeRobot v3.0 dataset in ``out``.

    ``out`` must not exist or be an empty directory. All exported episodes must share control rate, frame
    size, joint count and object count (LeRobot features have one shape); filter by ``embodiment``
    otherwise. ``codec`` is ``libsvtav1`` (AV1, LeRobot's default) or ``libx264`` (H.264).
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise LeRobotError(f"{out} is a file; export into a new directory")
    if out.exists() and any(out.iterdir()):
        raise LeRobotError(f"{out} is not empty; export into a new directory")
    if codec not in CODECS:
        raise LeRobotError(f"codec must be one of {sorted(CODECS)}, got {codec!r}")
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
    if dt is None:
        raise LeRobotError(f"episode {metas[0].id} has per-step arrays but no control_dt")
    fps = round(1.0 / dt)
    if abs(fps * dt - 1.0) > 1e-6:
        raise LeRobotError(f"control rate 1/{dt} s is not a whole number of frames per second")
    studio_tasks = list(dict.fromkeys(m.task for m in metas))
    task_names = list(dict.fromkeys(task_instruction(t) for t in studio_tasks))
    if len(task_names) != len(studio_tasks):
        task_names = studio_tasks  # two studio tasks read alike: keep their names apart
    instruction = dict(zip(studio_tasks, task_names))
    task_index = {t: i for i, t in enumerate(task_names)}
    cameras = [read_meta(store.episode_dir(m.id))[1] for m in metas]
    first_cam = cameras[0]
    one_camera = all(
        np.array_equal(c.K, first_cam.K) and np.array_equal(c.T_world_cam, first_cam.T_world_cam)
        for c in cameras
    )
    shared = first_cam if one_camera else None

    out.mkdir(parents=True, exist_ok=True)
    first = store.load(metas[0].id)
    features = studio_features(first, fps, shared, codec)
    data_chunk = data_file = video_chunk = video_file = 0
    data_writer: pq.ParquetWriter | None = None
    data_bytes = 0.0
    vfile: _VideoFile | None = None
    episode_rows: list[dict] = []
    all_stats: list[dict] = []
    total = 0
    for ep_index, meta in enumerate(metas):
        ep = first if ep_index == 0 else store.load(meta.id)
        rows = _episode_rows(ep, ep_index, total, task_index[instruction[meta.task]], fps)
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
            vfile = _VideoFile(path, fps, meta.height, meta.width, codec, crf)
        which, _ = _full_rate_frames(ep)
        from_ts = vfile.frames / fps
        vfile.append(ep.frames[which])
        to_ts = vfile.frames / fps

        stats = {k: _stats(np.asarray(v), features[k]["dtype"]) for k, v in rows.items()}
        stats[VIDEO_KEY] = _image_stats(ep.frames[which])
        all_stats.append(stats)
        cam = cameras[ep_index]
        row = {
            "episode_index": ep_index,
            "tasks": [instruction[meta.task]],
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
            **{
                EXACT_PREFIX + name: np.asarray(ep.arrays[name], np.float64).ravel().tolist()
                for name in ARRAY_FEATURES.values()
            },
        }
        for feat, st in stats.items():
            for name, value in st.items():
                row[f"stats/{feat}/{name}"] = value
        episode_rows.append(row)
        total += meta.num_steps
    assert data_writer is not None and vfile is not None  # there was at least one episode to write
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
    return ExportReport(episodes=len(metas), frames=total, tasks=studio_tasks, skipped=skipped)


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
        "osvi/task": meta.task,
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
