"""Augmentation: label consistency of pixel-affine warps, shared flips, mixup partners from other tasks, pair colour changes."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from studio.model.augment import augment_batch, color_jitter, mixup, mixup_partners, sample_affine, warp
from studio.model.config import TrainConfig
from studio.model.geometry import camera_to_image, image_to_camera
from studio.sim.camera import CameraModel

torch.set_num_threads(1)
H, W = 96, 128
K = torch.tensor([[110.0, 0.0, 64.0], [0.0, 110.0, 48.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
NO_COLOUR = dict(brightness=0.0, contrast=0.0, saturation=0.0, hue=0.0, mixup=False)


def _blob_image(p_cam: torch.Tensor) -> torch.Tensor:
    """A smooth bright blob centred on the projection of the camera-frame point."""
    uv = (K @ p_cam)[:2] / p_cam[2]
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    blob = torch.exp(-((u - uv[0]) ** 2 + (v - uv[1]) ** 2) / (2 * 2.0**2))
    return blob.expand(3, H, W).float()


def _centroid(img: torch.Tensor) -> torch.Tensor:
    m = img[0].double()
    m = m * (m > 0.2)
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    return torch.stack([(m * u).sum() / m.sum(), (m * v).sum() / m.sum()])


@pytest.mark.parametrize("seed", range(6))
def test_projecting_labels_after_augmentation_lands_on_the_same_scene_points(seed):
    cfg = TrainConfig(crop=0.1, translate=0.08, scale=(0.85, 1.15), hflip=0.5, vflip=0.5, **NO_COLOUR)
    g = torch.Generator().manual_seed(seed)
    p = torch.tensor([0.06 * (seed - 3), 0.03 * (seed % 3 - 1), 1.0 + 0.1 * seed], dtype=torch.float64)
    img = _blob_image(p)[None, None]
    A = sample_affine(1, (H, W), cfg, g)
    out = warp(img, A)[0, 0]
    K_aug = A[0] @ K
    # the label, projected with the augmented intrinsics, is where the augmented image shows the point
    uv_label = (K_aug @ p)[:2] / p[2]
    assert torch.allclose(_centroid(out), uv_label, atol=0.35)
    # and a prediction read off the augmented image converts back to the label's camera-frame point
    xy, depth = camera_to_image(p[None, None], K_aug[None], (H, W))
    assert torch.allclose(image_to_camera(xy, depth, K_aug[None], (H, W))[0, 0], p, atol=1e-9)
    # the studio's numpy camera model agrees on the virtual camera
    cam = CameraModel(W, H, K.numpy(), np.eye(4)).with_pixel_affine(A[0].numpy(), H, W)
    assert np.allclose(cam.cam_to_pixel(p.numpy()), uv_label.numpy())


def test_no_augmentation_is_the_identity():
    cfg = TrainConfig(crop=0.0, translate=0.0, scale=(1.0, 1.0), hflip=0.0, vflip=0.0, **NO_COLOUR)
    frames = torch.randint(0, 256, (2, 3, 3, 24, 32), dtype=torch.uint8)
    out = augment_batch(
        frames,
        frames,
        K.float()[None].repeat(2, 1, 1),
        torch.arange(2),
        torch.arange(2),
        torch.arange(2),
        cfg,
        torch.Generator().manual_seed(0),
    )
    assert torch.allclose(out.agent_frames, frames.float() / 255, atol=1e-6)
    assert torch.allclose(out.K, K.float()[None].repeat(2, 1, 1))


def test_flips_are_shared_by_an_expert_and_its_agent_clips():
    cfg = TrainConfig(hflip=0.5, vflip=0.5, **NO_COLOUR)
    expert = torch.zeros(3, 2, 3, 24, 32, dtype=torch.uint8)
    agent = torch.zeros(5, 3, 3, 24, 32, dtype=torch.uint8)
    ids = torch.tensor([0, 0, 1, 2, 2])
    seen = set()
    for seed in range(8):
        g = torch.Generator().manual_seed(seed)
        out = augment_batch(expert, agent, K.float()[None].repeat(5, 1, 1), ids, torch.arange(3), ids, cfg, g)
        h = (out.agent_affine[:, 0, 0] < 0).tolist()
        v = (out.agent_affine[:, 1, 1] < 0).tolist()
        assert h[0] == h[1] and h[3] == h[4] and v[0] == v[1] and v[3] == v[4]
        seen.update(h)
    assert seen == {True, False}


def test_expert_hflip_mirrors_the_expert_video_alone():
    cfg = TrainConfig(
        crop=0.0, translate=0.0, scale=(1.0, 1.0), hflip=0.0, vflip=0.0, expert_hflip=1.0, **NO_COLOUR
    )
    expert = torch.randint(0, 256, (2, 2, 3, 24, 32), dtype=torch.uint8)
    agent = torch.randint(0, 256, (2, 3, 3, 24, 32), dtype=torch.uint8)
    out = augment_batch(
        expert,
        agent,
        K.float()[None].repeat(2, 1, 1),
        torch.arange(2),
        torch.arange(2),
        torch.arange(2),
        cfg,
        torch.Generator().manual_seed(0),
    )
    assert torch.allclose(out.expert_frames, expert.flip(-1).float() / 255, atol=1e-5)
    assert torch.allclose(out.agent_frames, agent.float() / 255, atol=1e-6)  # the agent keeps its layout
    assert torch.allclose(out.K, K.float()[None].repeat(2, 1, 1))  # and its labels


def test_mixup_partners_come_from_another_task():
    g = torch.Generator().manual_seed(0)
    tasks = torch.tensor([0, 0, 1, 2, 2, 2])
    for _ in range(20):
        partner = mixup_partners(tasks, g)
        assert (tasks[partner] != tasks).all()
    assert (mixup_partners(torch.zeros(3, dtype=torch.long), g) == -1).all()


def test_mixup_blends_with_the_partners_first_frame_and_leaves_lonely_tasks_alone():
    cfg = TrainConfig(mixup_min=0.3)
    a = torch.rand(1, 3, 3, 4, 4)
    b = torch.rand(1, 3, 3, 4, 4)
    mixed = mixup(torch.cat([a, b]), torch.tensor([0, 1]), cfg, torch.Generator().manual_seed(0))
    beta = ((mixed[0] - b[0, 0]) / (a[0] - b[0, 0])).flatten()
    assert torch.allclose(beta, beta[0].expand_as(beta), atol=1e-4) and 0.3 <= beta[0] <= 1.0
    same = mixup(torch.cat([a, b]), torch.zeros(2, dtype=torch.long), cfg, torch.Generator().manual_seed(0))
    assert torch.equal(same, torch.cat([a, b]))


def test_colour_jitter_stays_in_range_and_is_constant_over_a_clip():
    cfg = TrainConfig()
    clip = torch.rand(1, 1, 3, 8, 8).expand(2, 4, 3, 8, 8).clone()
    out = color_jitter(clip, cfg, torch.Generator().manual_seed(0))
    assert out.min() >= 0 and out.max() <= 1
    assert torch.allclose(out[0, 0], out[0, 3])
    assert not torch.allclose(out[0], out[1])


def _uniform_pairs(rgb: list[int], u: int, **settings) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mean colours of ``u`` uniform 8×8 expert videos of colour ``rgb`` (U, 2, 3) and of their two agent clips
    each (2U, 3, 3) after ``augment_batch`` with only ``settings`` on; and the clips' expert index."""
    cfg = TrainConfig(
        crop=0.0, translate=0.0, scale=(1.0, 1.0), hflip=0.0, vflip=0.0, **NO_COLOUR, **settings
    )
    scene = torch.tensor(rgb, dtype=torch.uint8).view(1, 1, 3, 1, 1).repeat(1, 1, 1, 8, 8)
    ids = torch.arange(u).repeat_interleave(2)
    out = augment_batch(
        scene.repeat(u, 2, 1, 1, 1),
        scene.repeat(2 * u, 3, 1, 1, 1),
        K.float()[None].repeat(2 * u, 1, 1),
        ids,
        torch.arange(u),
        ids,
        cfg,
        torch.Generator().manual_seed(0),
    )
    return out.expert_frames.mean(dim=(-1, -2)), out.agent_frames.mean(dim=(-1, -2)), ids


def test_pair_hue_turns_an_expert_and_its_agent_clips_by_one_angle():
    rgb = [150, 100, 90]  # in gamut
    colour, agent, ids = _uniform_pairs(rgb, 16, pair_hue=1.0)
    assert torch.allclose(agent, colour[ids, :1].expand(-1, 3, 3), atol=1e-5)
    moved = (colour[:, 0] - torch.tensor(rgb) / 255).abs().amax(-1)
    assert (moved > 0.05).sum() >= 8  # angles spread over the circle, one per expert
    luma = torch.tensor([0.299, 0.587, 0.114])
    assert torch.allclose(colour @ luma, (torch.tensor(rgb) / 255 @ luma).expand(16, 2), atol=0.01)
    plain, _, _ = _uniform_pairs(rgb, 16, pair_hue=0.0)
    assert torch.allclose(plain, (torch.tensor(rgb) / 255).expand(16, 2, 3), atol=1e-6)


def test_pair_channels_reorders_an_expert_and_its_agent_clips_by_one_permutation():
    rgb = [200, 120, 40]
    colour, agent, ids = _uniform_pairs(rgb, 30, pair_channels=1.0)
    assert torch.allclose(agent, colour[ids, :1].expand(-1, 3, 3), atol=1e-6)
    seen = {tuple(round(v * 255) for v in c.tolist()) for c in colour[:, 0]}
    every_other_order = {tuple(rgb[i] for i in p) for p in itertools.permutations(range(3))} - {tuple(rgb)}
    assert seen == every_other_order  # never the identity; all five others drawn over 30 experts
    plain, _, _ = _uniform_pairs(rgb, 30, pair_channels=0.0)
    assert torch.allclose(plain, (torch.tensor(rgb) / 255).expand(30, 2, 3), atol=1e-6)
