"""The shared image encoder: a ResNet-18 trunk (``studio.model.resnet``, without global pooling) giving F×H×W
latent states.

Random initialisation by default; ``pretrained=True`` is an explicit opt-in that downloads torchvision's ImageNet
weights (the paper initialises from ImageNet; we keep network access out of the default path). The trunk can be
cut after stage 3 (stride 16) and its maps reduced by a 1×1 convolution to fewer state channels — both used by
the ``cpu`` preset. Inputs are uint8 or float images in [0, 1] of shape (…, 3, H, W); the encoder applies the
ImageNet normalisation itself, so callers never normalise. The trunk keeps its BatchNorm layers (train-mode
statistics over all frames of the batch, as in the paper; they run in eval mode for planning). The convolutions
run in channels-last layout when asked (measured faster on CPU); outputs are returned in that layout, which the
action model's (…, H, W, C) token view reads without a copy.
"""

from __future__ import annotations

import copy

import torch
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from studio.model.resnet import STAGE_CHANNELS, BasicBlock, imagenet_state_dict, resnet18_layers

_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


class Encoder(nn.Module):
    """ResNet-18 trunk → (…, C, H', W') states.

    Attributes:
        out_channels: C, the state channels (the reduction's width, or the last kept stage's channels).
    """

    mean: torch.Tensor  # buffers (register_buffer in __init__)
    std: torch.Tensor

    def __init__(
        self, stages: int = 4, state_channels: int = 0, pretrained: bool = False, channels_last: bool = True
    ) -> None:
        super().__init__()
        if not 1 <= stages <= 4:
            raise ValueError(f"Encoder stages must be 1..4, got {stages}")
        self.trunk = nn.Sequential(*resnet18_layers(stages))
        if pretrained:
            self.trunk.load_state_dict(imagenet_state_dict(stages))
        trunk_channels = STAGE_CHANNELS[stages - 1]
        self.reduce = nn.Conv2d(trunk_channels, state_channels, kernel_size=1) if state_channels > 0 else None
        self.out_channels = state_channels if state_channels > 0 else trunk_channels
        self.channels_last = channels_last
        self.register_buffer("mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        if channels_last:
            self.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stub lacks it

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if images.ndim < 4 or images.shape[-3] != 3:
            raise ValueError(f"Encoder expects (..., 3, H, W) images, got shape {tuple(images.shape)}")
        lead = images.shape[:-3]
        x = images.reshape(-1, *images.shape[-3:])
        x = x.float() / 255.0 if x.dtype == torch.uint8 else x.float()
        x = (x - self.mean) / self.std
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        y = self.trunk(x)
        if self.reduce is not None:
            y = self.reduce(y)
        return y.reshape(*lead, *y.shape[1:])

    @torch.no_grad()
    def fused_for_inference(self) -> Encoder:
        """A copy in eval mode with every BatchNorm folded into the convolution before it (same outputs up to
        rounding, fewer passes over the feature maps); for planning only — it cannot be trained."""
        fused = copy.deepcopy(self).eval()

        def fold(parent: nn.Module, conv_name: str, bn_name: str) -> None:
            conv, bn = getattr(parent, conv_name), getattr(parent, bn_name)
            setattr(parent, conv_name, fuse_conv_bn_eval(conv, bn))
            setattr(parent, bn_name, nn.Identity())

        fold(fused.trunk, "0", "1")
        for stage in list(fused.trunk)[4:]:
            assert isinstance(stage, nn.Sequential)  # after the stem: ResNet stages of BasicBlocks
            for block in stage:
                assert isinstance(block, BasicBlock)
                fold(block, "conv1", "bn1")
                fold(block, "conv2", "bn2")
                if block.downsample is not None:
                    fold(block.downsample, "0", "1")
        if fused.channels_last:
            fused.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # torch's stub lacks it
        fused.requires_grad_(False)
        return fused

    @torch.no_grad()
    def output_shape(self, image_size: tuple[int, int]) -> tuple[int, int, int]:
        """(C, H', W') for an input of ``image_size``, found by running the trunk once (eval mode)."""
        was_training = self.training
        self.eval()
        try:
            probe = torch.zeros(1, 3, *image_size, device=self.mean.device)
            c, h, w = self.forward(probe).shape[1:]
        finally:
            self.train(was_training)
        return int(c), int(h), int(w)
