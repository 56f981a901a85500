"""Depth cues for teleop in a flat 3D view: where the gripper is over the table, and which object it is over.

Without stereo or a 3D mouse, a person cannot tell a gripper 2 cm above a cube from one 2 cm behind it. Three
cues answer that, redrawn a few times a second while the live session is shown: a drop line from the grasp point
straight down to the surface below it, a dark disk (a shadow) where it lands, and a yellow outline around the
object under (or in) the gripper. :func:`describe` says the same in words for the status line: the height over
the surface and the distance to the nearest object.
"""

from __future__ import annotations

import numpy as np
import viser

from studio.ui.reach import Hit, object_label

LINE_RGB = (30, 30, 30)
SHADOW_RGB = (20, 20, 20)
HIGHLIGHT_RGB = (250, 200, 0)
SHADOW_RADIUS = 0.022
LINE_RADIUS = 0.0025


class DepthCues:
    """The drop line, shadow disk and object outline of one tab's live teleop view."""

    def __init__(self, scene: viser.SceneApi, root: str = "/teleop_cues"):
        self.scene = scene
        self.root = root
        self._line: viser.CylinderHandle | None = None
        self._shadow: viser.CylinderHandle | None = None
        self._outline: viser.BoxHandle | None = None
        self._outline_size: tuple[float, float, float] | None = None
        self.visible = False

    def _ensure(self) -> None:
        if self._line is None:
            self._line = self.scene.add_cylinder(
                f"{self.root}/drop",
                radius=LINE_RADIUS,
                height=1.0,
                color=LINE_RGB,
                cast_shadow=False,
                receive_shadow=False,
            )
            self._shadow = self.scene.add_cylinder(
                f"{self.root}/shadow",
                radius=SHADOW_RADIUS,
                height=0.002,
                color=SHADOW_RGB,
                opacity=0.55,
                cast_shadow=False,
                receive_shadow=False,
            )

    def show(
        self,
        ee: np.ndarray,
        below: Hit | None,
        outline: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> None:
        """Draw the cues for the grasp point ``ee``, the surface hit straight below it, and an object outline
        (centre, wxyz, size) or None."""
        self._ensure()
        assert self._line is not None and self._shadow is not None
        if below is None:
            self._line.visible = self._shadow.visible = False
        else:
            top, bottom = float(ee[2]), float(below.point[2])
            height = max(top - bottom, 1e-4)
            self._line.position = (float(ee[0]), float(ee[1]), bottom + height / 2)
            self._line.scale = (1.0, 1.0, height)
            self._shadow.position = (float(ee[0]), float(ee[1]), bottom + 0.001)
            self._line.visible = self._shadow.visible = True
        if outline is None:
            if self._outline is not None:
                self._outline.visible = False
        else:
            centre, wxyz, size = outline
            key = (round(float(size[0]), 4), round(float(size[1]), 4), round(float(size[2]), 4))
            if self._outline is None or self._outline_size != key:
                if self._outline is not None:
                    self._outline.remove()
                self._outline = self.scene.add_box(
                    f"{self.root}/outline",
                    color=HIGHLIGHT_RGB,
                    dimensions=tuple(np.asarray(size) + 0.012),
                    wireframe=True,
                    cast_shadow=False,
                    receive_shadow=False,
                )
                self._outline_size = key
            self._outline.position = np.asarray(centre, dtype=np.float64)
            self._outline.wxyz = np.asarray(wxyz, dtype=np.float64)
            self._outline.visible = True
        self.visible = True

    def hide(self) -> None:
        for h in (self._line, self._shadow, self._outline):
            if h is not None:
                h.visible = False
        self.visible = False

    def remove(self) -> None:
        for h in (self._line, self._shadow, self._outline):
            if h is not None:
                h.remove()
        self._line = self._shadow = self._outline = None
        self._outline_size = None
        self.visible = False


def describe(ee: np.ndarray, below: Hit | None, nearest: tuple[str, float] | None, held: str | None) -> str:
    """One line for the status: height over the surface below and the nearest object's distance."""
    parts = []
    if held is not None:
        parts.append(f"holding the **{object_label(held)}**")
    if below is not None:
        what = "the " + object_label(below.body) if below.is_object else "the table"
        parts.append(f"grasp point **{100 * (float(ee[2]) - float(below.point[2])):.1f} cm** above {what}")
    if nearest is not None and nearest[0] != held:
        parts.append(f"**{100 * nearest[1]:.1f} cm** from the {object_label(nearest[0])}")
    return " · ".join(parts)
