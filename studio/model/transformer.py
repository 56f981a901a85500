"""A block-causal transformer over frames of tokens, with per-layer key/value caches.

Both the action model π and the world model 𝒲 are "causal transformers over time": a sequence of T frames, each
made of S tokens of width D (π: S = H·W cells of a latent state; 𝒲: one token per step). A token of frame t
attends to every token of frames ≤ t — all cells of its own frame and of earlier frames — and never to later
frames, so the output at frame t depends only on inputs up to t.

Blocks are pre-LayerNorm (LN → multi-head attention → residual; LN → GELU MLP → residual) with a final LN. This
differs on purpose from the reference code's action-model layer, which normalises with BatchNorm3d over all frames
of the batch (statistics that depend on later frames break causality) and scales attention by √512 instead of
√head_dim; we use LayerNorm and √head_dim (PyTorch's scaled-dot-product attention).

Caching: ``forward(x_new, cache)`` processes new frames given the keys/values of all earlier frames and returns
the extended cache. Feeding frames one at a time with the cache gives exactly the outputs of one pass over the
whole sequence (tested), so the recursive rollout does each frame's work once instead of recomputing the prefix
at every step as the reference does.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F


@dataclass
class KVCache:
    """Keys and values of the frames seen so far, one (k, v) pair per block, each (B, heads, frames·S, head_dim)."""

    layers: list[tuple[torch.Tensor, torch.Tensor]]
    frames: int

    def index_select(self, index: torch.Tensor) -> KVCache:
        """The cache of a batch re-indexed along the batch axis (e.g. unique experts → pairs)."""
        return KVCache(
            [(k.index_select(0, index), v.index_select(0, index)) for k, v in self.layers], self.frames
        )


class CausalBlock(nn.Module):
    def __init__(self, dim: int, heads: int, attn_dim: int, mlp_dim: int, dropout: float) -> None:
        super().__init__()
        if attn_dim % heads:
            raise ValueError(f"attention width {attn_dim} is not divisible by {heads} heads")
        self.heads = heads
        self.attn_dim = attn_dim
        self.dropout = dropout
        self.norm1 = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * attn_dim)
        self.proj = nn.Linear(attn_dim, dim)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = (
            nn.Sequential(nn.Linear(dim, mlp_dim), nn.GELU(), nn.Linear(mlp_dim, dim))
            if mlp_dim > 0
            else None
        )
        self.drop = nn.Dropout(dropout)

    def forward(
        self, x: torch.Tensor, past: tuple[torch.Tensor, torch.Tensor] | None, past_frames: int
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        b, t, s, d = x.shape
        h, hd = self.heads, self.attn_dim // self.heads
        qkv = self.qkv(self.norm1(x).reshape(b, t * s, d))
        q, k, v = qkv.reshape(b, t * s, 3, h, hd).permute(2, 0, 3, 1, 4)
        if past is not None:
            k = torch.cat([past[0], k], dim=2)
            v = torch.cat([past[1], v], dim=2)
        mask = None
        if t > 1:
            q_frame = torch.arange(past_frames, past_frames + t, device=x.device).repeat_interleave(s)
            k_frame = torch.arange(past_frames + t, device=x.device).repeat_interleave(s)
            mask = k_frame[None, :] <= q_frame[:, None]
        attn = F.scaled_dot_product_attention(
            q, k, v, attn_mask=mask, dropout_p=self.dropout if self.training else 0.0
        )
        attn = attn.transpose(1, 2).reshape(b, t, s, self.attn_dim)
        x = x + self.drop(self.proj(attn))
        if self.mlp is not None:
            x = x + self.drop(self.mlp(self.norm2(x)))
        return x, (k, v)


class CausalTransformer(nn.Module):
    """A stack of ``CausalBlock`` over (B, T, S, D) inputs, with a final LayerNorm."""

    def __init__(
        self, dim: int, blocks: int, heads: int, attn_dim: int, mlp_dim: int, dropout: float = 0.0
    ) -> None:
        super().__init__()
        if blocks < 1:
            raise ValueError(f"a causal transformer needs at least one block, got {blocks}")
        self.blocks = nn.ModuleList(
            CausalBlock(dim, heads, attn_dim, mlp_dim, dropout) for _ in range(blocks)
        )
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor, cache: KVCache | None = None) -> tuple[torch.Tensor, KVCache]:
        if x.ndim != 4:
            raise ValueError(f"CausalTransformer expects (B, T, S, D), got shape {tuple(x.shape)}")
        past_frames = 0 if cache is None else cache.frames
        layers = []
        for i, block in enumerate(self.blocks):
            x, kv = block(x, None if cache is None else cache.layers[i], past_frames)
            layers.append(kv)
        return self.norm(x), KVCache(layers, past_frames + x.shape[1])
