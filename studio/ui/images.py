"""Image helpers for panels: filmstrips (a grid of frames in one image), thumbnails, and the *Enlarge* modal.

The side panel is narrow: its images are thumbnails. :func:`open_enlarged` shows a panel's images again, drawn
large, in a modal window that spans most of the browser window (a person demoing reads them from across a room).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np

#: CSS that widens the modal it is placed in (viser's modals are a fixed 440 px otherwise).
WIDE_MODAL_CSS = "<style>.mantine-Modal-content { --modal-size: min(96vw, 1600px) !important; }</style>"
#: Height in pixels of each frame drawn in the Enlarge modal.
ENLARGED_HEIGHT = 240


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
    grow = max(1.0, height / 240)  # labels grow with large frames (the Enlarge modal) to stay readable
    scale, thick, at = 0.38 * grow, max(1, round(grow)), (round(3 * grow), round(12 * grow))
    for i, t in enumerate(thumbs):
        r, c = divmod(i, cols)
        y, x = r * (height + gap), c * (tw + gap)
        tile = np.ascontiguousarray(t[:, :tw])  # drawn on its own frame: a long label is cut at its edge
        if labels is not None and i < len(labels) and labels[i]:
            font = cv2.FONT_HERSHEY_SIMPLEX
            cv2.putText(tile, labels[i], at, font, scale, (0, 0, 0), thick + 2, cv2.LINE_AA)
            cv2.putText(tile, labels[i], at, font, scale, (255, 255, 255), thick, cv2.LINE_AA)
        out[y : y + height, x : x + tw] = tile
    return out


def side_by_side(left: np.ndarray, right: np.ndarray, height: int = 120, gap: int = 4) -> np.ndarray:
    """Two images next to each other at the same height."""
    a, b = thumbnail(left, height), thumbnail(right, height)
    out = np.full((height, a.shape[1] + gap + b.shape[1], 3), 255, np.uint8)
    out[:, : a.shape[1]] = a
    out[:, a.shape[1] + gap :] = b
    return out


def open_enlarged(
    gui, title: str, images: Sequence[tuple[str, np.ndarray]], on_close: Callable[[], None] | None = None
) -> list:
    """A modal titled ``title`` showing ``images`` ((label, RGB image) pairs, drawn as large as the window
    allows) with a *Close* button; returns the image handles (a caller may keep updating them while it is open)."""
    if not images:
        raise ValueError("nothing to enlarge yet")
    handles = []
    with gui.add_modal(title) as modal:
        gui.add_html(WIDE_MODAL_CSS)
        for label, image in images:
            handles.append(
                gui.add_image(np.asarray(image, np.uint8), label=label, format="jpeg", jpeg_quality=90)
            )
        close = gui.add_button("Close", icon="x")

    def closed(_) -> None:
        modal.close()
        if on_close is not None:
            on_close()

    close.on_click(closed)
    return handles
