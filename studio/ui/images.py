"""Small image helpers for panels: filmstrips (a grid of frames in one image) and thumbnails."""

from __future__ import annotations

import cv2
import numpy as np


def thumbnail(image: np.ndarray, height: int) -> np.ndarray:
    """``image`` scaled to ``height`` rows (aspect kept), uint8 RGB."""
    img = np.asarray(image, dtype=np.uint8)
    h, w = img.shape[:2]
    width = max(1, round(w * height / h))
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA if height < h else cv2.INTER_LINEAR)


def filmstrip(
    frames: np.ndarray, cols: int = 5, height: int = 72, labels: list[str] | None = None, gap: int = 2
) -> np.ndarray:
    """Frames (N, H, W, 3) as a grid ``cols`` wide, each ``height`` rows tall, with optional labels."""
    frames = np.asarray(frames, dtype=np.uint8)
    if frames.ndim != 4 or len(frames) == 0:
        raise ValueError(f"filmstrip needs (N, H, W, 3) frames, got shape {frames.shape}")
    thumbs = [thumbnail(f, height) for f in frames]
    tw = thumbs[0].shape[1]
    cols = max(1, min(cols, len(thumbs)))
    rows = -(-len(thumbs) // cols)
    out = np.full((rows * height + (rows - 1) * gap, cols * tw + (cols - 1) * gap, 3), 255, np.uint8)
    for i, t in enumerate(thumbs):
        r, c = divmod(i, cols)
        y, x = r * (height + gap), c * (tw + gap)
        out[y : y + height, x : x + tw] = t[:, :tw]
        if labels is not None and i < len(labels) and labels[i]:
            cv2.putText(
                out, labels[i], (x + 3, y + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (0, 0, 0), 3, cv2.LINE_AA
            )
            cv2.putText(
                out,
                labels[i],
                (x + 3, y + 12),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.38,
                (255, 255, 255),
                1,
                cv2.LINE_AA,
            )
    return out


def side_by_side(left: np.ndarray, right: np.ndarray, height: int = 120, gap: int = 4) -> np.ndarray:
    """Two images next to each other at the same height."""
    a, b = thumbnail(left, height), thumbnail(right, height)
    out = np.full((height, a.shape[1] + gap + b.shape[1], 3), 255, np.uint8)
    out[:, : a.shape[1]] = a
    out[:, a.shape[1] + gap :] = b
    return out
