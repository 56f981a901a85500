"""Block-causal transformer: causality and cache equivalence."""

from __future__ import annotations

import pytest
import torch

from studio.model.transformer import CausalTransformer

torch.set_num_threads(1)


def _model() -> CausalTransformer:
    torch.manual_seed(0)
    return CausalTransformer(dim=16, blocks=2, heads=4, attn_dim=16, mlp_dim=32).eval()


def test_later_frames_never_change_earlier_outputs():
    model = _model()
    x = torch.randn(2, 6, 5, 16)
    y, _ = model(x)
    x2 = x.clone()
    x2[:, 4:] += torch.randn(2, 2, 5, 16)
    y2, _ = model(x2)
    assert torch.allclose(y[:, :4], y2[:, :4], atol=1e-6)
    assert not torch.allclose(y[:, 4:], y2[:, 4:])


def test_tokens_of_one_frame_see_each_other():
    model = _model()
    x = torch.randn(1, 3, 4, 16)
    y, _ = model(x)
    x2 = x.clone()
    x2[:, 1, 3] += torch.randn(16)  # the last token of frame 1 changes every token of frame 1
    y2, _ = model(x2)
    assert not torch.allclose(y[:, 1, 0], y2[:, 1, 0])


@pytest.mark.parametrize("chunks", [[6], [3, 1, 1, 1], [1, 2, 3]])
def test_cached_chunks_equal_one_full_pass(chunks):
    model = _model()
    x = torch.randn(2, 6, 5, 16)
    full, _ = model(x)
    cache, outs, t = None, [], 0
    for c in chunks:
        y, cache = model(x[:, t : t + c], cache)
        outs.append(y)
        t += c
    assert cache.frames == 6
    assert torch.allclose(torch.cat(outs, 1), full, atol=1e-5)


def test_cache_index_select_broadcasts_a_prefix_to_several_sequences():
    model = _model()
    prefix = torch.randn(1, 3, 5, 16)
    tails = torch.randn(3, 1, 5, 16)
    _, cache = model(prefix)
    y, _ = model(tails, cache.index_select(torch.zeros(3, dtype=torch.long)))
    full, _ = model(torch.cat([prefix.expand(3, -1, -1, -1), tails], 1))
    assert torch.allclose(y, full[:, 3:], atol=1e-5)
