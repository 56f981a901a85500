"""The world model 𝒲: r_{i+1} = 𝒲(r_i, a_i, …, r_1, a_1).

Each step's token is the state and its latent action concatenated along the features ([state ‖ action], 2C×H×W)
and projected by one dense linear layer to the model width — the whole map is one token, as in the paper and the
reference code. A fixed temporal sin/cos code is added (the reference learns a 30-slot table; the fixed code has no
length limit), the tokens go through a causal transformer (1 block, 4 heads in the paper), and the output at the
last step is projected by a second dense layer back to C×H×W: the next state, unconstrained (no activation),
since it is only read through the spatial softmax. With ``residual`` the projection is a change added to the
current state, r_{i+1} = r_i + 𝒲(…), starting at zero (an option; off in every preset): it kept the plain map form
from collapsing to one input-independent map early in training from random weights (pooled keypoint spread 6e-5
after 400 steps), but with the zero start π receives no gradient at first and, on the synthetic
follow-the-demonstration task (``tests/model/test_train.py``), never came to use the demonstration. Sizes follow
from the state shape probed from the encoder, never from a hard-coded map size. Maps are flattened in (H, W, C)
order, which is a free view of the encoder's channels-last output. Steps are fed one at a time on top of a
key/value cache.

With ``tokens="cells"`` (the ``cpu`` preset) each cell of the map is a token instead: [state ‖ action] of one
cell (2C) is projected to the width, a fixed 2-D code of the cell is added, the causal transformer runs divided
time-then-space attention (``transformer``), and each cell's output is projected back to that cell's C channels.
Measured reason: with one dense token per map, a latent action that differed between two demonstrations by 3 %
moved the predicted state by 0.005 % (real data, 300 training steps), and on the synthetic task the map form
never let the demonstration move the plan (0.0 m after 300 steps, with divided attention in π), while per-cell
tokens did (0.21 m, final error 0.069 m against 0.18 m for the mean). Per-cell tokens keep π's mark at the cell
where it is, which is where the spatial softmax reads keypoints from.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from studio.model.pooling import grid_encoding, sinusoidal_encoding
from studio.model.transformer import CausalTransformer, KVCache


class WorldModel(nn.Module):
    """𝒲 over states shaped ``state_shape``: (C, H, W) maps or (D,) vectors."""

    cell_code: torch.Tensor  # a buffer (register_buffer in __init__), with per-cell tokens only

    def __init__(
        self,
        state_shape: tuple[int, ...],
        width: int,
        blocks: int,
        heads: int,
        mlp_dim: int,
        dropout: float = 0.0,
        residual: bool = False,
        tokens: str = "map",
    ) -> None:
        super().__init__()
        if len(state_shape) not in (1, 3):
            raise ValueError(f"WorldModel state_shape must be (C, H, W) or (D,), got {state_shape}")
        if tokens not in ("map", "cells"):
            raise ValueError(f"WorldModel tokens must be 'map' or 'cells', got {tokens!r}")
        self.state_shape = tuple(state_shape)
        self.per_cell = tokens == "cells" and len(state_shape) == 3
        size = state_shape[0] if self.per_cell else math.prod(state_shape)
        self.embed = nn.Linear(2 * size, width)
        self.embed_drop = nn.Dropout(dropout)
        self.transformer = CausalTransformer(width, blocks, heads, width, mlp_dim, 0.0, divided=self.per_cell)
        self.out = nn.Linear(width, size)
        if self.per_cell:
            _, h, w = state_shape
            self.register_buffer("cell_code", grid_encoding(h, w, width), persistent=False)
        self.residual = residual
        if residual:  # starts as the identity map r_{i+1} = r_i, so predicted states keep the frame's layout
            nn.init.zeros_(self.out.weight)
            nn.init.zeros_(self.out.bias)

    def _flat(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, *state_shape) → (B, T, S, size): one token of the whole map, or one per cell, (H, W, C) order."""
        if len(self.state_shape) == 3:
            x = x.movedim(-3, -1)
        b, t = x.shape[:2]
        return x.reshape(b, t, -1, self.out.out_features)

    def _unflat(self, y: torch.Tensor) -> torch.Tensor:
        """(B, T, S, size) → (B, T, *state_shape)."""
        b, t = y.shape[:2]
        if len(self.state_shape) == 3:
            c, h, w = self.state_shape
            return y.reshape(b, t, h, w, c).movedim(-1, -3)
        return y.reshape(b, t, *self.state_shape)

    def _tokens(self, states: torch.Tensor, actions: torch.Tensor, first_step: int) -> torch.Tensor:
        """(B, T, *state_shape) ×2 → (B, T, S, width) with S = 1 (map) or H·W (cells)."""
        tokens = self.embed(torch.cat([self._flat(states), self._flat(actions)], dim=-1))
        steps = torch.arange(first_step, first_step + tokens.shape[1], device=tokens.device)
        tokens = tokens + sinusoidal_encoding(steps, tokens.shape[-1]).to(tokens.dtype)[None, :, None]
        if self.per_cell:
            tokens = tokens + self.cell_code.to(tokens.dtype)[None, None]
        return self.embed_drop(tokens)

    def step(
        self, state: torch.Tensor, action: torch.Tensor, cache: KVCache | None
    ) -> tuple[torch.Tensor, KVCache]:
        """The next state (B, *state_shape) from the current state and action and the cache of earlier steps."""
        first = 0 if cache is None else cache.frames
        out, cache = self.transformer(self._tokens(state.unsqueeze(1), action.unsqueeze(1), first), cache)
        nxt = self._unflat(self.out(out))[:, 0]
        return (state + nxt if self.residual else nxt), cache

    def forward(self, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Predicted next states at every step of full (B, T, …) sequences (one causal pass, no cache)."""
        out, _ = self.transformer(self._tokens(states, actions, 0))
        nxt = self._unflat(self.out(out))
        return states + nxt if self.residual else nxt
