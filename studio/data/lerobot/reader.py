"""LeRobot v3.0 import: bring a dataset's trajectories into the store (source ``import``).

Reads datasets that carry the studio's per-step features (as :mod:`studio.data.lerobot.writer` writes them),
recovers the rendered frames from ``observation.frame_rendered`` and the camera from the ``osvi/*`` columns or
the video feature's ``info``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from studio.data.episode import Episode, EpisodeMeta, new_episode_id, nominal_fps
from studio.data.lerobot.schema import ARRAY_FEATURES, INFO_PATH, RENDERED, VIDEO_KEY, LeRobotError
from studio.data.lerobot.validate import as_matrix, read_table, validate_dataset
from studio.data.store import EpisodeStore
from studio.data.video import read_video
from studio.sim.camera import CameraModel


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
    eps = read_table(sorted((root / "meta/episodes").glob("chunk-*/file-*.parquet"))).to_pylist()
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
    data = read_table([root / info["data_path"].format(chunk_index=c, file_index=f) for c, f in data_files])
    cols = {
        name: as_matrix(data.column(name))
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
