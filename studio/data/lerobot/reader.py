"""LeRobot v3.0 import: bring a dataset's episodes into the store (source ``import``), as one of two kinds.

* **Trajectories**, when the dataset carries the studio's per-step features (``observation.qpos``,
  ``observation.ee_pos_world``, ``observation.ee_pos_cam``, ``observation.gripper_opening``,
  ``observation.environment_state``, ``osvi.gripper_cmd``, ``osvi.time`` — as
  :mod:`studio.data.lerobot.writer` writes them, or any dataset made with those names): per-step arrays,
  frames, camera and metadata. A studio export comes back exactly (the float64 arrays from its
  ``osvi/exact/*`` columns, the rendered frames from ``osvi.frame_rendered``, the camera from ``osvi/*``).
* **Demonstration videos**, from any dataset with a camera stream (a ``video`` or an ``image`` feature):
  each episode's frames become an expert demonstration of a task the user names, the way an uploaded
  human video does (:func:`studio.data.video_import.demonstration_from_frames`: thinned, letterboxed to the
  store's frame size, a nominal camera).

Everything is read and checked before the store is touched; the episodes are then added one by one, and a
failure removes the ones already added. Each imported episode records its origin in ``extra["lerobot"]``
(dataset directory, episode index, camera, a SHA-256 of its content: the data columns, and a demonstration's
frames); an episode whose content is already in the store is not imported again.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import av
import cv2
import numpy as np
import pyarrow as pa

from studio.data.episode import Episode, EpisodeMeta, new_episode_id, nominal_fps
from studio.data.lerobot.schema import (
    ARRAY_FEATURES,
    EXACT_PREFIX,
    INFO_PATH,
    LEGACY_NAMES,
    RENDERED,
    VIDEO_KEY,
    LeRobotError,
    task_instruction,
)
from studio.data.lerobot.validate import as_matrix, read_table, validate_dataset
from studio.data.store import EpisodeStore
from studio.data.video_import import (
    NOMINAL_FOVY_DEG,
    ImportLimits,
    VideoImportError,
    demonstration_from_frames,
    thin_indices,
)
from studio.sim.camera import CameraModel

KINDS = ("auto", "trajectories", "demonstrations")


@dataclass
class ImportPlan:
    """What :func:`read_lerobot` found: the episodes to store, and those already in the store."""

    kind: str
    episodes: list[Episode]
    already: list[str] = field(default_factory=list)


def _feature_names(features: dict) -> dict[str, str]:
    """The studio's feature name -> the dataset's name for it (current names, or the legacy ones)."""
    found = {}
    for name in [*ARRAY_FEATURES, RENDERED]:
        legacy = [old for old, new in LEGACY_NAMES.items() if new == name]
        for candidate in [name, *legacy]:
            if candidate in features:
                found[name] = candidate
                break
    return found


def camera_keys(features: dict) -> list[str]:
    """The dataset's camera streams: video and image features, the studio's own camera first."""
    keys = [k for k, ft in features.items() if ft.get("dtype") in ("video", "image")]
    return sorted(keys, key=lambda k: (k != VIDEO_KEY, keys.index(k)))


def read_lerobot(
    root: str | Path,
    *,
    kind: str = "auto",
    task: str | None = None,
    task_map: dict[str, str] | None = None,
    role: str | None = None,
    embodiment: str | None = None,
    known_tasks: Sequence[str] | None = None,
    camera: str | None = None,
    episodes: Sequence[int] | None = None,
    size: tuple[int, int] = (240, 320),
    fps_cap: float | None = 15.0,
    min_frames: int = 20,
) -> ImportPlan:
    """Read and check a LeRobot v3.0 dataset's episodes as unsaved :class:`Episode` objects (see the module
    docstring for the two kinds; ``auto`` picks trajectories when the studio's features are there).

    ``task`` names the studio task of demonstration videos (required for them; for trajectories it
    replaces every episode's task). ``task_map`` maps the dataset's task strings (or studio task names) to
    studio task names. ``camera`` picks the camera stream (default: the studio's, else the first).
    ``episodes`` picks episode indices (default: all). Raises :class:`LeRobotError` for anything wrong.
    """
    root = Path(root)
    if not root.is_dir():
        raise LeRobotError(f"{root}: no such directory")
    problems = validate_dataset(root)
    if problems:
        raise LeRobotError(f"{root} is not a valid LeRobot v3.0 dataset: " + "; ".join(problems[:5]))
    if kind not in KINDS:
        raise LeRobotError(f"kind must be one of {KINDS}, got {kind!r}")
    info = json.loads((root / INFO_PATH).read_text())
    features = info["features"]
    names = _feature_names(features)
    has_studio = all(k in names for k in ARRAY_FEATURES)
    if kind == "auto":
        kind = "trajectories" if has_studio else "demonstrations"
    cams = camera_keys(features)
    if camera is not None and camera not in cams:
        raise LeRobotError(f"{root}: no camera stream {camera!r}; its video and image features are {cams}")
    key = camera or (cams[0] if cams else None)
    if key is None:
        raise LeRobotError(f"{root}: the dataset has no camera stream (no video or image feature)")
    if kind == "trajectories" and not has_studio:
        lacking = [k for k in ARRAY_FEATURES if k not in names]
        raise LeRobotError(
            f"{root}: the dataset lacks the studio's per-step features {lacking}, so it cannot be imported as "
            "trajectories; import its camera stream as demonstration videos with --task TASK"
        )
    if kind == "demonstrations" and task is None:
        raise LeRobotError(
            f"{root}: without the studio's per-step features its camera stream ({key}) imports as demonstration "
            "videos: name the studio task they show with --task (e.g. push/blue-backward)"
        )
    all_eps = read_table(sorted((root / "meta/episodes").glob("chunk-*/file-*.parquet"))).to_pylist()
    if episodes is not None:
        wanted = set(episodes)
        unknown = sorted(wanted - {e["episode_index"] for e in all_eps})
        if unknown:
            raise LeRobotError(f"{root}: no episodes {unknown} (it has 0..{len(all_eps) - 1})")
        all_eps = [e for e in all_eps if e["episode_index"] in wanted]
    fps = int(info["fps"])
    tasks_of = {e["episode_index"]: _studio_task(e, task, task_map or {}) for e in all_eps}
    bad = sorted(
        {t for t in tasks_of.values() if "/" not in t or (known_tasks is not None and t not in known_tasks)}
    )
    if bad:
        raise LeRobotError(
            f"tasks {bad} are not studio tasks; name one with --task or map them with "
            "--task-map 'DATASET TASK=scene/task'"
        )
    data_files = sorted({(e["data/chunk_index"], e["data/file_index"]) for e in all_eps})
    data = read_table([root / info["data_path"].format(chunk_index=c, file_index=f) for c, f in data_files])
    row_of_index = {int(v): i for i, v in enumerate(as_matrix(data.column("index")))}
    # Demonstrations keep only the frames they are thinned to (at most fps_cap per second), so that long
    # episodes of large frames are never held in memory whole.
    keep = None
    if kind == "demonstrations":
        limit = ImportLimits().max_duration_s
        long = [e["episode_index"] for e in all_eps if e["length"] / fps > limit]
        if long:
            raise LeRobotError(
                f"{root}: episodes {long} are longer than the {limit:.0f} s a demonstration may last; "
                "leave them out with --episodes"
            )
        keep = {e["episode_index"]: thin_indices(np.arange(e["length"]) / fps, fps_cap, 10) for e in all_eps}
    frames_of = _camera_frames(root, info, key, all_eps, data, row_of_index, keep)
    origin = str(root.resolve())
    out: list[Episode] = []
    for e in all_eps:
        lo, hi = row_of_index[e["dataset_from_index"]], row_of_index[e["dataset_to_index"] - 1] + 1
        frames = frames_of[e["episode_index"]]
        digest = _content_hash(data.slice(lo, hi - lo), frames, kind, tasks_of[e["episode_index"]])
        source = {"dataset": origin, "episode_index": e["episode_index"], "camera": key, "sha256": digest}
        if kind == "trajectories":
            ep = _trajectory(e, data.slice(lo, hi - lo), names, frames, fps, features, tasks_of, min_frames)
            ep = ep.with_meta(
                role=role or ep.meta.role,
                embodiment=embodiment or ep.meta.embodiment,
                extra={**ep.meta.extra, "lerobot": source},
            )
        else:
            try:
                ep = demonstration_from_frames(
                    frames,
                    keep[e["episode_index"]] / fps if keep is not None else np.arange(len(frames)) / fps,
                    tasks_of[e["episode_index"]],
                    size=size,
                    fps_cap=fps_cap,
                    min_frames=10,
                    source_fps=float(fps),
                    embodiment=embodiment or "human",
                    source="import",
                    extra={"lerobot": source, "lerobot_task": e["tasks"][0] if e["tasks"] else None},
                )
            except VideoImportError as err:
                raise LeRobotError(f"{root}: episode {e['episode_index']}: {err}") from None
        out.append(ep)
    return ImportPlan(kind, out)


def _studio_task(e: dict, task: str | None, task_map: dict[str, str]) -> str:
    """The studio task of an episode: the user's ``task``, else its mapped task string, else the studio's
    own name for it (``osvi/task``, or a studio task whose instruction it is)."""
    if task is not None:
        return task
    text = e["tasks"][0] if e["tasks"] else ""
    if text in task_map:
        return task_map[text]
    studio = e.get("osvi/task") or _task_of_instruction(text) or text
    return task_map.get(studio, studio)


def _task_of_instruction(text: str) -> str | None:
    from studio.sim.tasks import list_tasks

    return next((t for t in list_tasks() if task_instruction(t) == text), None)


def _camera_frames(
    root: Path, info: dict, key: str, eps: list[dict], data: pa.Table, row_of_index, keep: dict | None
) -> dict[int, np.ndarray]:
    """Each episode's frames of camera ``key``: one per data row, or the rows ``keep[episode]`` (offsets in the
    episode). Each video file is decoded once, converting only the frames kept."""
    ft = info["features"][key]
    fps = info["fps"]
    wanted = {
        e["episode_index"]: keep[e["episode_index"]] if keep is not None else np.arange(e["length"])
        for e in eps
    }
    out = {}
    if ft["dtype"] == "image":
        blobs = data.column(key).combine_chunks().field("bytes").to_pylist()
        for e in eps:
            lo = row_of_index[e["dataset_from_index"]]
            out[e["episode_index"]] = np.stack(
                [
                    _decode_image(blobs[lo + int(i)], key, e["episode_index"])
                    for i in wanted[e["episode_index"]]
                ]
            )
        return out
    h, w = ft["shape"][0], ft["shape"][1]
    by_file: dict[tuple[int, int], list[dict]] = {}
    for e in eps:
        by_file.setdefault((e[f"videos/{key}/chunk_index"], e[f"videos/{key}/file_index"]), []).append(e)
    for (c, f), file_eps in sorted(by_file.items()):
        path = root / info["video_path"].format(video_key=key, chunk_index=c, file_index=f)
        slots: dict[
            int, tuple[int, int]
        ] = {}  # frame of the file -> (episode, position among its kept frames)
        for e in file_eps:
            first = round(e[f"videos/{key}/from_timestamp"] * fps)
            for j, i in enumerate(wanted[e["episode_index"]]):
                slots[first + int(i)] = (e["episode_index"], j)
        got: dict[int, list] = {
            e["episode_index"]: [None] * len(wanted[e["episode_index"]]) for e in file_eps
        }
        last = max(slots) if slots else -1
        try:
            with av.open(str(path)) as container:
                stream = container.streams.video[0]
                stream.thread_type = "AUTO"
                t0 = None
                for n, frame in enumerate(container.decode(stream)):
                    t = float(frame.time) if frame.time is not None else n / fps
                    t0 = t if t0 is None else t0
                    index = round((t - t0) * fps)
                    if index in slots:
                        ep_index, j = slots[index]
                        got[ep_index][j] = frame.to_ndarray(format="rgb24")[:h, :w]
                    if index >= last:
                        break
        except (av.error.FFmpegError, IndexError) as err:
            raise LeRobotError(f"{path.relative_to(root)}: cannot decode it ({err})") from None
        for e in file_eps:
            frames = got[e["episode_index"]]
            missing = sum(fr is None for fr in frames)
            if missing:
                raise LeRobotError(
                    f"episode {e['episode_index']}: {missing} of its frames are not in {path.relative_to(root)}"
                )
            out[e["episode_index"]] = np.stack(frames)
    return out


def _decode_image(blob: bytes | None, key: str, episode: int) -> np.ndarray:
    if not blob:
        raise LeRobotError(f"episode {episode}: an image of {key} has no bytes (images kept as paths only)")
    img = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise LeRobotError(f"episode {episode}: an image of {key} is not a PNG or JPEG")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _content_hash(rows: pa.Table, frames: np.ndarray, kind: str, task: str) -> str:
    """A SHA-256 of an episode's content, not of its place in the dataset: kind, task and data columns, and
    for demonstrations their frames. A trajectory's full-rate arrays identify it, so a re-encoded video (as
    LeRobot's editing tools write) is still the same trajectory."""
    h = hashlib.sha256(f"{kind}\n{task}\n".encode())
    for name in sorted(rows.column_names):
        if name in ("index", "episode_index", "task_index"):
            continue
        col = rows.column(name)
        if pa.types.is_struct(col.type):
            continue  # image bytes: their decoded pixels are hashed with the frames
        h.update(name.encode())
        h.update(np.ascontiguousarray(as_matrix(col)).tobytes())
    if kind == "demonstrations":
        h.update(np.ascontiguousarray(frames).tobytes())
    return h.hexdigest()


def _trajectory(e, rows: pa.Table, names, frames, fps, features, tasks_of, min_frames) -> Episode:
    T = rows.num_rows
    arrays = {}
    for feat, name in ARRAY_FEATURES.items():
        col = as_matrix(rows.column(names[feat]))
        v = np.asarray(col, dtype=np.float64)
        exact = e.get(EXACT_PREFIX + name)
        if exact is not None and len(exact) == v.size:
            x = np.asarray(exact, dtype=np.float64).reshape(v.shape)
            if np.array_equal(x.astype(col.dtype), col):  # the columns still hold these values, rounded
                v = x
        if name == "object_poses":
            v = v.reshape(T, -1, 7)
        elif features[names[feat]]["shape"] == [1]:
            v = v.reshape(T)
        arrays[name] = v
    steps = np.zeros(0, np.int64)
    if RENDERED in names:
        steps = np.flatnonzero(as_matrix(rows.column(names[RENDERED])).astype(bool).reshape(T)).astype(
            np.int64
        )
    if not len(steps):  # no flag, or no row flagged: evenly spaced frames
        steps = np.unique(np.round(np.linspace(0, T - 1, min(T, min_frames))).astype(np.int64))
    picked = np.ascontiguousarray(frames[steps])
    height, width = picked.shape[1:3]
    extra = json.loads(e.get("osvi/extra_json") or "{}")
    extra.pop("collect_seed", None)
    extra.pop("collect_index", None)
    if "osvi/camera_K" in e:
        camera = CameraModel(
            e["osvi/camera_width"],
            e["osvi/camera_height"],
            np.reshape(e["osvi/camera_K"], (3, 3)),
            np.reshape(e["osvi/camera_T_world_cam"], (4, 4)),
        )
    elif "camera.K" in features.get(VIDEO_KEY, {}).get("info", {}):
        shared = features[VIDEO_KEY]["info"]
        camera = CameraModel(
            width, height, np.asarray(shared["camera.K"]), np.asarray(shared["camera.T_world_cam"])
        )
    else:  # LeRobot has no field for camera parameters: a nominal one, flagged as such
        camera = CameraModel.from_fovy(NOMINAL_FOVY_DEG, width, height, np.eye(4))
        extra["camera_nominal"] = True
    extra.update(original_id=e.get("osvi/id"), original_source=e.get("osvi/source"))
    task = tasks_of[e["episode_index"]]
    dt = e.get("osvi/control_dt") or 1.0 / fps
    n_objects = arrays["object_poses"].shape[1]
    env_names = features[names["observation.environment_state"]]["names"]
    object_names = e.get("osvi/object_names") or [
        n.split(".")[0] for n in (env_names if isinstance(env_names, list) else [])[::7]
    ]
    if len(object_names) < n_objects:
        object_names = [f"object{k}" for k in range(n_objects)]
    meta = EpisodeMeta(
        id=new_episode_id(),
        task=task,
        scene=e.get("osvi/scene") or task.split("/", 1)[0],
        embodiment=e.get("osvi/embodiment") or "panda",
        role=e.get("osvi/role") or "agent",
        source="import",
        seed=e.get("osvi/seed"),
        success=e.get("osvi/success"),
        created=e.get("osvi/created") or time.time(),
        num_frames=len(picked),
        num_steps=T,
        height=height,
        width=width,
        fps=nominal_fps(steps, dt),
        control_dt=float(dt),
        object_names=tuple(object_names[:n_objects]),
        extra=extra,
    )
    return Episode(meta, camera, picked, arrays["time"][steps], steps, arrays)


def imported_hashes(store: EpisodeStore) -> dict[str, str]:
    """Content hash -> episode id of every episode imported from a LeRobot dataset."""
    out = {}
    for meta in store.episodes(source="import"):
        digest = (meta.extra.get("lerobot") or {}).get("sha256")
        if digest:
            out[digest] = meta.id
    return out


def store_plan(store: EpisodeStore, plan: ImportPlan) -> tuple[list[EpisodeMeta], list[str]]:
    """Add the plan's episodes whose content is not yet in the store; all or none (a failure removes the
    ones added). Returns the stored metadata and the ids of the episodes that were already there."""
    known = imported_hashes(store)
    fresh, already = [], []
    for ep in plan.episodes:
        digest = ep.meta.extra["lerobot"]["sha256"]
        if digest in known:
            already.append(known[digest])
        else:
            fresh.append(ep)
    added: list[EpisodeMeta] = []
    try:
        for ep in fresh:
            added.append(store.add_episode(ep))
    except BaseException:  # an interrupt too: all or none
        for meta in added:
            store.delete_episode(meta.id)
        raise
    return added, already


def import_lerobot(store: EpisodeStore, root: str | Path, **options) -> list[EpisodeMeta]:
    """Read a LeRobot v3.0 dataset (:func:`read_lerobot`, same options) and store its new episodes (source
    ``import``); episodes already imported are left out. Nothing is stored when anything is wrong."""
    added, _ = store_plan(store, read_lerobot(root, **options))
    return added
