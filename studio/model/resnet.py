"""ResNet-18 (He et al. 2016) written out, with torchvision's parameter names and initialisation.

The encoder's trunk. We keep it here rather than importing torchvision: torchvision's wheels are built against
PyPI's CUDA build of torch (~5.5 GB installed with its CUDA libraries, more than CI machines have free), and
they do not load beside the CPU-only torch we install (docs/dependencies.md). Parameter names match
``torchvision.models.resnet18`` (``conv1``, ``bn1``, ``layer1.0.conv1`` …), so checkpoints written while the
trunk came from torchvision load unchanged, and the ImageNet weights torchvision publishes load with
``imagenet_state_dict`` — an explicit opt-in that downloads, never the default.
"""

from __future__ import annotations

import torch
from torch import nn

#: torchvision's ResNet-18 ImageNet weights (IMAGENET1K_V1); the hash prefix in the name is checked on download.
IMAGENET_URL = "https://download.pytorch.org/models/resnet18-f37072fd.pth"

STAGE_CHANNELS = (64, 128, 256, 512)
#: torchvision's top-level module names → their index in ``nn.Sequential(*resnet18_layers())``.
TRUNK_INDEX = {"conv1": 0, "bn1": 1, "layer1": 4, "layer2": 5, "layer3": 6, "layer4": 7}


class BasicBlock(nn.Module):
    """Two 3×3 convolutions with a residual connection; a strided 1×1 projection when the shape changes."""

    def __init__(self, in_channels: int, channels: int, stride: int = 1) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, channels, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(channels)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)
        self.downsample: nn.Module | None = None
        if stride != 1 or in_channels != channels:
            self.downsample = nn.Sequential(
                nn.Conv2d(in_channels, channels, 1, stride=stride, bias=False), nn.BatchNorm2d(channels)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


def stage(in_channels: int, channels: int, stride: int) -> nn.Sequential:
    """One ResNet-18 stage: two basic blocks, the first one strided."""
    return nn.Sequential(BasicBlock(in_channels, channels, stride), BasicBlock(channels, channels, 1))


def resnet18_layers(stages: int = 4) -> list[nn.Module]:
    """The stem (conv1, bn1, relu, maxpool) and the first ``stages`` stages, freshly initialised as torchvision
    does (Kaiming-normal convolutions, fan-out, ReLU gain; BatchNorm weight 1, bias 0).

    The whole network, classifier included, is built and initialised before the unused part is dropped, so the
    random-number stream is consumed exactly as by ``torchvision.models.resnet18()``: a seeded run draws the
    same initial weights as runs made when the trunk came from torchvision (and so do the modules built after
    the encoder).
    """
    if not 1 <= stages <= 4:
        raise ValueError(f"ResNet-18 has 4 stages, asked for {stages}")
    layers: list[nn.Module] = [
        nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False),
        nn.BatchNorm2d(64),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(3, stride=2, padding=1),
    ]
    in_channels = 64
    for i, channels in enumerate(STAGE_CHANNELS):
        layers.append(stage(in_channels, channels, 1 if i == 0 else 2))
        in_channels = channels
    classifier = nn.Linear(in_channels, 1000)  # built only to draw from the random stream as torchvision does
    for layer in [*layers, classifier]:
        for m in layer.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
    return layers[: 4 + stages]


def trunk_key(torchvision_key: str) -> str | None:
    """Where a torchvision ResNet-18 parameter lives in ``nn.Sequential(*resnet18_layers())``; None for the
    classifier (``fc``) and anything else the trunk does not have."""
    head, _, rest = torchvision_key.partition(".")
    index = TRUNK_INDEX.get(head)
    return None if index is None or not rest else f"{index}.{rest}"


def imagenet_state_dict(stages: int = 4) -> dict[str, torch.Tensor]:
    """torchvision's ImageNet weights for the first ``stages`` stages, keyed for the trunk. Downloads (~45 MB,
    cached by ``torch.hub``) — call it only when the user asked for pretrained weights."""
    source = torch.hub.load_state_dict_from_url(
        IMAGENET_URL, map_location="cpu", check_hash=True, progress=False
    )
    return remap_torchvision(source, stages)


def remap_torchvision(source: dict[str, torch.Tensor], stages: int = 4) -> dict[str, torch.Tensor]:
    """A torchvision ResNet-18 state dict re-keyed for a trunk of ``stages`` stages (later stages and ``fc``
    dropped)."""
    out = {}
    for key, value in source.items():
        mapped = trunk_key(key)
        if mapped is not None and int(mapped.split(".")[0]) < 4 + stages:
            out[mapped] = value
    return out
