"""Grasp correction from the end-effector depth camera (the paper's appendix, after AWDA).

Before closing the gripper at a grasp waypoint, the arm hovers above it and looks down with the
wrist depth camera: pixels clearly above the table and clearly below the fingers are candidate
object pixels; the largest connected component is taken as the object to grasp; its centroid is
back-projected to the world and the gripper is moved so that it sits directly beneath. This is
repeated three times (each time from the corrected pose).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from studio.sim.camera import CameraModel


@dataclass(frozen=True)
class Detection:
    """The object the wrist camera sees: its centroid in the world and its pixel area."""

    world: np.ndarray
    pixels: int


def segment_largest(
    depth: np.ndarray,
    camera: CameraModel,
    table_z: float = 0.0,
    min_height: float = 0.008,
    min_range: float = 0.11,
    min_pixels: int = 12,
    near: np.ndarray | None = None,
    radius: float = 0.06,
) -> Detection | None:
    """The largest connected blob standing above the table in a wrist depth image, or None.

    Args:
        depth: (H, W) metres along the optical axis.
        camera: the wrist camera's model at the moment the image was taken.
        table_z: world height of the table surface.
        min_height: a pixel belongs to an object when its world point is this much above the table.
        min_range: pixels closer than this to the camera (the fingers) are ignored.
        min_pixels: blobs smaller than this are noise.
        near: if given, only blobs whose centroid lies within ``radius`` (horizontally) of this world
            point compete — the wrist camera also sees neighbouring objects, and the waypoint already
            says roughly where the object to grasp is.
    """
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w]
    uv = np.stack([u + 0.5, v + 0.5], axis=-1).reshape(-1, 2)
    pts = camera.pixel_to_world(uv, depth.reshape(-1)).reshape(h, w, 3)
    mask = (pts[..., 2] > table_z + min_height) & (depth > min_range) & (depth < 2.0)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return None
    best: Detection | None = None
    for label in range(1, n):
        area = int(stats[label, cv2.CC_STAT_AREA])
        if area < min_pixels or (best is not None and area <= best.pixels):
            continue
        world = pts[labels == label]
        # Centroid of the blob in the world (x, y from its points; z = its highest part).
        centre = np.array([world[:, 0].mean(), world[:, 1].mean(), world[:, 2].max()])
        if near is not None and np.linalg.norm(centre[:2] - np.asarray(near)[:2]) > radius:
            continue
        best = Detection(world=centre, pixels=area)
    return best
