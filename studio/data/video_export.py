"""Stored episodes out as video files: ``studio export-video EPISODE_ID OUT.mp4 [--size H W] [--fps F]``.

The inverse of ``studio import-video``: any episode of the store (a simulated robot's, the simulated hand's, an
uploaded one) is written as an H.264 MP4 (see :mod:`studio.data.video`), optionally at another frame size and
frame rate, e.g. to hand a simulated human demonstration to the upload path as if a camera had filmed it.

Timing is kept: frame ``k`` of the output is shown at ``k / fps`` seconds and shows the episode's frame in force
then (the last one whose recorded time is not later), so a video at any rate lasts as long as the episode: from
its first frame to one frame interval (``1 / meta.fps``) past its last.
"""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from studio.data import video
from studio.data.paths import CATALOG_NAME, add_data_dir_argument, resolve_data_dir
from studio.data.store import EpisodeStore

#: The largest frame side and frame rate accepted.
MAX_SIDE = 4096
MAX_FPS = 240.0


class VideoExportError(ValueError):
    """An export that cannot be made; the message says why. Nothing was written."""


@dataclass(frozen=True)
class ExportedVideo:
    """What was written: the file, its frame size, rate, frame count and duration."""

    path: Path
    height: int
    width: int
    fps: float
    num_frames: int
    duration_s: float


def check_size(size: tuple[int, int] | None) -> None:
    """Raise :class:`VideoExportError` unless ``size`` is None or a positive even (H, W) up to MAX_SIDE."""
    if size is None:
        return
    h, w = size
    if not (0 < h <= MAX_SIDE and 0 < w <= MAX_SIDE):
        raise VideoExportError(f"size must be H W between 2 and {MAX_SIDE}, got {h} {w}")
    if h % 2 or w % 2:
        raise VideoExportError(f"size must be even (H.264 in yuv420p), got {h} {w}")


def check_fps(fps: float | None) -> None:
    """Raise :class:`VideoExportError` unless ``fps`` is None or in (0, MAX_FPS]."""
    if fps is not None and not (np.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise VideoExportError(f"fps must be above 0 and at most {MAX_FPS:g}, got {fps:g}")


def resample_indices(frame_times: np.ndarray, duration_s: float, fps: float) -> np.ndarray:
    """For each output frame ``k`` (at ``k / fps`` s, while before ``duration_s``): the source frame in force.

    That is the last source frame whose time (relative to the first) is not later; at least one frame.
    """
    times = np.asarray(frame_times, dtype=np.float64)
    times = times - times[0]
    n = max(1, round(float(duration_s) * float(fps)))
    out_times = np.arange(n) / fps
    idx = np.searchsorted(times, out_times + 1e-9, side="right") - 1
    return np.clip(idx, 0, len(times) - 1)


def episode_duration(frame_times: np.ndarray, fps: float) -> float:
    """From the first frame to one frame interval past the last."""
    times = np.asarray(frame_times, dtype=np.float64)
    return float(times[-1] - times[0]) + 1.0 / fps


def export_episode_video(
    store: EpisodeStore,
    episode_id: str,
    out: str | os.PathLike,
    *,
    size: tuple[int, int] | None = None,
    fps: float | None = None,
) -> ExportedVideo:
    """Write the frames of a stored episode as an MP4 at ``size`` (H, W) and ``fps`` (default: the episode's)."""
    check_size(size)
    check_fps(fps)
    out = Path(out)
    if not out.parent.is_dir():
        raise VideoExportError(f"{out.parent}: no such directory")
    try:
        meta = store.get(episode_id)
    except KeyError:
        raise VideoExportError(f"no episode {episode_id!r} in {store.root}") from None
    frames = store.load_frames(episode_id)
    frame_times, _, _ = store.load_arrays(episode_id)
    if len(frames) == 0 or len(frame_times) != len(frames):
        raise VideoExportError(
            f"episode {episode_id}: {len(frames)} frames decode but {len(frame_times)} frame times are stored"
        )
    rate = float(fps) if fps is not None else float(meta.fps)
    idx = resample_indices(frame_times, episode_duration(frame_times, meta.fps), rate)
    picked = frames[idx]
    h, w = size if size is not None else picked.shape[1:3]
    if (h, w) != picked.shape[1:3]:
        shrink = h < picked.shape[1] or w < picked.shape[2]
        interp = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        picked = np.stack([cv2.resize(f, (w, h), interpolation=interp) for f in picked])
    try:
        video.write_video(out, picked, rate)
    except video.VideoError as e:
        raise VideoExportError(f"{out}: {e}") from e
    return ExportedVideo(out, int(h), int(w), rate, len(picked), len(picked) / rate)


# ---------------------------------------------------------------------- CLI
def _size(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number of pixels: {text!r}") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("episode", help="id of a stored episode")
    parser.add_argument("out", help="video file to write (MP4, H.264)")
    parser.add_argument(
        "--size", nargs=2, type=_size, metavar=("H", "W"), help="frame size (even; default: the episode's)"
    )
    parser.add_argument(
        "--fps", type=float, help="frame rate; the episode's timing is kept (default: the episode's rate)"
    )
    add_data_dir_argument(parser)


def run(args: argparse.Namespace) -> int:
    root = resolve_data_dir(args.data_dir)
    try:
        check_size(tuple(args.size) if args.size else None)
        check_fps(args.fps)
        if not (root / CATALOG_NAME).is_file():
            raise VideoExportError(f"no episode store in {root}")
        with EpisodeStore(root) as store:
            done = export_episode_video(
                store, args.episode, args.out, size=tuple(args.size) if args.size else None, fps=args.fps
            )
    except VideoExportError as e:
        print(f"studio export-video: {e}", file=sys.stderr)
        return 2
    print(
        f"wrote {done.path}: {done.num_frames} frames, {done.width}×{done.height} at {done.fps:g} fps, "
        f"{done.duration_s:.2f} s"
    )
    return 0
