"""Human demonstration videos into the store: ``studio import-video FILE --task T`` and the UI's upload.

Any container/codec FFmpeg reads (MP4, WebM, MOV, AVI, ...) is accepted. Frames are normalised to the
store's frame size (240×320 by default) in one of two ways:

* ``letterbox`` (default): scale to fit inside, pad the rest with black — nothing of the demonstration
  is cut off, at the price of bars when the aspect ratio differs;
* ``crop``: scale to cover, then cut the centre — no bars, but the edges of the view are lost.

The result is an expert episode with embodiment ``human``, source ``upload``, no per-step arrays, and a
*nominal* camera (45° vertical field of view on the original frame, mapped through the same letterbox or
crop; pose unknown, identity) flagged ``extra["camera_nominal"] = True``. Frame rates above ``fps_cap``
are thinned by timestamp.

Everything is checked and decoded before the store is touched, so a rejected file writes nothing. It is
rejected with a :class:`VideoImportError` when it is missing or empty, is not a video (e.g. a text file
renamed ``.mp4``), is corrupt or truncated, has fewer than ``min_frames`` frames (in the trimmed
segment), or exceeds the size or duration limit.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from studio.data import video
from studio.data.episode import Episode, EpisodeMeta, new_episode_id, scene_of_task
from studio.data.paths import add_data_dir_argument
from studio.data.store import EpisodeStore
from studio.sim.camera import CameraModel

FIT_MODES = ("letterbox", "crop")
NOMINAL_FOVY_DEG = 45.0


class VideoImportError(ValueError):
    """A video that cannot be imported; the message says why in one sentence for a person, ``detail`` (if any)
    what the decoder reported. Nothing was written."""

    def __init__(self, message: str, detail: str | None = None):
        super().__init__(message)
        self.detail = detail


@dataclass(frozen=True)
class ImportLimits:
    """Limits of an import. The duration limit applies to the (trimmed) segment that is imported."""

    max_bytes: int = 500 * 1024 * 1024
    max_duration_s: float = 120.0
    min_frames: int = 10


def fit_affine(src_hw: tuple[int, int], dst_hw: tuple[int, int], fit: str) -> np.ndarray:
    """The 3×3 pixel-space affine map from source pixels to normalised-frame pixels."""
    if fit not in FIT_MODES:
        raise ValueError(f"fit must be one of {FIT_MODES}, got {fit!r}")
    (sh, sw), (dh, dw) = src_hw, dst_hw
    scale = min(dh / sh, dw / sw) if fit == "letterbox" else max(dh / sh, dw / sw)
    tx, ty = (dw - sw * scale) / 2.0, (dh - sh * scale) / 2.0
    return np.array([[scale, 0.0, tx], [0.0, scale, ty], [0.0, 0.0, 1.0]])


def normalise_frames(frames: np.ndarray, size: tuple[int, int], fit: str) -> np.ndarray:
    """(F, h, w, 3) -> (F, H, W, 3) uint8 by letterbox or centre crop (see module docstring)."""
    A = fit_affine(frames.shape[1:3], size, fit)
    h, w = size
    shrink = A[0, 0] < 1.0
    out = np.empty((len(frames), h, w, 3), np.uint8)
    for i, f in enumerate(frames):
        out[i] = cv2.warpAffine(
            f,
            A[:2],
            (w, h),
            flags=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=(0, 0, 0),
        )
    return out


def thin_indices(times: np.ndarray, fps_cap: float | None, min_frames: int) -> np.ndarray:
    """Indices keeping at most ``fps_cap`` frames per second (by timestamp), never fewer than min_frames."""
    if fps_cap is None or len(times) < 2:
        return np.arange(len(times))
    keep, next_t = [], -np.inf
    for i, t in enumerate(times):
        if t >= next_t - 1e-6:
            keep.append(i)
            next_t = t + 1.0 / fps_cap
    if keep[-1] != len(times) - 1 and times[-1] - times[keep[-1]] > 0.5 / fps_cap:
        keep.append(len(times) - 1)
    return np.asarray(keep) if len(keep) >= min_frames else np.arange(len(times))


def load_human_video(
    file: str | os.PathLike,
    task: str,
    *,
    trim: tuple[float, float] | None = None,
    size: tuple[int, int] = (240, 320),
    fit: str = "letterbox",
    limits: ImportLimits = ImportLimits(),
    fps_cap: float | None = 15.0,
) -> Episode:
    """Check, decode and normalise a video into an (unsaved) human expert :class:`Episode`."""
    path = Path(file)
    name = path.name
    if not path.is_file():
        raise VideoImportError(f"{name}: no such file")
    n_bytes = path.stat().st_size
    if n_bytes == 0:
        raise VideoImportError(f"{name}: the file is empty")
    if n_bytes > limits.max_bytes:
        raise VideoImportError(
            f"{name}: {n_bytes / 2**20:.1f} MB is over the size limit of {limits.max_bytes / 2**20:.0f} MB"
        )
    if fit not in FIT_MODES:
        raise VideoImportError(f"fit must be one of {FIT_MODES}, got {fit!r}")
    try:
        scene_of_task(task)
    except ValueError as e:
        raise VideoImportError(str(e)) from e
    start: float | None = None
    end: float | None = None
    if trim is not None:
        start, end = float(trim[0]), float(trim[1])
        if not 0.0 <= start < end:
            raise VideoImportError(f"trim needs 0 <= START < END, got {start} {end}")
    try:
        info = video.probe_video(path)
    except video.VideoError as e:
        raise VideoImportError(
            f"{name} is not a video file the studio can read: it may be another kind of file, or damaged.",
            str(e).replace(f"{path}: ", ""),
        ) from e
    if info.duration_s is not None:
        if start is not None and start >= info.duration_s:
            raise VideoImportError(
                f"{name}: trim start {start:.2f} s is past the end ({info.duration_s:.2f} s)"
            )
        segment = (
            min(end, info.duration_s) - start if start is not None and end is not None else info.duration_s
        )
        if segment > limits.max_duration_s:
            raise VideoImportError(
                f"{name}: {segment:.1f} s is over the duration limit of {limits.max_duration_s:.0f} s"
                + ("" if trim else " (use --trim to import a part)")
            )
    rate = info.fps if info.fps > 0 else 30.0
    max_frames = int(limits.max_duration_s * rate * 1.5) + limits.min_frames
    try:
        decoded = video.read_video(path, start_s=start, end_s=end, max_frames=max_frames)
    except video.VideoError as e:
        raise VideoImportError(
            f"{name} could not be decoded to the end: it is truncated or corrupt, or longer than it says.",
            str(e).replace(f"{path}: ", ""),
        ) from e
    n = len(decoded.frames)
    if n < limits.min_frames:
        where = f" between {start:g} s and {end:g} s" if trim else ""
        raise VideoImportError(
            f"{name}: only {n} frames{where}; a demonstration needs at least {limits.min_frames}"
        )
    seconds = float(decoded.times[-1] - decoded.times[0]) + 1.0 / rate
    if seconds > limits.max_duration_s + 1.0 / rate:
        raise VideoImportError(
            f"{name}: {seconds:.1f} s is over the duration limit of {limits.max_duration_s:.0f} s"
        )
    if trim is None and info.num_frames and n < info.num_frames - 1:
        raise VideoImportError(
            f"{name}: the video is truncated or corrupt (the header says {info.num_frames} frames, {n} decode)"
        )
    if info.duration_s is not None and n > 1:
        expected_end = (min(end, info.duration_s) if end is not None else info.duration_s) - (start or 0.0)
        if decoded.times[-1] - (start or 0.0) < expected_end - max(0.5, 3.0 / rate):
            raise VideoImportError(f"{name}: the video is truncated or corrupt (frames stop early)")

    return demonstration_from_frames(
        decoded.frames,
        decoded.times,
        task,
        size=size,
        fit=fit,
        fps_cap=fps_cap,
        min_frames=limits.min_frames,
        source_fps=float(info.fps),
        extra={
            "original_name": name,
            "trim": None if trim is None else [start, end],
            "source_codec": info.codec,
        },
    )


def demonstration_from_frames(
    frames: np.ndarray,
    times: np.ndarray,
    task: str,
    *,
    size: tuple[int, int] = (240, 320),
    fit: str = "letterbox",
    fps_cap: float | None = 15.0,
    min_frames: int = ImportLimits.min_frames,
    source_fps: float | None = None,
    embodiment: str = "human",
    source: str = "upload",
    extra: dict | None = None,
) -> Episode:
    """Decoded frames ((F, h, w, 3) uint8 RGB at ``times`` s) as an (unsaved) expert :class:`Episode` of ``task``:
    thinned to ``fps_cap``, normalised to ``size`` by ``fit``, with the nominal camera (see the module docstring).

    The path of an uploaded video after decoding, and of a camera stream of a LeRobot dataset
    (:mod:`studio.data.lerobot.reader`). ``extra`` is added to the episode's ``extra``.
    """
    if fit not in FIT_MODES:
        raise VideoImportError(f"fit must be one of {FIT_MODES}, got {fit!r}")
    if len(frames) < min_frames:
        raise VideoImportError(f"only {len(frames)} frames; a demonstration needs at least {min_frames}")
    try:
        scene = scene_of_task(task)
    except ValueError as e:
        raise VideoImportError(str(e)) from e
    times = np.asarray(times, dtype=np.float64)
    rate = source_fps if source_fps else 30.0
    keep = thin_indices(times, fps_cap, min_frames)
    src = frames[keep]
    times = times[keep] - times[keep[0]]
    out = normalise_frames(src, size, fit)
    A = fit_affine(src.shape[1:3], size, fit)
    camera = CameraModel.from_fovy(NOMINAL_FOVY_DEG, src.shape[2], src.shape[1], np.eye(4)).with_pixel_affine(
        A, size[0], size[1]
    )
    fps = (len(times) - 1) / float(times[-1]) if len(times) > 1 and times[-1] > 0 else rate
    meta = EpisodeMeta(
        id=new_episode_id(),
        task=task,
        scene=scene,
        embodiment=embodiment,
        role="expert",
        source=source,
        seed=None,
        success=None,
        created=time.time(),
        num_frames=len(out),
        num_steps=0,
        height=size[0],
        width=size[1],
        fps=float(fps),
        extra={
            **(extra or {}),
            "source_size": [int(src.shape[1]), int(src.shape[2])],
            "source_fps": float(source_fps or 0.0),
            "fit": fit,
            "camera_nominal": True,
        },
    )
    return Episode(meta, camera, out, np.asarray(times, dtype=np.float64))


def import_video(
    store: EpisodeStore,
    file: str | os.PathLike,
    task: str,
    *,
    trim: tuple[float, float] | None = None,
    size: tuple[int, int] = (240, 320),
    fit: str = "letterbox",
    limits: ImportLimits = ImportLimits(),
    fps_cap: float | None = 15.0,
    known_tasks: list[str] | None = None,
) -> EpisodeMeta:
    """Import a human video as an expert episode of ``task``; the function behind the CLI and the UI upload.

    ``known_tasks``, if given, restricts ``task`` to those names. Raises :class:`VideoImportError`, with
    nothing written, for every rejected file.
    """
    if known_tasks is not None and task not in known_tasks:
        raise VideoImportError(f"unknown task {task!r}; known: {', '.join(known_tasks)}")
    ep = load_human_video(file, task, trim=trim, size=size, fit=fit, limits=limits, fps_cap=fps_cap)
    return store.add_episode(ep)


# ---------------------------------------------------------------------- CLI
def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", help="video file (MP4, WebM, MOV, AVI, ...)")
    parser.add_argument("--task", required=True, help="task it demonstrates, e.g. 'pick_place/cube->red'")
    parser.add_argument(
        "--trim", nargs=2, type=float, metavar=("START", "END"), help="keep only START..END s"
    )
    parser.add_argument("--fit", choices=FIT_MODES, default="letterbox", help="how to reach the frame size")
    parser.add_argument("--size", nargs=2, type=int, default=(240, 320), metavar=("H", "W"))
    parser.add_argument(
        "--max-mb", type=float, default=ImportLimits.max_bytes / 2**20, help="file size limit"
    )
    parser.add_argument(
        "--max-seconds", type=float, default=ImportLimits.max_duration_s, help="duration limit"
    )
    parser.add_argument(
        "--fps-cap", type=float, default=15.0, help="thin faster videos to this rate (0: keep all)"
    )
    parser.add_argument(
        "--allow-new-task", action="store_true", help="accept a task the simulator does not know"
    )
    add_data_dir_argument(parser)


def run(args: argparse.Namespace) -> int:
    known = None
    if not args.allow_new_task:
        from studio.sim.tasks import list_tasks

        known = list_tasks()
    limits = ImportLimits(max_bytes=int(args.max_mb * 2**20), max_duration_s=args.max_seconds)
    store = EpisodeStore(args.data_dir)
    report = store.check()
    if not report.ok:
        print(report.summary(), file=sys.stderr)
    try:
        meta = import_video(
            store,
            args.file,
            args.task,
            trim=tuple(args.trim) if args.trim else None,
            size=tuple(args.size),
            fit=args.fit,
            limits=limits,
            fps_cap=args.fps_cap or None,
            known_tasks=known,
        )
    except VideoImportError as e:
        print(f"studio import-video: rejected: {e}" + (f" ({e.detail})" if e.detail else ""), file=sys.stderr)
        return 2
    print(
        f"stored human demonstration {meta.id}: {meta.task}, {meta.num_frames} frames at {meta.fps:.1f} fps"
    )
    return 0
