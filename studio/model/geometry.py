"""Batched torch conversions between the model's waypoint parameterisation and camera / world points.

The model predicts a position as (x, y, z): (x, y) in the input image's normalised coordinates, x = −1 at the
left edge and +1 at the right edge of the image, y likewise from top to bottom, and z the camera depth in metres.
Pixels follow the studio's camera convention (``studio.sim.camera``): u right, v down, the image spanning
[0, W] × [0, H], so ``u = (x + 1)·W/2`` and ``v = (y + 1)·H/2``. With the intrinsics K of *that* image,
a camera-frame point (x right, y down, z forward) is ``p = z · K⁻¹ [u, v, 1]ᵀ``.

Because augmentations are pixel-space affine maps A with K' = A·K (``augment``), predicting in the augmented
image and converting with K' lands on the same camera-frame point as the un-augmented label: the labels never
move, only the intrinsics do. This module mirrors ``CameraModel``'s conventions in torch (the model package does
not import the simulator); a test checks the two agree.
"""

from __future__ import annotations

import torch


def normalized_to_pixel(xy: torch.Tensor, image_size: tuple[int, int]) -> torch.Tensor:
    """(…, 2) normalised image coordinates → (…, 2) pixels (u, v)."""
    h, w = image_size
    scale = xy.new_tensor([w / 2.0, h / 2.0])
    return (xy + 1.0) * scale


def pixel_to_normalized(uv: torch.Tensor, image_size: tuple[int, int]) -> torch.Tensor:
    """(…, 2) pixels (u, v) → (…, 2) normalised image coordinates."""
    h, w = image_size
    scale = uv.new_tensor([w / 2.0, h / 2.0])
    return uv / scale - 1.0


def image_to_camera(
    xy: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, image_size: tuple[int, int]
) -> torch.Tensor:
    """Back-project normalised image points at camera depth ``depth`` to camera-frame points.

    Args:
        xy: (B, …, 2) normalised coordinates.
        depth: (B, …) depth in metres.
        K: (B, 3, 3) intrinsics of the image the coordinates refer to.
    Returns:
        (B, …, 3) camera-frame points in metres.
    """
    uv = normalized_to_pixel(xy, image_size)
    ones = torch.ones_like(uv[..., :1])
    uv1 = torch.cat([uv, ones], dim=-1)
    K_inv = torch.linalg.inv(K.to(uv1.dtype))
    shape = uv1.shape
    rays = torch.einsum("bij,bnj->bni", K_inv, uv1.reshape(shape[0], -1, 3)).reshape(shape)
    return rays * depth.unsqueeze(-1)


def camera_to_image(
    p_cam: torch.Tensor, K: torch.Tensor, image_size: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Project camera-frame points (B, …, 3) to normalised image coordinates (B, …, 2) and depth (B, …)."""
    shape = p_cam.shape
    uvw = torch.einsum("bij,bnj->bni", K.to(p_cam.dtype), p_cam.reshape(shape[0], -1, 3)).reshape(shape)
    depth = p_cam[..., 2]
    uv = uvw[..., :2] / uvw[..., 2:3]
    return pixel_to_normalized(uv, image_size), depth


def camera_to_world(p_cam: torch.Tensor, T_world_cam: torch.Tensor) -> torch.Tensor:
    """(B, …, 3) camera-frame points → world frame with (B, 4, 4) camera poses."""
    shape = p_cam.shape
    T = T_world_cam.to(p_cam.dtype)
    flat = p_cam.reshape(shape[0], -1, 3)
    out = torch.einsum("bij,bnj->bni", T[:, :3, :3], flat) + T[:, None, :3, 3]
    return out.reshape(shape)


def world_to_camera(p_world: torch.Tensor, T_world_cam: torch.Tensor) -> torch.Tensor:
    """(B, …, 3) world points → camera frame with (B, 4, 4) camera poses."""
    shape = p_world.shape
    T = T_world_cam.to(p_world.dtype)
    R = T[:, :3, :3]
    flat = p_world.reshape(shape[0], -1, 3) - T[:, None, :3, 3]
    out = torch.einsum("bji,bnj->bni", R, flat)
    return out.reshape(shape)


def resize_intrinsics(K: torch.Tensor, old_size: tuple[int, int], new_size: tuple[int, int]) -> torch.Tensor:
    """Intrinsics of an image resampled from ``old_size`` to ``new_size`` (both (height, width))."""
    sy = new_size[0] / old_size[0]
    sx = new_size[1] / old_size[1]
    S = torch.diag(K.new_tensor([sx, sy, 1.0]))
    return S @ K
