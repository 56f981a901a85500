"""Latent decoder: output sizes for several resolutions and uint8 rendering."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from studio.model.config import DecoderConfig
from studio.model.decoder import LatentDecoder

torch.set_num_threads(1)


@pytest.mark.parametrize(("size", "stages"), [((48, 64), 3), ((120, 160), 4), ((50, 70), 3)])
def test_decodes_pooled_states_to_images_of_the_model_size(size, stages):
    dec = LatentDecoder(32, size, DecoderConfig(base_channels=32, stages=stages))
    out = dec(torch.randn(2, 3, 32))
    assert out.shape == (2, 3, 3, *size) and out.min() >= 0 and out.max() <= 1


def test_render_gives_uint8_hwc_frames():
    dec = LatentDecoder(8, (24, 32), DecoderConfig(base_channels=16, stages=2))
    img = dec.render(np.zeros((4, 8), dtype=np.float32))
    assert img.shape == (4, 24, 32, 3) and img.dtype == np.uint8 and dec.training
