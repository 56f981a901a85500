"""The ResNet-18 trunk: output sizes for several resolutions and cuts, input handling."""

from __future__ import annotations

import pytest
import torch

from studio.model.encoder import Encoder

torch.set_num_threads(1)


@pytest.mark.parametrize(
    ("stages", "reduce", "size", "expected"),
    [
        (4, 0, (224, 224), (512, 7, 7)),
        (4, 0, (240, 320), (512, 8, 10)),
        (3, 64, (120, 160), (64, 8, 10)),
        (2, 16, (48, 64), (16, 6, 8)),
        (4, 32, (96, 128), (32, 3, 4)),
    ],
)
def test_output_shape_is_probed_for_any_resolution(stages, reduce, size, expected):
    enc = Encoder(stages, reduce)
    assert enc.output_shape(size) == expected
    assert enc.out_channels == expected[0]


def test_uint8_and_unit_float_inputs_agree_and_leading_axes_are_kept():
    torch.manual_seed(0)
    enc = Encoder(2, 8).eval()
    frames = torch.randint(0, 256, (2, 3, 3, 32, 48), dtype=torch.uint8)
    with torch.no_grad():
        a = enc(frames)
        b = enc(frames.float() / 255.0)
    assert a.shape == (2, 3, 8, 4, 6)
    assert torch.allclose(a, b, atol=1e-5)


def test_channels_last_changes_layout_not_values():
    torch.manual_seed(0)
    a = Encoder(2, 8, channels_last=True).eval()
    b = Encoder(2, 8, channels_last=False).eval()
    b.load_state_dict(a.state_dict())
    x = torch.rand(2, 3, 32, 48)
    with torch.no_grad():
        assert torch.allclose(a(x), b(x), atol=1e-5)


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match="3, H, W"):
        Encoder(1)(torch.zeros(2, 4, 32, 32))


def test_folding_batchnorm_for_inference_keeps_the_outputs():
    torch.manual_seed(0)
    enc = Encoder(3, 16).eval()
    for m in enc.modules():  # non-trivial statistics, as after training
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    fused = enc.fused_for_inference()
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fused.modules())
    x = torch.rand(2, 3, 64, 80)
    with torch.no_grad():
        assert torch.allclose(enc(x), fused(x), atol=1e-4)
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in enc.modules())  # the original is untouched
