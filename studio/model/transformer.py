"""A block-causal transformer over frames of tokens, with per-layer key/value caches.

Both the action model π and the world model 𝒲 are "causal transformers over time": a sequence of T frames, each
made of S tokens of width D (π: S = H·W cells of a latent state; 𝒲: one token per step). A token of frame t
attends to every token of frames ≤ t — all cells of its own frame and of earlier frames — and never to later
frames, so the output at frame t depends only on inputs up to t.

Blocks are pre-LayerNorm (LN → multi-head attention → residual; LN → GELU MLP → residual) with a final LN. This
differs on purpose from the reference code's action-model layer, which normalises with BatchNorm3d over all frames
of the batch (statistics that depend on later frames break causality) and scales attention by √512 instead of
√head_dim; we use LayerNorm and √head_dim (PyTorch's scaled-dot-product attention).

Attention layout (``divided``): "joint" attention lets every token attend to every token of frames ≤ t at once,
as the paper describes. "divided" factorises it as in video transformers (TimeSformer's divided space-time
attention): each block first attends over *time* — a token attends to the same cell in frames ≤ t — then over
*space* — to the other cells of its own frame — then the MLP. Measured on our CPU budget, joint attention over
the 10 × 108 expert tokens of the ``cpu`` preset stayed near-uniform, so what π passed on was an average over
the whole demonstration: after 500 training steps swapping the demonstration for another task's changed the latent
action by 0.05 % and the waypoints not at all. With divided attention a cell of the agent's frame reads, from
its first step, what happened at that place during the demonstration (over 10 frames, not 1 188 tokens), and
the space step relays it to the cells that look alike (the same object elsewhere in the agent's scene).
Causality and caching are the same in both layouts; the cache holds the time-attention keys and values.

Cross step (``cross``; π's ``action_attention="cross"``, an option — the ``cpu`` preset stays divided): after
time and space, every token of a frame *after the context* (π's agent frames) also attends to every token of the
context frames (π's expert frames, all cells, all times) — a content-addressed look-up of the demonstration, for
matching the demonstrated object by appearance in one hop. The context tokens themselves do not cross-attend, so
their outputs are those of the divided layout, and the cross keys and values of the context are cached once.
Measured on the pick-and-place data it did not help within 500 steps (validation path error 0.079 m, as
divided; docs/experiments.md).

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
    context: list[tuple[torch.Tensor, torch.Tensor]] | None = (
        None  # cross keys/values of the context, per block
    )

    def index_select(self, index: torch.Tensor) -> KVCache:
        """The cache of a batch re-indexed along the batch axis (e.g. unique experts → pairs)."""

        def pick(pairs: list[tuple[torch.Tensor, torch.Tensor]]) -> list[tuple[torch.Tensor, torch.Tensor]]:
            return [(k.index_select(0, index), v.index_select(0, index)) for k, v in pairs]

        return KVCache(pick(self.layers), self.frames, None if self.context is None else pick(self.context))


class CausalBlock(nn.Module):
    """One pre-LN block: joint attention over frames ≤ t, or time then space attention (``divided``), then the
    cross step to the context (``cross``), then MLP."""

    def __init__(
        self,
        dim: int,
        heads: int,
        attn_dim: int,
        mlp_dim: int,
        dropout: float,
        divided: bool = False,
        cross: bool = False,
    ) -> None:
        super().__init__()
        if attn_dim % heads:
            raise ValueError(f"attention width {attn_dim} is not divisible by {heads} heads")
        self.heads = heads
        self.attn_dim = attn_dim
        self.dropout = dropout
        self.divided = divided
        self.norm1 = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * attn_dim)
        self.proj = nn.Linear(attn_dim, dim)
        if divided:
            self.norm_space = nn.LayerNorm(dim)
            self.qkv_space = nn.Linear(dim, 3 * attn_dim)
            self.proj_space = nn.Linear(attn_dim, dim)
        self.cross = cross
        if cross:
            self.norm_cross = nn.LayerNorm(dim)
            self.q_cross = nn.Linear(dim, attn_dim)
            self.kv_cross = nn.Linear(dim, 2 * attn_dim)
            self.proj_cross = nn.Linear(attn_dim, dim)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = (
            nn.Sequential(nn.Linear(dim, mlp_dim), nn.GELU(), nn.Linear(mlp_dim, dim))
            if mlp_dim > 0
            else None
        )
        self.drop = nn.Dropout(dropout)

    def forward(
        self,
        x: torch.Tensor,
        past: tuple[torch.Tensor, torch.Tensor] | None,
        past_frames: int,
        context: tuple[torch.Tensor, torch.Tensor] | None = None,
        context_frames: int = 0,
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor] | None]:
        """One block over new frames x (B, t, S, D) given the earlier frames' keys/values ``past``.

        ``context`` holds the cross keys/values of earlier context frames; otherwise the first
        ``context_frames`` frames of x are the context. Returns the new x, the extended keys/values and the
        context's cross keys/values (None without a context or without the cross step).
        """
        b, t, s, d = x.shape
        h, hd = self.heads, self.attn_dim // self.heads
        qkv = self.qkv(self.norm1(x).reshape(b, t * s, d))
        q, k, v = qkv.reshape(b, t * s, 3, h, hd).permute(2, 0, 3, 1, 4)
        if past is not None:
            k = torch.cat([past[0], k], dim=2)
            v = torch.cat([past[1], v], dim=2)
        p_drop = self.dropout if self.training else 0.0
        if self.divided:
            x = x + self.drop(self.proj(self._time_attention(q, k, v, t, s, past_frames, p_drop)))
            x = x + self.drop(self.proj_space(self._space_attention(self.norm_space(x), p_drop)))
        else:
            mask = None
            if t > 1:
                q_frame = torch.arange(past_frames, past_frames + t, device=x.device).repeat_interleave(s)
                k_frame = torch.arange(past_frames + t, device=x.device).repeat_interleave(s)
                mask = k_frame[None, :] <= q_frame[:, None]
            attn = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=p_drop)
            x = x + self.drop(self.proj(attn.transpose(1, 2).reshape(b, t, s, self.attn_dim)))
        if self.cross:
            x, context = self._cross_step(x, context, context_frames, p_drop)
        else:
            context = None
        if self.mlp is not None:
            x = x + self.drop(self.mlp(self.norm2(x)))
        return x, (k, v), context

    def _cross_step(
        self,
        x: torch.Tensor,
        context: tuple[torch.Tensor, torch.Tensor] | None,
        context_frames: int,
        p_drop: float,
    ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor] | None]:
        """Tokens of the frames after the context attend to all context tokens (see the module docstring)."""
        b, t, s, _ = x.shape
        h, hd = self.heads, self.attn_dim // self.heads
        xn = self.norm_cross(x)
        first = 0
        if context is None:
            if context_frames == 0:
                return x, None
            first = context_frames
            kv = self.kv_cross(xn[:, :first].reshape(b, first * s, -1))
            k, v = kv.reshape(b, first * s, 2, h, hd).permute(2, 0, 3, 1, 4)  # (B, heads, frames·S, hd)
            context = (k, v)
        if t > first:
            q = (
                self.q_cross(xn[:, first:].reshape(b, (t - first) * s, -1))
                .reshape(b, -1, h, hd)
                .transpose(1, 2)
            )
            out = F.scaled_dot_product_attention(q, context[0], context[1], dropout_p=p_drop)
            out = out.transpose(1, 2).reshape(b, t - first, s, self.attn_dim)
            x = torch.cat([x[:, :first], x[:, first:] + self.drop(self.proj_cross(out))], dim=1)
        return x, context

    def _time_attention(
        self,
        q: torch.Tensor,
        k: torch.Tensor,
        v: torch.Tensor,
        t: int,
        s: int,
        past_frames: int,
        p_drop: float,
    ) -> torch.Tensor:
        """Each cell attends to itself in frames ≤ its own: (B, heads, frames·S, hd) → (B, t, S, attn_dim)."""
        b, h, _, hd = q.shape
        frames = past_frames + t
        q = q.reshape(b, h, t, s, hd).permute(0, 3, 1, 2, 4)  # (B, S, heads, t, hd)
        k = k.reshape(b, h, frames, s, hd).permute(0, 3, 1, 2, 4)
        v = v.reshape(b, h, frames, s, hd).permute(0, 3, 1, 2, 4)
        mask = None
        if t > 1:
            q_frame = torch.arange(past_frames, frames, device=q.device)
            mask = torch.arange(frames, device=q.device)[None, :] <= q_frame[:, None]
        out = F.scaled_dot_product_attention(
            q, k, v, attn_mask=mask, dropout_p=p_drop
        )  # (B, S, heads, t, hd)
        return out.permute(0, 3, 1, 2, 4).reshape(b, t, s, self.attn_dim)

    def _space_attention(self, x: torch.Tensor, p_drop: float) -> torch.Tensor:
        """Each cell attends to every cell of its own frame: (B, t, S, D) → (B, t, S, attn_dim)."""
        b, t, s, _ = x.shape
        h, hd = self.heads, self.attn_dim // self.heads
        q, k, v = (
            self.qkv_space(x).reshape(b, t, s, 3, h, hd).permute(3, 0, 1, 4, 2, 5)
        )  # (B, t, heads, S, hd)
        out = F.scaled_dot_product_attention(q, k, v, dropout_p=p_drop)
        return out.transpose(2, 3).reshape(b, t, s, self.attn_dim)


class CausalTransformer(nn.Module):
    """A stack of ``CausalBlock`` over (B, T, S, D) inputs, with a final LayerNorm."""

    def __init__(
        self,
        dim: int,
        blocks: int,
        heads: int,
        attn_dim: int,
        mlp_dim: int,
        dropout: float = 0.0,
        divided: bool = False,
        cross: bool = False,
    ) -> None:
        super().__init__()
        if blocks < 1:
            raise ValueError(f"a causal transformer needs at least one block, got {blocks}")
        self.blocks = nn.ModuleList(
            CausalBlock(dim, heads, attn_dim, mlp_dim, dropout, divided, cross) for _ in range(blocks)
        )
        self.norm = nn.LayerNorm(dim)

    def forward(
        self, x: torch.Tensor, cache: KVCache | None = None, context_frames: int = 0
    ) -> tuple[torch.Tensor, KVCache]:
        """Outputs for the new frames x (B, T, S, D) and the extended cache.

        ``context_frames``: without a cache, how many leading frames of x are the context of the cross step
        (ignored unless the blocks have one); with a cache, the context is the one it holds.
        """
        if x.ndim != 4:
            raise ValueError(f"CausalTransformer expects (B, T, S, D), got shape {tuple(x.shape)}")
        if cache is not None and context_frames:
            raise ValueError("context_frames is given by the cache once there is one")
        if context_frames > x.shape[1]:
            raise ValueError(
                f"the {context_frames} context frames must come in one call, got {x.shape[1]} frames"
            )
        past_frames = 0 if cache is None else cache.frames
        layers: list[tuple[torch.Tensor, torch.Tensor]] = []
        contexts: list[tuple[torch.Tensor, torch.Tensor]] = []
        for i, block in enumerate(self.blocks):
            past = None if cache is None else cache.layers[i]
            context = None if cache is None or cache.context is None else cache.context[i]
            x, kv, context = block(x, past, past_frames, context, context_frames)
            layers.append(kv)
            if context is not None:  # every block has the cross step, or none
                contexts.append(context)
        return self.norm(x), KVCache(layers, past_frames + x.shape[1], contexts or None)
