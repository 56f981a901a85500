"""Synthetic, seeded recordings for the data tests (no simulator needed); imported by the test files."""

from __future__ import annotations

import numpy as np

from studio.sim.camera import CameraModel
from studio.sim.recording import Recording


def look_at_camera(width: int, height: int) -> CameraModel:
    """A camera 1.5 m in front of the table origin looking at it (OpenCV axes)."""
    eye = np.array([1.5, 0.0, 1.0])
    target = np.array([0.0, 0.0, 0.8])
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = eye
    return CameraModel.from_fovy(45.0, width, height, T)


def synthetic_frames(rng: np.random.Generator, n: int, height: int, width: int) -> np.ndarray:
    """Smooth frames with a moving coloured square: compress well, so H.264 keeps them close."""
    yy, xx = np.mgrid[0:height, 0:width]
    base = np.stack([xx * 255 // max(width - 1, 1), yy * 255 // max(height - 1, 1), np.full_like(xx, 90)], -1)
    colour = rng.integers(60, 255, 3)
    frames = np.repeat(base[None].astype(np.uint8), n, axis=0)
    s = max(4, min(height, width) // 5)
    for i in range(n):
        r = int((height - s) * i / max(n - 1, 1))
        c = int((width - s) * (n - 1 - i) / max(n - 1, 1))
        frames[i, r : r + s, c : c + s] = colour
    return frames


def make_recording(
    task: str = "pick_place/cube->red",
    robot: str = "panda",
    seed: int = 0,
    steps: int = 60,
    num_frames: int = 20,
    size: tuple[int, int] = (48, 64),
    success: bool = True,
) -> Recording:
    rng = np.random.default_rng(seed)
    h, w = size
    camera = look_at_camera(w, h)
    dt = 0.02
    ee_world = np.cumsum(rng.normal(0, 0.005, (steps, 3)), axis=0) + np.array([0.5, 0.0, 0.9])
    qpos = rng.normal(0, 0.3, (steps, 9))
    cmd = (np.arange(steps) > steps // 2).astype(np.float64)
    arrays = {
        "time": np.arange(steps) * dt,
        "qpos": qpos,
        "ee_pos_world": ee_world,
        "ee_pos_cam": camera.world_to_cam(ee_world),
        "gripper_cmd": cmd,
        "gripper_opening": 0.08 * (1 - cmd) + rng.uniform(0, 0.001, steps),
        "object_poses": rng.normal(0, 0.1, (steps, 2, 7)),
    }
    frame_steps = np.linspace(0, steps - 1, num_frames).round().astype(np.int64)
    return Recording(
        scene=task.split("/")[0],
        robot=robot,
        task=task,
        seed=seed,
        success=success,
        camera=camera,
        frames=synthetic_frames(rng, num_frames, h, w),
        frame_steps=frame_steps,
        arrays=arrays,
        object_names=["cube", "cylinder"],
        control_dt=dt,
    )


def flaky_recorder(scene, robot, task, seed, image_size=(48, 64), min_frames=20):
    """A stand-in for ``record_expert`` whose episodes fail for one seed in three (by seed)."""
    return make_recording(
        task=task,
        robot=robot,
        seed=seed,
        size=tuple(image_size),
        num_frames=min_frames,
        success=seed % 3 != 0,
    )
