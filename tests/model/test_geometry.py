"""Torch waypoint geometry agrees with the studio's numpy CameraModel and round-trips."""

from __future__ import annotations

import numpy as np
import torch

from studio.model.geometry import (
    camera_to_image,
    camera_to_world,
    image_to_camera,
    normalized_to_pixel,
    resize_intrinsics,
    world_to_camera,
)
from studio.sim.camera import CameraModel

torch.set_num_threads(1)


def _camera(seed: int = 0) -> CameraModel:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = q, rng.normal(size=3)
    K = np.array([[300.0, 0.5, 161.0], [0.0, 290.0, 118.0], [0.0, 0.0, 1.0]])
    return CameraModel(320, 240, K, T)


def test_image_to_camera_matches_camera_model_pixel_to_cam():
    cam = _camera()
    rng = np.random.default_rng(1)
    xy = rng.uniform(-1.2, 1.2, size=(7, 2))
    depth = rng.uniform(0.5, 2.0, size=7)
    ours = image_to_camera(
        torch.tensor(xy)[None], torch.tensor(depth)[None], torch.tensor(cam.K)[None], (cam.height, cam.width)
    )[0].numpy()
    uv = normalized_to_pixel(torch.tensor(xy), (cam.height, cam.width)).numpy()
    assert np.allclose(ours, cam.pixel_to_cam(uv, depth), atol=1e-9)


def test_round_trips_image_camera_world():
    cam = _camera(2)
    K = torch.tensor(cam.K)[None]
    T = torch.tensor(cam.T_world_cam)[None]
    p = torch.tensor(np.random.default_rng(3).uniform([-0.5, -0.4, 0.6], [0.5, 0.4, 2.0], size=(1, 5, 3)))
    xy, depth = camera_to_image(p, K, (240, 320))
    assert torch.allclose(image_to_camera(xy, depth, K, (240, 320)), p, atol=1e-10)
    world = camera_to_world(p, T)
    assert np.allclose(world[0].numpy(), cam.cam_to_world(p[0].numpy()), atol=1e-10)
    assert torch.allclose(world_to_camera(world, T), p, atol=1e-10)


def test_resize_intrinsics_matches_camera_model_resized():
    cam = _camera()
    small = cam.resized(120, 160)
    K = resize_intrinsics(torch.tensor(cam.K), (240, 320), (120, 160))
    assert np.allclose(K.numpy(), small.K)
