"""The latent image decoder: pooled latent states (2C keypoints) → camera images, for visualising plans.

A linear layer lifts the keypoint vector to a (base_channels, ⌈H/2^k⌉, ⌈W/2^k⌉) map, k stride-2 transposed
convolutions (each followed by BatchNorm and ReLU, channels halving) upsample it, and a 3×3 convolution with a
sigmoid gives an RGB image in [0, 1], resized to exactly (H, W) when H or W is not a multiple of 2^k. It reads
the same pooled states as the waypoint head, so the UI can show what the world model "imagines" at every step.
Trained with the main model frozen (``train_decoder``).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from studio.model.config import DecoderConfig


class LatentDecoder(nn.Module):
    """(…, in_dim) pooled states → (…, 3, H, W) images in [0, 1]."""

    def __init__(self, in_dim: int, image_size: tuple[int, int], cfg: DecoderConfig) -> None:
        super().__init__()
        self.in_dim = in_dim
        self.image_size = (int(image_size[0]), int(image_size[1]))
        k = cfg.stages
        self.start = (math.ceil(self.image_size[0] / 2**k), math.ceil(self.image_size[1] / 2**k))
        channels = [max(cfg.base_channels // 2**i, 16) for i in range(k + 1)]
        self.lift = nn.Linear(in_dim, channels[0] * self.start[0] * self.start[1])
        layers: list[nn.Module] = []
        for c_in, c_out in itertools.pairwise(channels):
            layers += [
                nn.ConvTranspose2d(c_in, c_out, kernel_size=4, stride=2, padding=1),
                nn.BatchNorm2d(c_out),
                nn.ReLU(inplace=True),
            ]
        self.up = nn.Sequential(*layers)
        self.to_rgb = nn.Conv2d(channels[-1], 3, kernel_size=3, padding=1)
        self.c0 = channels[0]

    def forward(self, pooled: torch.Tensor) -> torch.Tensor:
        lead = pooled.shape[:-1]
        x = self.lift(pooled.reshape(-1, self.in_dim)).reshape(-1, self.c0, *self.start)
        img = torch.sigmoid(self.to_rgb(self.up(x)))
        if tuple(img.shape[-2:]) != self.image_size:
            img = F.interpolate(img, size=self.image_size, mode="bilinear", align_corners=False)
        return img.reshape(*lead, 3, *self.image_size)

    @torch.inference_mode()
    def render(self, pooled: np.ndarray | torch.Tensor) -> np.ndarray:
        """(S, in_dim) pooled states → (S, H, W, 3) uint8 images (eval mode)."""
        was = self.training
        self.eval()
        try:
            x = torch.as_tensor(np.asarray(pooled), dtype=torch.float32, device=self.lift.weight.device)
            img = self.forward(x)
        finally:
            self.train(was)
        return (img.movedim(-3, -1) * 255).round().clamp(0, 255).to(torch.uint8).cpu().numpy()
