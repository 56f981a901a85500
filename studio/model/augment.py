"""Batch augmentations on the model's side: pixel-space affine warps, colour jitter and demonstration mixup.

Geometric augmentations — random crop (then resize back), zoom about the centre, translation, horizontal and
vertical flips — are composed into one 3×3 pixel affine map A per video (pixels: u right, v down, the image
spanning [0, W] × [0, H]); the image is warped by A (``grid_sample``, zero fill) and the intrinsics become
K' = A·K. Labels stay in the camera frame and never move: converting a prediction made in the warped image with
K' gives the same camera-frame point (``geometry``), which is what keeps every augmentation label-consistent.

One draw per *video*: all frames of an agent clip share their warp and colours, so the future frames that serve
as world-model targets are seen like the input frame (the reference draws each agent frame independently). The
expert video gets its own draw, except flips, which are shared by an expert and its agent clips: mirroring only
one of them mirrors the layout (left target ↔ right target). ``expert_hflip`` does that on purpose, for tasks
named by colour rather than place (see ``TrainConfig``): the expert video alone is mirrored on top of the shared
flip.

``pair_hue`` (not in the paper) rotates the hue of an expert video *and of its agent clips* by one shared angle,
uniform over the whole circle: the two boxes of a push scene stay two different colours and the demonstration
still shows the box of the agent's scene that it pushes, but which colour that is no longer predicts the motion.
Where a training set pairs a colour with one motion only (push: the blue box is only ever pushed forward), this
is what lets the held-out combination be read from the demonstration rather than from the colour.

``pair_channels`` (not in the paper) does the same with a shared permutation of the RGB channels, drawn from
the five that are not the identity: saturated colours stay saturated and distinct (red, green and blue trade
places), where a hue rotation passes through in-between shades. It changes the whole scene, table and arm
included, and is drawn after the colour jitter, so it is an exact relabelling of the colours the pair shows.

Mixup (paper appendix B, "asymmetric demonstration image mixup"): each expert video and each agent clip is mixed
as β·I + (1 − β)·J with β ~ U(mixup_min, 1) and J the (augmented) first frame of a video from a *different task*
in the batch (the reference rolls the batch and may pick the same task); labels are not mixed. A video whose
batch holds no other task is left unmixed. Applied in training only, never in validation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch.nn import functional as F

from studio.model.config import TrainConfig


@dataclass
class AugmentedBatch:
    """Float frames in [0, 1] and the intrinsics of the augmented agent images.

    Attributes:
        expert_frames: (U, N, 3, H, W).
        agent_frames: (B, M, 3, H, W).
        K: (B, 3, 3) intrinsics of the augmented agent images (K' = A·K).
        agent_affine: (B, 3, 3) the pixel maps A applied to the agent clips.
    """

    expert_frames: torch.Tensor
    agent_frames: torch.Tensor
    K: torch.Tensor
    agent_affine: torch.Tensor


def _uniform(n: int, low: float, high: float, g: torch.Generator) -> torch.Tensor:
    return low + (high - low) * torch.rand(n, generator=g, dtype=torch.float64)


def sample_affine(
    n: int,
    image_size: tuple[int, int],
    cfg: TrainConfig,
    g: torch.Generator,
    hflip: torch.Tensor | None = None,
    vflip: torch.Tensor | None = None,
) -> torch.Tensor:
    """(n, 3, 3) float64 pixel maps: crop → zoom → translate → flips (flips drawn unless given)."""
    h, w = image_size
    size = torch.tensor([w, h], dtype=torch.float64)
    A = torch.eye(3, dtype=torch.float64).repeat(n, 1, 1)

    def then(M: torch.Tensor) -> None:
        nonlocal A
        A = M @ A

    # crop a box [l, W − r] × [t, H − b] and resize it to the full image
    lo = _uniform(2 * n, 0.0, cfg.crop, g).reshape(n, 2) * size
    hi = _uniform(2 * n, 0.0, cfg.crop, g).reshape(n, 2) * size
    s = size / (size - lo - hi)
    C = torch.eye(3, dtype=torch.float64).repeat(n, 1, 1)
    C[:, 0, 0], C[:, 1, 1] = s[:, 0], s[:, 1]
    C[:, 0, 2], C[:, 1, 2] = -lo[:, 0] * s[:, 0], -lo[:, 1] * s[:, 1]
    then(C)
    # zoom about the centre
    z = _uniform(n, cfg.scale[0], cfg.scale[1], g)
    Z = torch.eye(3, dtype=torch.float64).repeat(n, 1, 1)
    Z[:, 0, 0], Z[:, 1, 1] = z, z
    Z[:, 0, 2], Z[:, 1, 2] = (1 - z) * w / 2, (1 - z) * h / 2
    then(Z)
    # translate
    t = _uniform(2 * n, -cfg.translate, cfg.translate, g).reshape(n, 2) * size
    T = torch.eye(3, dtype=torch.float64).repeat(n, 1, 1)
    T[:, 0, 2], T[:, 1, 2] = t[:, 0], t[:, 1]
    then(T)
    # flips
    if hflip is None:
        hflip = torch.rand(n, generator=g) < cfg.hflip
    if vflip is None:
        vflip = torch.rand(n, generator=g) < cfg.vflip
    Fm = torch.eye(3, dtype=torch.float64).repeat(n, 1, 1)
    Fm[hflip, 0, 0], Fm[hflip, 0, 2] = -1.0, float(w)
    Fm[vflip, 1, 1], Fm[vflip, 1, 2] = -1.0, float(h)
    then(Fm)
    return A


def warp(frames: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    """Warp (B, T, 3, H, W) float frames by per-video pixel maps A (B, 3, 3): out(A·p) = in(p)."""
    b, t, c, h, w = frames.shape
    N = torch.tensor([[2.0 / w, 0.0, -1.0], [0.0, 2.0 / h, -1.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    theta = (N @ torch.linalg.inv(A.cpu()) @ torch.linalg.inv(N))[:, :2].to(frames.dtype).to(frames.device)
    theta = theta.repeat_interleave(t, dim=0)
    flat = frames.reshape(b * t, c, h, w)
    grid = F.affine_grid(theta, [b * t, c, h, w], align_corners=False)
    return F.grid_sample(flat, grid, mode="bilinear", padding_mode="zeros", align_corners=False).reshape(
        b, t, c, h, w
    )


def color_jitter(frames: torch.Tensor, cfg: TrainConfig, g: torch.Generator) -> torch.Tensor:
    """Per-video brightness, contrast, saturation and hue jitter of (B, T, 3, H, W) frames in [0, 1]."""
    b = frames.shape[0]
    dev, dt = frames.device, frames.dtype

    def factors(x: float) -> torch.Tensor:
        return _uniform(b, max(0.0, 1 - x), 1 + x, g).to(dev, dt).view(b, 1, 1, 1, 1)

    weights = torch.tensor([0.299, 0.587, 0.114], device=dev, dtype=dt).view(1, 1, 3, 1, 1)
    x = frames * factors(cfg.brightness)
    gray = (x * weights).sum(2, keepdim=True)
    mean = gray.mean(dim=(-1, -2), keepdim=True)
    x = (x - mean) * factors(cfg.contrast) + mean
    gray = (x * weights).sum(2, keepdim=True)
    x = (x - gray) * factors(cfg.saturation) + gray
    if cfg.hue > 0:
        x = rotate_hue(x, _uniform(b, -cfg.hue, cfg.hue, g) * 2 * math.pi)
    return x.clamp(0.0, 1.0)


def rotate_hue(frames: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """(B, T, 3, H, W) frames with the chroma plane of YIQ rotated by ``angle`` (B,) radians per video."""
    to_yiq = torch.tensor(
        [[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]], dtype=torch.float64
    )
    rot = torch.zeros(len(angle), 3, 3, dtype=torch.float64)
    rot[:, 0, 0] = 1.0
    cos, sin = torch.cos(angle.double().cpu()), torch.sin(angle.double().cpu())
    rot[:, 1, 1], rot[:, 1, 2] = cos, -sin
    rot[:, 2, 1], rot[:, 2, 2] = sin, cos
    M = (torch.linalg.inv(to_yiq) @ rot @ to_yiq).to(frames.device, frames.dtype)
    return torch.einsum("bij,btjhw->btihw", M, frames)


CHANNEL_PERMUTATIONS = torch.tensor([[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]])
"""Every ordering of (R, G, B); row 0 is the identity."""


def permute_channels(frames: torch.Tensor, which: torch.Tensor) -> torch.Tensor:
    """(B, T, 3, H, W) frames with their colour channels reordered by ``CHANNEL_PERMUTATIONS[which]`` (B,)."""
    order = CHANNEL_PERMUTATIONS[which.cpu()].to(frames.device)
    index = order.view(-1, 1, 3, 1, 1).expand(-1, frames.shape[1], 3, *frames.shape[-2:])
    return torch.gather(frames, 2, index)


def mixup_partners(tasks: torch.Tensor, g: torch.Generator) -> torch.Tensor:
    """For each video, a random index of a video of another task, or −1 when the batch has none."""
    out = torch.full((len(tasks),), -1, dtype=torch.long)
    for i in range(len(tasks)):
        others = torch.nonzero(tasks != tasks[i]).flatten()
        if len(others):
            out[i] = others[torch.randint(len(others), (1,), generator=g)]
    return out


def mixup(frames: torch.Tensor, tasks: torch.Tensor, cfg: TrainConfig, g: torch.Generator) -> torch.Tensor:
    """β·video + (1 − β)·(first frame of a video of another task), per video (B, T, 3, H, W)."""
    partner = mixup_partners(tasks.cpu(), g)
    beta = _uniform(len(partner), cfg.mixup_min, 1.0, g)
    beta[partner < 0] = 1.0
    partner = partner.clamp(min=0)
    beta = beta.to(frames.device, frames.dtype).view(-1, 1, 1, 1, 1)
    other = frames[partner.to(frames.device), :1]
    return beta * frames + (1 - beta) * other


def augment_batch(
    expert_frames: torch.Tensor,
    agent_frames: torch.Tensor,
    K: torch.Tensor,
    expert_ids: torch.Tensor,
    expert_tasks: torch.Tensor,
    agent_tasks: torch.Tensor,
    cfg: TrainConfig,
    g: torch.Generator,
) -> AugmentedBatch:
    """Augment uint8 expert videos (U, N, 3, H, W) and agent clips (B, M, 3, H, W) of pairs ``expert_ids`` → U.

    Flips are drawn per expert and shared with its agent clips (``expert_hflip`` then mirrors the expert
    alone); everything else is drawn per video.
    """
    h, w = agent_frames.shape[-2:]
    u, b = expert_frames.shape[0], agent_frames.shape[0]
    hflip = torch.rand(u, generator=g) < cfg.hflip
    vflip = torch.rand(u, generator=g) < cfg.vflip
    ids = expert_ids.cpu()
    expert_only = (
        torch.rand(u, generator=g) < cfg.expert_hflip if cfg.expert_hflip > 0 else torch.zeros_like(hflip)
    )
    A_exp = sample_affine(u, (h, w), cfg, g, hflip ^ expert_only, vflip)
    A_agt = sample_affine(b, (h, w), cfg, g, hflip[ids], vflip[ids])
    expert = color_jitter(warp(expert_frames.float() / 255.0, A_exp), cfg, g)
    agent = color_jitter(warp(agent_frames.float() / 255.0, A_agt), cfg, g)
    if cfg.pair_hue > 0:
        turned = torch.rand(u, generator=g) < cfg.pair_hue
        angle = torch.where(turned, torch.rand(u, generator=g, dtype=torch.float64) * 2 * math.pi, 0.0)
        expert = rotate_hue(expert, angle).clamp(0.0, 1.0)
        agent = rotate_hue(agent, angle[ids]).clamp(0.0, 1.0)
    if cfg.pair_channels > 0:
        permuted = torch.rand(u, generator=g) < cfg.pair_channels
        which = torch.where(permuted, torch.randint(1, len(CHANNEL_PERMUTATIONS), (u,), generator=g), 0)
        expert = permute_channels(expert, which)
        agent = permute_channels(agent, which[ids])
    if cfg.mixup:
        expert = mixup(expert, expert_tasks, cfg, g)
        agent = mixup(agent, agent_tasks, cfg, g)
    K_aug = A_agt.to(K.device, torch.float64) @ K.double()
    return AugmentedBatch(expert, agent, K_aug.to(K.dtype), A_agt.to(K.dtype))
