"""The action model π: latent action a_i = π(r_i, …, r_1, e_N, …, e_1).

The expert states e_1..e_N and the agent states r_1..r_i are one sequence of N + i frames (expert first). Each
frame is H·W tokens of width C — one per cell of the latent state — or a single 2C token when states are pooled
before the world model (ablation). A fixed temporal sin/cos code of the frame index is added to every token, plus
a fixed 2-D sin/cos code of the cell (the paper names only the temporal code; the reference code's flattened
(t, h, w) index codes the cell too, and without it attention could not tell cells apart). The block-causal
transformer (``transformer``; joint attention as in the paper, or divided time-then-space attention —
``ModelConfig.action_attention``; "cross" adds a step where agent tokens attend to all expert tokens — reasons
in ``transformer``) then gives, at the last frame, H·W output tokens: the latent action a_i, shaped like a state
(C, H, W).

The expert prefix is processed once (``context``) and the agent frames one by one (``step``) on top of its
key/value cache: a_i is identical to the last frame's output of one causal pass over all N + i frames.
"""

from __future__ import annotations

import torch
from torch import nn

from studio.model.pooling import grid_encoding, sinusoidal_encoding
from studio.model.transformer import CausalTransformer, KVCache


class ActionModel(nn.Module):
    """π over states shaped ``state_shape``: (C, H, W) maps or (D,) vectors."""

    cell_code: torch.Tensor  # a buffer (register_buffer in __init__)

    def __init__(
        self,
        state_shape: tuple[int, ...],
        blocks: int,
        heads: int,
        attn_dim: int,
        mlp_dim: int,
        dropout: float = 0.0,
        attention: str = "joint",
    ) -> None:
        super().__init__()
        if len(state_shape) not in (1, 3):
            raise ValueError(f"ActionModel state_shape must be (C, H, W) or (D,), got {state_shape}")
        if attention not in ("joint", "divided", "cross"):
            raise ValueError(
                f"ActionModel attention must be 'joint', 'divided' or 'cross', got {attention!r}"
            )
        self.state_shape = tuple(state_shape)
        dim = state_shape[0]
        self.transformer = CausalTransformer(
            dim,
            blocks,
            heads,
            attn_dim,
            mlp_dim,
            dropout,
            divided=attention in ("divided", "cross"),
            cross=attention == "cross",
        )
        if len(state_shape) == 3:
            _, h, w = state_shape
            self.register_buffer("cell_code", grid_encoding(h, w, dim), persistent=False)
        else:
            self.register_buffer("cell_code", torch.zeros(1, dim), persistent=False)

    # ---------------------------------------------------------------- token views
    def _tokens(self, states: torch.Tensor, first_frame: int) -> torch.Tensor:
        """(B, T, *state_shape) → (B, T, S, D) with temporal and cell codes added."""
        b, t = states.shape[:2]
        if len(self.state_shape) == 3:
            c, h, w = self.state_shape
            tokens = states.permute(0, 1, 3, 4, 2).reshape(b, t, h * w, c)
        else:
            tokens = states.reshape(b, t, 1, self.state_shape[0])
        frames = torch.arange(first_frame, first_frame + t, device=states.device)
        time_code = sinusoidal_encoding(frames, tokens.shape[-1]).to(tokens.dtype)
        return tokens + time_code[None, :, None, :] + self.cell_code.to(tokens.dtype)[None, None]

    def _states(self, tokens: torch.Tensor) -> torch.Tensor:
        """(B, T, S, D) → (B, T, *state_shape)."""
        b, t = tokens.shape[:2]
        if len(self.state_shape) == 3:
            c, h, w = self.state_shape
            return tokens.reshape(b, t, h, w, c).permute(0, 1, 4, 2, 3)
        return tokens.reshape(b, t, *self.state_shape)

    # ---------------------------------------------------------------- API
    def context(self, expert_states: torch.Tensor) -> KVCache:
        """Run the expert prefix (B, N, *state_shape) and return its cache."""
        return self.context_and_outputs(expert_states)[0]

    def context_and_outputs(self, expert_states: torch.Tensor) -> tuple[KVCache, torch.Tensor]:
        """The expert prefix's cache and π's outputs at the expert frames (B, N, *state_shape)."""
        out, cache = self.transformer(self._tokens(expert_states, 0), context_frames=expert_states.shape[1])
        return cache, self._states(out)

    def step(self, agent_state: torch.Tensor, cache: KVCache) -> tuple[torch.Tensor, KVCache]:
        """The latent action for the next agent state (B, *state_shape), given the cache of all earlier frames."""
        out, cache = self.transformer(self._tokens(agent_state.unsqueeze(1), cache.frames), cache)
        return self._states(out)[:, 0], cache

    def forward(self, sequence: torch.Tensor, expert_frames: int) -> torch.Tensor:
        """Outputs at every position of a full (B, T, *state_shape) sequence whose first ``expert_frames`` frames
        are the expert's (one causal pass, no cache)."""
        out, _ = self.transformer(self._tokens(sequence, 0), context_frames=expert_frames)
        return self._states(out)
