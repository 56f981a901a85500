"""Video files with PyAV: writing H.264 MP4s that browsers play, reading frames back, probing any file.

Written files use libx264, pixel format yuv420p and the ``faststart`` layout (index at the front), the
combination every browser's ``<video>`` element plays and streams. yuv420p needs even sizes, so an odd
height or width is padded by one replicated row/column; readers pass the true ``size`` to crop it off.
"""

from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import av
import numpy as np


class VideoError(ValueError):
    """A file that is not a readable video, or a video that cannot be written."""


@dataclass(frozen=True)
class VideoInfo:
    """What a container says about its first video stream (``num_frames`` may be 0 when unknown)."""

    width: int
    height: int
    fps: float
    num_frames: int
    duration_s: float | None
    codec: str


@dataclass
class DecodedVideo:
    """Frames (F, H, W, 3) uint8 RGB and their presentation times (F,) in seconds."""

    frames: np.ndarray
    times: np.ndarray
    fps: float


def _even(frames: np.ndarray) -> np.ndarray:
    h, w = frames.shape[1:3]
    pad_h, pad_w = h % 2, w % 2
    if pad_h or pad_w:
        frames = np.pad(frames, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    return frames


def write_video(
    path: str | Path, frames: np.ndarray, fps: float, crf: int = 18, preset: str = "veryfast"
) -> None:
    """Encode (F, H, W, 3) uint8 RGB frames as an H.264 / yuv420p MP4 at a constant ``fps``."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) == 0:
        raise VideoError(
            f"frames must be a non-empty (F, H, W, 3) uint8 array, got {frames.shape} {frames.dtype}"
        )
    if not fps > 0:
        raise VideoError(f"fps must be positive, got {fps}")
    frames = _even(frames)
    rate = Fraction(fps).limit_denominator(1001)
    with av.open(str(path), mode="w", format="mp4", options={"movflags": "+faststart"}) as container:
        stream = container.add_stream("libx264", rate=rate)
        stream.width = frames.shape[2]
        stream.height = frames.shape[1]
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": str(int(crf)), "preset": preset}
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def _open(path: str | Path):
    path = Path(path)
    if not path.is_file():
        raise VideoError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise VideoError(f"{path}: the file is empty")
    try:
        container = av.open(str(path), mode="r")
    except (av.error.FFmpegError, UnicodeDecodeError) as e:
        raise VideoError(f"{path}: not a readable video file ({e.__class__.__name__}: {e})") from e
    if not container.streams.video:
        container.close()
        raise VideoError(f"{path}: the file has no video stream")
    return container


def probe_video(path: str | Path) -> VideoInfo:
    """Size, frame rate, frame count and duration from the container headers, without decoding."""
    with _open(path) as container:
        stream = container.streams.video[0]
        ctx = stream.codec_context
        if not ctx.width or not ctx.height:
            raise VideoError(f"{path}: the video stream has no frame size (corrupt header?)")
        rate = stream.average_rate or stream.guessed_rate or stream.base_rate
        fps = float(rate) if rate else 0.0
        duration = None
        if stream.duration is not None and stream.time_base is not None:
            duration = float(stream.duration * stream.time_base)
        elif container.duration is not None:
            duration = container.duration / av.time_base
        return VideoInfo(ctx.width, ctx.height, fps, int(stream.frames or 0), duration, ctx.name)


def read_video(
    path: str | Path,
    size: tuple[int, int] | None = None,
    start_s: float | None = None,
    end_s: float | None = None,
    max_frames: int | None = None,
) -> DecodedVideo:
    """Decode the frames of the first video stream, optionally only those with start_s <= t < end_s.

    Args:
        size: (height, width) to crop to (undoes the even-size padding of :func:`write_video`).
        max_frames: stop with a :class:`VideoError` if more than this many frames would be decoded.

    Frame times are relative to the first frame of the stream. Raises :class:`VideoError` for unreadable
    or corrupt files.
    """
    frames: list[np.ndarray] = []
    times: list[float] = []
    with _open(path) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        rate = stream.average_rate or stream.guessed_rate
        t0: float | None = None
        try:
            for i, frame in enumerate(container.decode(stream)):
                t = float(frame.time) if frame.time is not None else (i / float(rate) if rate else float(i))
                if t0 is None:
                    t0 = t
                t -= t0
                if start_s is not None and t < start_s - 1e-6:
                    continue
                if end_s is not None and t >= end_s - 1e-6:
                    break
                if max_frames is not None and len(frames) >= max_frames:
                    raise VideoError(f"{path}: more than {max_frames} frames")
                img = frame.to_ndarray(format="rgb24")
                if size is not None:
                    img = img[: size[0], : size[1]]
                frames.append(img)
                times.append(t)
        except av.error.FFmpegError as e:
            raise VideoError(f"{path}: the video is corrupt ({e.__class__.__name__}: {e})") from e
    fps = float(rate) if rate else 0.0
    if not frames:
        return DecodedVideo(np.zeros((0, *(size or (0, 0)), 3), np.uint8), np.zeros(0), fps)
    return DecodedVideo(np.stack(frames), np.asarray(times, dtype=np.float64), fps)
