"""LeRobot v3.0 validation: check a dataset directory against the documented schema (without LeRobot).

Accepts what LeRobot itself writes: ``meta/tasks.parquet`` with the task as a named or unnamed index
(``__index_level_0__``) or a ``task`` column, and ``image`` features stored in the data parquet.
Also the reading helpers the importer shares (``read_table``, ``as_matrix``, ``read_tasks``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from studio.data.lerobot.schema import CODEBASE_VERSION, DEFAULT_FEATURES, INFO_PATH, STATS_PATH, TASKS_PATH

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


def read_table(paths: list[Path]) -> pa.Table:
    """The parquet files as one table (empty for no files)."""
    return pa.concat_tables([pq.read_table(p) for p in paths]) if paths else pa.table({})


def as_matrix(col: pa.ChunkedArray) -> np.ndarray:
    """A column as numpy: one row per value, list columns as a (rows, size) matrix."""
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


def read_tasks(root: Path) -> list[str]:
    """The task strings of ``meta/tasks.parquet`` in ``task_index`` order. Raises ``ValueError`` (with the
    reason) when the file cannot be read or has no task strings and indices."""
    import pandas as pd

    try:
        df = pd.read_parquet(root / TASKS_PATH)
    except (OSError, ValueError) as e:
        raise ValueError(f"cannot read {TASKS_PATH}: {e}") from None
    if "task_index" not in df.columns:
        raise ValueError(f"{TASKS_PATH} has no column 'task_index'")
    if "task" in df.columns:
        names = list(df["task"])
    elif "__index_level_0__" in df.columns:
        names = list(df["__index_level_0__"])
    else:
        names = list(df.index)
    if not all(isinstance(t, str) for t in names):
        raise ValueError(f"{TASKS_PATH} has no task strings (as its index or a 'task' column)")
    indices = [int(i) for i in df["task_index"]]
    if sorted(indices) != list(range(len(indices))):
        raise ValueError(f"{TASKS_PATH}: task_index values are not 0..n-1")
    by_index = dict(zip(indices, names))
    return [by_index[i] for i in range(len(indices))]


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
            isinstance(ft["names"], list)  # LeRobot also writes {"motors": [...]} and None
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
        tasks = read_tasks(root)
    except ValueError as e:
        return [str(e)]
    if len(tasks) != info["total_tasks"]:
        problems.append(f"total_tasks is {info['total_tasks']} but tasks.parquet has {len(tasks)}")
    task_names = set(tasks)

    # episodes
    ep_files = sorted((root / "meta/episodes").glob("chunk-*/file-*.parquet"))
    if not ep_files:
        return [*problems, "no meta/episodes/chunk-XXX/file-XXX.parquet"]
    eps = read_table(ep_files)
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
    data = read_table(paths)
    stored = [k for k, ft in features.items() if ft["dtype"] != "video"]
    if sorted(data.column_names) != sorted(stored):
        problems.append(
            f"data columns {sorted(data.column_names)} differ from the features stored in the data files "
            f"(all but videos) {sorted(stored)}"
        )
        return problems
    for name in stored:
        ft = features[name]
        col = data.column(name)
        if ft["dtype"] == "image":
            if not (pa.types.is_struct(col.type) and col.type.get_field_index("bytes") >= 0):
                problems.append(f"image column {name!r} is {col.type}, not a struct with 'bytes'")
        elif ft["dtype"] == "string":
            continue
        elif ft["shape"] == [1]:
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
    index = as_matrix(data.column("index"))
    if not np.array_equal(index, np.arange(data.num_rows)):
        problems.append("index column is not 0..total_frames-1")
    episode_index = as_matrix(data.column("episode_index"))
    frame_index = as_matrix(data.column("frame_index"))
    timestamp = as_matrix(data.column("timestamp"))
    task_index = as_matrix(data.column("task_index"))
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
