"""Spatial softmax keypoints, sinusoidal codes and attention pooling."""

from __future__ import annotations

import torch

from studio.model.pooling import AttentionPool, SpatialSoftmax, grid_encoding, sinusoidal_encoding

torch.set_num_threads(1)


def test_spatial_softmax_finds_a_sharp_peak_on_the_cell_centre_grid():
    maps = torch.zeros(2, 3, 4, 5)
    maps[0, 1, 2, 3] = 50.0  # row 2 of 4, column 3 of 5
    out = SpatialSoftmax()(maps)
    assert out.shape == (2, 6)
    assert torch.allclose(out[0, 1], torch.tensor((2 * 3 + 1) / 5 - 1), atol=1e-5)  # x of channel 1
    assert torch.allclose(out[0, 3 + 1], torch.tensor((2 * 2 + 1) / 4 - 1), atol=1e-5)  # y of channel 1
    assert torch.allclose(out[1], torch.zeros(6), atol=1e-6)  # uniform maps → the centre


def test_spatial_softmax_is_invariant_to_per_channel_offsets():
    maps = torch.randn(3, 8, 6, 7, generator=torch.Generator().manual_seed(0))
    shifted = maps + torch.randn(3, 8, 1, 1, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(SpatialSoftmax()(maps), SpatialSoftmax()(shifted), atol=1e-5)


def test_sinusoidal_codes_are_distinct_per_step_and_bounded():
    code = sinusoidal_encoding(torch.arange(6), 16)
    assert code.shape == (6, 16) and code.abs().max() <= 1.0
    assert torch.cdist(code, code).add(torch.eye(6) * 10).min() > 0.1
    assert grid_encoding(3, 4, 10).shape == (12, 10)
    assert torch.equal(sinusoidal_encoding(torch.arange(1), 4)[0], torch.tensor([0.0, 1.0, 0.0, 1.0]))


def test_attention_pool_depends_on_step_order_through_the_temporal_code():
    torch.manual_seed(0)
    pool = AttentionPool(8, heads=2)
    seq = torch.randn(2, 5, 8)
    out = pool(seq)
    assert out.shape == (2, 8)
    assert not torch.allclose(out, pool(seq.flip(1)))
