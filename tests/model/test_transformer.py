"""Block-causal transformer: causality and cache equivalence."""

from __future__ import annotations

import pytest
import torch

from studio.model.transformer import CausalTransformer

torch.set_num_threads(1)


LAYOUTS = pytest.mark.parametrize("layout", ["joint", "divided", "cross"])
CONTEXT = 2  # leading frames that are the cross step's context (used by the "cross" layout only)


def _model(layout: str = "joint") -> CausalTransformer:
    torch.manual_seed(0)
    return CausalTransformer(
        dim=16, blocks=2, heads=4, attn_dim=16, mlp_dim=32, divided=layout != "joint", cross=layout == "cross"
    ).eval()


@LAYOUTS
def test_later_frames_never_change_earlier_outputs(layout):
    model = _model(layout)
    x = torch.randn(2, 6, 5, 16)
    y, _ = model(x, context_frames=CONTEXT)
    x2 = x.clone()
    x2[:, 4:] += torch.randn(2, 2, 5, 16)
    y2, _ = model(x2, context_frames=CONTEXT)
    assert torch.allclose(y[:, :4], y2[:, :4], atol=1e-6)
    assert not torch.allclose(y[:, 4:], y2[:, 4:])


@LAYOUTS
def test_tokens_of_one_frame_see_each_other(layout):
    model = _model(layout)
    x = torch.randn(1, 3, 4, 16)
    y, _ = model(x, context_frames=CONTEXT)
    x2 = x.clone()
    x2[:, 1, 3] += torch.randn(16)  # the last token of frame 1 changes every token of frame 1
    y2, _ = model(x2, context_frames=CONTEXT)
    assert not torch.allclose(y[:, 1, 0], y2[:, 1, 0])


@LAYOUTS
@pytest.mark.parametrize("chunks", [[6], [3, 1, 1, 1], [2, 1, 3]])
def test_cached_chunks_equal_one_full_pass(chunks, layout):
    model = _model(layout)
    x = torch.randn(2, 6, 5, 16)
    full, _ = model(x, context_frames=CONTEXT)
    cache, outs, t = None, [], 0
    for c in chunks:
        y, cache = model(x[:, t : t + c], cache, context_frames=0 if cache else CONTEXT)
        outs.append(y)
        t += c
    assert cache.frames == 6
    assert torch.allclose(torch.cat(outs, 1), full, atol=1e-5)


@LAYOUTS
def test_cache_index_select_broadcasts_a_prefix_to_several_sequences(layout):
    model = _model(layout)
    prefix = torch.randn(1, 3, 5, 16)
    tails = torch.randn(3, 1, 5, 16)
    _, cache = model(prefix, context_frames=CONTEXT)
    y, _ = model(tails, cache.index_select(torch.zeros(3, dtype=torch.long)))
    full, _ = model(torch.cat([prefix.expand(3, -1, -1, -1), tails], 1), context_frames=CONTEXT)
    assert torch.allclose(y, full[:, 3:], atol=1e-5)


@LAYOUTS
def test_a_token_reads_other_cells_of_earlier_frames(layout):
    """Time then space (divided) still carries a change at any cell of an earlier frame to every cell later on."""
    model = _model(layout)
    x = torch.randn(1, 4, 5, 16)
    y, _ = model(x, context_frames=CONTEXT)
    x2 = x.clone()
    x2[:, 0, 4] += torch.randn(16)
    y2, _ = model(x2, context_frames=CONTEXT)
    assert (y[:, 3, 0] - y2[:, 3, 0]).abs().max() > 1e-4


def test_divided_time_attention_sees_only_the_same_cell_over_time():
    """In one divided block without MLP, before the space step, a cell's time step reads only its own cell."""
    torch.manual_seed(0)
    block = CausalTransformer(dim=8, blocks=1, heads=2, attn_dim=8, mlp_dim=0, divided=True).blocks[0].eval()
    x = torch.randn(1, 3, 4, 8)
    q, k, v = block.qkv(block.norm1(x).reshape(1, 12, 8)).reshape(1, 12, 3, 2, 4).permute(2, 0, 3, 1, 4)
    out = block._time_attention(q, k, v, 3, 4, 0, 0.0)
    x2 = x.clone()
    x2[:, 0, 1] += 5.0  # another cell of an earlier frame
    q2, k2, v2 = block.qkv(block.norm1(x2).reshape(1, 12, 8)).reshape(1, 12, 3, 2, 4).permute(2, 0, 3, 1, 4)
    out2 = block._time_attention(q2, k2, v2, 3, 4, 0, 0.0)
    assert torch.allclose(out[:, :, [0, 2, 3]], out2[:, :, [0, 2, 3]], atol=1e-6)
    assert not torch.allclose(out[:, 1:, 1], out2[:, 1:, 1])


def test_the_cross_step_changes_only_the_frames_after_the_context():
    """Agent tokens read the context through the cross step; the context's own outputs are the divided layout's."""
    cross, divided = _model("cross"), _model("divided")
    divided.load_state_dict(cross.state_dict(), strict=False)
    x = torch.randn(2, 5, 4, 16)
    y_cross, cache = cross(x, context_frames=CONTEXT)
    y_divided, _ = divided(x)
    assert torch.allclose(y_cross[:, :CONTEXT], y_divided[:, :CONTEXT], atol=1e-6)
    assert (y_cross[:, CONTEXT:] - y_divided[:, CONTEXT:]).abs().max() > 1e-3
    assert cache.context is not None and len(cache.context) == 2
    assert cache.context[0][0].shape == (2, 4, CONTEXT * 4, 4)  # (B, heads, context frames · S, head_dim)


def test_context_frames_must_come_whole_and_first():
    model = _model("cross")
    with pytest.raises(ValueError, match="context frames must come in one call"):
        model(torch.randn(1, 1, 4, 16), context_frames=CONTEXT)
    _, cache = model(torch.randn(1, 3, 4, 16), context_frames=CONTEXT)
    with pytest.raises(ValueError, match="given by the cache"):
        model(torch.randn(1, 1, 4, 16), cache, context_frames=CONTEXT)
