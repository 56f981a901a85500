"""Pooling of latent states: spatial-softmax keypoints, fixed sinusoidal codes, attention pooling over time.

* ``SpatialSoftmax``: a softmax over the H×W cells of each channel and the expected (x, y) position on the
  cell-centre grid of [−1, 1]² (x = −1 is the left image edge; cell j's centre is (2j + 1)/W − 1). A (C, H, W)
  state becomes a 2C vector ``[x_1 … x_C, y_1 … y_C]``. No temperature and no parameters, as in the paper; the
  output is invariant to per-channel additive offsets, which matters because predicted states are unconstrained.
* ``sinusoidal_encoding``: the standard sin/cos table indexed by *time step* along the feature axis (the reference
  code indexes a transposed table; the paper asks for a temporal code, which is what this is). The same function
  gives the 2-D spatial code of the action model (``grid_encoding``: half the channels for rows, half for columns).
* ``AttentionPool``: one learned query attends over the predicted steps (plus their temporal code) and returns
  one vector (multi-head cross attention, temperature √head_dim).
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F


class SpatialSoftmax(nn.Module):
    """(…, C, H, W) maps → (…, 2C) expected keypoint coordinates."""

    def forward(self, maps: torch.Tensor) -> torch.Tensor:
        *lead, c, h, w = maps.shape
        flat = maps.reshape(*lead, c, h * w).float()
        prob = torch.softmax(flat, dim=-1).reshape(*lead, c, h, w)
        xs = (2.0 * torch.arange(w, device=maps.device, dtype=prob.dtype) + 1.0) / w - 1.0
        ys = (2.0 * torch.arange(h, device=maps.device, dtype=prob.dtype) + 1.0) / h - 1.0
        ex = (prob.sum(-2) * xs).sum(-1)
        ey = (prob.sum(-1) * ys).sum(-1)
        return torch.cat([ex, ey], dim=-1)


def sinusoidal_encoding(positions: torch.Tensor, dim: int) -> torch.Tensor:
    """(T,) integer or real positions → (T, dim) sin/cos code (sin on even, cos on odd features)."""
    half = (dim + 1) // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, device=positions.device).float() * 2.0 / dim)
    angles = positions.float()[:, None] * freqs[None, :]
    code = torch.stack([torch.sin(angles), torch.cos(angles)], dim=-1).reshape(len(positions), 2 * half)
    return code[:, :dim]


def grid_encoding(h: int, w: int, dim: int, device: torch.device | None = None) -> torch.Tensor:
    """(h·w, dim) fixed 2-D code of a row-major grid: the first half of the features codes the row, the rest
    the column."""
    dim_rows = dim // 2
    rows = sinusoidal_encoding(torch.arange(h, device=device), dim_rows)
    cols = sinusoidal_encoding(torch.arange(w, device=device), dim - dim_rows)
    return torch.cat([rows[:, None, :].expand(h, w, -1), cols[None, :, :].expand(h, w, -1)], dim=-1).reshape(
        h * w, dim
    )


class AttentionPool(nn.Module):
    """Summarise a (B, T, D) sequence into (B, D) with one learned query (temporal code added to the keys)."""

    def __init__(self, dim: int, heads: int = 1) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"AttentionPool dim {dim} is not divisible by heads {heads}")
        self.heads = heads
        self.query = nn.Parameter(torch.randn(1, 1, dim) * 0.02)
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.out = nn.Linear(dim, dim)

    def forward(self, seq: torch.Tensor) -> torch.Tensor:
        b, t, d = seq.shape
        x = seq + sinusoidal_encoding(torch.arange(t, device=seq.device), d).to(seq.dtype)
        q = self.q(self.query.expand(b, 1, d))
        k, v = self.kv(x).chunk(2, dim=-1)
        h = self.heads

        def split(z: torch.Tensor) -> torch.Tensor:
            return z.reshape(b, -1, h, d // h).transpose(1, 2)

        pooled = F.scaled_dot_product_attention(split(q), split(k), split(v))
        return self.out(pooled.transpose(1, 2).reshape(b, d))
