"""Our ResNet-18: torchvision's parameter names, initialisation and random-number use; the ImageNet re-keying."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from studio.model.resnet import TRUNK_INDEX, remap_torchvision, resnet18_layers, trunk_key

torch.set_num_threads(1)

# Read off torchvision 0.29.1 (torch 2.14.1): torch.manual_seed(0); net = torchvision.models.resnet18(); the first
# three values of three weights, then torch.rand(5) drawn right after building the network.
TORCHVISION_SEED0 = {
    "conv1.weight": [0.024109674617648125, 0.007528774905949831, 0.04665837436914444],
    "layer3.1.conv2.weight": [0.03378148749470711, 0.03723536804318428, -0.019699130207300186],
    "layer2.0.downsample.0.weight": [-0.10871897637844086, 0.07623140513896942, -0.17475658655166626],
}
TORCHVISION_SEED0_NEXT_RAND = [
    0.8865256309509277,
    0.21111810207366943,
    0.7820602059364319,
    0.7007341384887695,
    0.19891357421875,
]


def torchvision_named(trunk: nn.Sequential) -> dict[str, torch.Tensor]:
    """The trunk's state dict under torchvision's names (the inverse of ``trunk_key``)."""
    names = {index: name for name, index in TRUNK_INDEX.items()}
    out = {}
    for key, value in trunk.state_dict().items():
        index, _, rest = key.partition(".")
        out[f"{names[int(index)]}.{rest}"] = value
    return out


@pytest.mark.parametrize("stages", [1, 3])
def test_seeded_initialisation_and_random_stream_match_torchvision(stages):
    torch.manual_seed(0)
    trunk = nn.Sequential(*resnet18_layers(stages))
    after = torch.rand(5)
    named = torchvision_named(trunk)
    for key, first in TORCHVISION_SEED0.items():
        if key in named:
            assert named[key].flatten()[:3].tolist() == pytest.approx(first, abs=1e-7), key
    assert after.tolist() == pytest.approx(TORCHVISION_SEED0_NEXT_RAND, abs=1e-7)


def test_stages_shapes_and_batchnorm_init():
    trunk = nn.Sequential(*resnet18_layers(4))
    assert len(trunk) == 8
    y = trunk(torch.zeros(2, 3, 64, 96))
    assert y.shape == (2, 512, 2, 3)
    bns = [m for m in trunk.modules() if isinstance(m, nn.BatchNorm2d)]
    assert len(bns) == 20 and all(bool((m.weight == 1).all() and (m.bias == 0).all()) for m in bns)
    assert sum(p.numel() for p in trunk.parameters()) == 11_176_512  # torchvision's 11,689,512 minus fc
    with pytest.raises(ValueError, match="4 stages"):
        resnet18_layers(5)


def test_torchvision_state_dict_is_rekeyed_and_cut_to_the_kept_stages():
    torch.manual_seed(1)
    full = nn.Sequential(*resnet18_layers(4))
    source = torchvision_named(full)
    source["fc.weight"], source["fc.bias"] = torch.zeros(1000, 512), torch.zeros(1000)
    cut = nn.Sequential(*resnet18_layers(2))
    remapped = remap_torchvision(source, stages=2)
    cut.load_state_dict(remapped)  # strict: every key present, nothing extra
    assert torch.equal(cut[5][0].conv1.weight, full[5][0].conv1.weight)
    assert torch.equal(cut[1].running_var, full[1].running_var)
    assert trunk_key("fc.weight") is None and trunk_key("layer4.1.bn2.bias") == "7.1.bn2.bias"
    assert not any(k.startswith(("6.", "7.")) for k in remapped)
