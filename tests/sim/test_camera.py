"""Camera model: conversions are exact inverses and agree with MuJoCo's renderer."""

import numpy as np
import pytest

from studio.sim.camera import CameraModel


def _camera() -> CameraModel:
    rng = np.random.default_rng(0)
    a = rng.normal(size=3)
    a /= np.linalg.norm(a)
    angle = 0.7
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    R = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [0.1, 1.2, 0.7]
    return CameraModel.from_fovy(45.0, 320, 240, T)


def test_world_pixel_world_round_trip():
    cam = _camera()
    rng = np.random.default_rng(1)
    p_cam = np.column_stack(
        [rng.uniform(-0.3, 0.3, 100), rng.uniform(-0.2, 0.2, 100), rng.uniform(0.3, 2.0, 100)]
    )
    p_world = cam.cam_to_world(p_cam)
    uv = cam.world_to_pixel(p_world)
    back = cam.pixel_to_world(uv, p_cam[:, 2])
    assert np.max(np.abs(back - p_world)) < 1e-6
    assert np.max(np.abs(cam.world_to_cam(p_world) - p_cam)) < 1e-9


def test_resized_and_affine_cameras_project_consistently():
    cam = _camera()
    p = cam.cam_to_world(np.array([[0.05, -0.02, 1.0]]))
    uv = cam.world_to_pixel(p)
    half = cam.resized(120, 160)
    assert np.allclose(half.world_to_pixel(p), uv / 2)
    # Horizontal flip: u -> W - u.
    A = np.array([[-1.0, 0.0, cam.width], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    flipped = cam.with_pixel_affine(A, cam.height, cam.width)
    assert np.allclose(flipped.world_to_pixel(p), [[cam.width - uv[0, 0], uv[0, 1]]])
    with pytest.raises(ValueError):
        cam.with_pixel_affine(np.ones((3, 3)), 10, 10)


def test_serialisation_round_trip():
    cam = _camera()
    back = CameraModel.from_dict(cam.to_dict())
    assert np.array_equal(back.K, cam.K) and np.array_equal(back.T_world_cam, cam.T_world_cam)


def test_mujoco_camera_matches_render(env_factory):
    """An object's centre projects onto pixels of that object's colour in the rendered image."""
    env = env_factory("pick_place", "panda")
    env.reset("pick_place/cube->red", 3)
    img = env.render()
    cam = env.camera_model()
    for name, colour in [("cube", (242, 140, 25)), ("cylinder", (153, 64, 217))]:
        top = env.object_poses()[name][:3].copy()
        u, v = cam.world_to_pixel(top[None])[0]
        px = img[int(v), int(u)].astype(int)
        # Shaded, so compare hue order rather than exact values.
        assert np.argmax(px) == np.argmax(colour), (name, px)
