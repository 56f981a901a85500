"""Segmentation of the wrist depth image: the largest blob above the table wins."""

import numpy as np

from studio.sim.camera import CameraModel
from studio.sim.grasp_correction import segment_largest


def _down_camera(height=0.3) -> CameraModel:
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # looking straight down, image x = world x
    T[:3, 3] = [0.0, 0.0, height]
    return CameraModel.from_fovy(70.0, 64, 64, T)


def test_largest_blob_centroid():
    cam = _down_camera()
    depth = np.full((64, 64), 0.3, dtype=np.float32)  # the table
    depth[10:14, 10:14] = 0.27  # a small blob
    depth[30:46, 36:52] = 0.25  # the big one, 5 cm tall
    det = segment_largest(depth, cam)
    assert det is not None and det.pixels == 16 * 16
    expected = cam.pixel_to_world(np.array([[44.0, 38.0]]), np.array([0.25]))[0]
    assert np.allclose(det.world[:2], expected[:2], atol=1e-3)
    assert abs(det.world[2] - 0.05) < 1e-3


def test_nothing_on_the_table():
    depth = np.full((64, 64), 0.3, dtype=np.float32)
    depth[:5] = 0.03  # the fingers, too close to count
    assert segment_largest(depth, _down_camera()) is None
