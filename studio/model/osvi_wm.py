"""The OSVI-WM network: encoder → action model π ⇄ world model 𝒲 recursion → pooling → waypoint head.

Data flow (paper section 3, appendix A):

1. The shared encoder maps every expert frame E_1..E_N and the agent's first frame R_1 to latent states
   e_1..e_N, r_1 of shape (C, H, W) — sizes probed from the encoder at construction for ``cfg.image_size``.
2. For i = 1 … M−1: a_i = π(r_i, …, r_1, e_N, …, e_1) (output of the causal action model at the last frame);
   r_{i+1} = 𝒲(r_i, a_i, …, r_1, a_1). Both run on key/value caches, so each frame is processed once.
3. Each predicted state r_2..r_M is pooled by the spatial softmax into a 2C keypoint vector; a temporal sin/cos
   code is added and attention pooling with one learned query gives one 2C vector.
4. A two-layer MLP (Linear → GELU → Dropout → Linear) predicts ``waypoint_rows`` = 1 + 2 + … + 5 = 15 rows: the
   waypoint sets of 1..5 waypoints stacked (set n = rows n(n−1)/2 … n(n+1)/2 − 1; the 5-set is the last 5 rows).

Waypoint row (x, y, d, g): (x, y) the position in the *input image's* normalised coordinates [−1, 1]; depth
z = depth_offset + depth_scale · d metres (``depth_offset`` is a buffer set from the training data, saved with
the weights); g a gripper logit — closed when sigmoid(g) > 0.5. ``decode_waypoints`` converts to camera-frame
metres with the intrinsics of the (possibly augmented) input image (``geometry``), so every augmentation that is a
pixel-space affine map keeps the labels consistent.

For training, ``forward`` also encodes the real future agent frames as world-model targets, under
``torch.no_grad`` when the stop-gradient is on (they are only targets), with gradient otherwise (ablation). Expert
videos are passed once per unique demonstration with ``expert_ids`` mapping pairs to them, so a demonstration
shared by several pairs of a batch is encoded and run through π's expert prefix once.

Choices against the paper / reference code: no EMA target encoder (the reference computes one and never uses
it); LayerNorm instead of BatchNorm3d in π (causality); attention temperature √head_dim; a real temporal sinusoid
before the attention pooling; ablations as config switches (``config``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

from studio.model.action_model import ActionModel
from studio.model.config import ModelConfig
from studio.model.encoder import Encoder
from studio.model.geometry import image_to_camera
from studio.model.pooling import AttentionPool, SpatialSoftmax
from studio.model.transformer import KVCache
from studio.model.world_model import WorldModel

TargetMode = Literal["none", "detached", "grad"]


@dataclass
class ModelOutput:
    """What one forward pass returns.

    Attributes:
        waypoints: (B, rows, 4) raw rows (x, y, d, g-logit) — decode with ``OSVIWM.decode_waypoints``.
        actions: (B, S, *state_shape) latent actions a_1..a_S.
        states: (B, S, *state_shape) predicted states r_2..r_{S+1} (the actions when there is no world model).
        pooled: (B, S, 2C) spatially pooled predicted states.
        target_pooled: (B, S, 2C) pooled encodings of the real future agent frames, or None.
        demo_task_logits: (U, classes) the demonstration-task classifier's logits per expert video, or None.
    """

    waypoints: torch.Tensor
    actions: torch.Tensor
    states: torch.Tensor
    pooled: torch.Tensor
    target_pooled: torch.Tensor | None
    demo_task_logits: torch.Tensor | None = None


class OSVIWM(nn.Module):
    """The full network; every size derives from ``ModelConfig`` and the probed encoder output."""

    depth_offset: torch.Tensor  # a buffer (register_buffer in __init__)

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = Encoder(cfg.encoder_stages, cfg.state_channels, cfg.pretrained, cfg.channels_last)
        c, h, w = self.encoder.output_shape(cfg.image_size)
        self.map_shape = (c, h, w)
        self.pooled_dim = 2 * c
        self.state_shape: tuple[int, ...] = (self.pooled_dim,) if cfg.pool_before_wm else (c, h, w)
        self.spatial_pool = SpatialSoftmax()
        self.action_model = ActionModel(
            self.state_shape,
            cfg.action_blocks,
            cfg.action_heads,
            cfg.action_attn_dim,
            cfg.action_mlp_dim,
            cfg.action_dropout,
            cfg.action_attention,
        )
        self.world_model = (
            WorldModel(
                self.state_shape,
                cfg.wm_width,
                cfg.wm_blocks,
                cfg.wm_heads,
                cfg.wm_mlp_dim,
                cfg.wm_dropout,
                residual=cfg.wm_residual,
                tokens=cfg.wm_tokens,
            )
            if cfg.world_model
            else None
        )
        self.temporal_pool = AttentionPool(self.pooled_dim, cfg.pool_heads)
        self.head = nn.Sequential(
            nn.Linear(self.pooled_dim, cfg.head_hidden),
            nn.GELU(),
            nn.Dropout(cfg.head_dropout),
            nn.Linear(cfg.head_hidden, cfg.waypoint_rows * 4),
        )
        self.register_buffer("depth_offset", torch.tensor(float(cfg.depth_offset)))
        self._frozen: tuple[str, ...] = ()  # submodules held fixed (``freeze``)
        # Optional (not in the paper): names the demonstrated task from π's outputs at the expert frames,
        # averaged over frames and cells; trained by TrainConfig.demo_task_weight.
        self.demo_task_head = (
            nn.Sequential(
                nn.LayerNorm(self.state_shape[0]), nn.Linear(self.state_shape[0], cfg.demo_task_classes)
            )
            if cfg.demo_task_classes > 0
            else None
        )

    # ---------------------------------------------------------------- frozen parts
    def freeze(self, parts: tuple[str, ...]) -> None:
        """Hold the named submodules fixed: no gradient, and eval mode whatever ``train()`` asks, so BatchNorm
        keeps the statistics it was trained with. A part the model does not have (no 𝒲) is ignored."""
        self._frozen = tuple(p for p in parts if getattr(self, p, None) is not None)
        for name in self._frozen:
            getattr(self, name).requires_grad_(False)
        self.train(self.training)

    def train(self, mode: bool = True) -> OSVIWM:
        super().train(mode)
        for name in self._frozen:
            getattr(self, name).eval()
        return self

    # ---------------------------------------------------------------- pieces
    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """(…, 3, H, W) uint8 or [0, 1] frames → (…, *state_shape) states."""
        maps = self.encoder(frames)
        return self.spatial_pool(maps) if self.cfg.pool_before_wm else maps

    def pool(self, states: torch.Tensor) -> torch.Tensor:
        """(…, *state_shape) → (…, 2C) keypoints (identity when states are already pooled)."""
        return states if self.cfg.pool_before_wm else self.spatial_pool(states)

    def target_frame_indices(self) -> list[int]:
        """Indices of the agent frames whose encodings supervise the predicted states."""
        m = self.cfg.n_agent_frames
        return [m - 1] if self.cfg.single_step else list(range(1, m))

    def rollout(
        self, expert_states: torch.Tensor, agent_state: torch.Tensor, expert_ids: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Latent actions and predicted states (B, S, *state_shape) from expert states (U, N, …) and r_1 (B, …)."""
        cache = self.action_model.context(expert_states)
        pairs = _pair_context(cache, expert_ids, expert_states.shape[0], agent_state.shape[0])
        return self.rollout_from_context(pairs, agent_state)

    def rollout_from_context(
        self, context: KVCache, agent_state: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The recursion a_i = π(…), r_{i+1} = 𝒲(…) on top of π's cache of the expert prefix."""
        actions, states = [], []
        cache, state, wm_cache = context, agent_state, None
        for _ in range(self.cfg.predicted_steps):
            action, cache = self.action_model.step(state, cache)
            actions.append(action)
            if self.world_model is None:
                states.append(action)
                break
            state, wm_cache = self.world_model.step(state, action, wm_cache)
            states.append(state)
        return torch.stack(actions, 1), torch.stack(states, 1)

    def predict_waypoints(self, pooled: torch.Tensor) -> torch.Tensor:
        """(B, S, 2C) pooled predicted states → (B, rows, 4) raw waypoint rows."""
        summary = self.temporal_pool(pooled)
        return self.head(summary).reshape(pooled.shape[0], self.cfg.waypoint_rows, 4)

    def demo_task_logits(self, expert_outputs: torch.Tensor) -> torch.Tensor | None:
        """The demonstration-task head on π's outputs at the expert frames (U, N, …), averaged over frames (and
        cells); None without the head."""
        if self.demo_task_head is None:
            return None
        dims = (1, 3, 4) if expert_outputs.dim() == 5 else (1,)
        return self.demo_task_head(expert_outputs.mean(dim=dims))

    # ---------------------------------------------------------------- forward
    def forward(
        self,
        expert_frames: torch.Tensor,
        agent_frames: torch.Tensor,
        expert_ids: torch.Tensor | None = None,
        targets: TargetMode = "none",
    ) -> ModelOutput:
        """Plan from (U, N, 3, H, W) expert videos and (B, T, 3, H, W) agent clips (only frame 0 is an input).

        ``targets`` = "detached" encodes the future agent frames without gradient as world-model targets,
        "grad" with gradient (no-stop-gradient ablation), "none" skips them (planning, no 𝓛_wm).
        """
        u, n = expert_frames.shape[:2]
        b, t = agent_frames.shape[:2]
        if expert_frames.shape[-2:] != agent_frames.shape[-2:] or tuple(agent_frames.shape[-2:]) != tuple(
            self.cfg.image_size
        ):
            raise ValueError(
                f"frames must be {self.cfg.image_size}, got expert {tuple(expert_frames.shape[-2:])} and agent "
                f"{tuple(agent_frames.shape[-2:])}"
            )
        want_targets = targets != "none" and self.world_model is not None
        target_idx = self.target_frame_indices() if want_targets else []
        if target_idx and t <= max(target_idx):
            raise ValueError(f"world-model targets need {max(target_idx) + 1} agent frames, got {t}")
        inputs = [expert_frames.reshape(u * n, *expert_frames.shape[2:]), agent_frames[:, 0]]
        if targets == "grad" and target_idx:
            inputs.append(agent_frames[:, target_idx].reshape(b * len(target_idx), *agent_frames.shape[2:]))
        encoded = self.encode(torch.cat(inputs, 0))
        expert_states = encoded[: u * n].reshape(u, n, *self.state_shape)
        agent_state = encoded[u * n : u * n + b]
        target_pooled = None
        if target_idx:
            if targets == "grad":
                future = encoded[u * n + b :]
            else:
                with torch.no_grad():
                    future = self.encode(
                        agent_frames[:, target_idx].reshape(b * len(target_idx), *agent_frames.shape[2:])
                    )
            target_pooled = self.pool(future).reshape(b, len(target_idx), self.pooled_dim)
        cache, expert_outputs = self.action_model.context_and_outputs(expert_states)
        logits = self.demo_task_logits(expert_outputs)
        actions, states = self.rollout_from_context(_pair_context(cache, expert_ids, u, b), agent_state)
        pooled = self.pool(states)
        return ModelOutput(self.predict_waypoints(pooled), actions, states, pooled, target_pooled, logits)

    # ---------------------------------------------------------------- waypoints
    def decode_waypoints(self, raw: torch.Tensor, K: torch.Tensor) -> dict[str, torch.Tensor]:
        """Raw rows (B, R, 4) → camera-frame positions (B, R, 3) metres and gripper probabilities (B, R).

        ``K`` (B, 3, 3) are the intrinsics of the model-resolution input images (after augmentation).
        """
        depth = self.depth_offset + self.cfg.depth_scale * raw[..., 2]
        p_cam = image_to_camera(raw[..., :2].float(), depth.float(), K.float(), self.cfg.image_size)
        return {
            "position": p_cam,
            "gripper": torch.sigmoid(raw[..., 3].float()),
            "gripper_logit": raw[..., 3],
        }

    def set_depth_prior(self, depth_m: float) -> None:
        """Centre the depth parameterisation on a typical camera depth of the training paths (metres)."""
        self.depth_offset.fill_(float(depth_m))


def _pair_context(cache: KVCache, expert_ids: torch.Tensor | None, experts: int, pairs: int) -> KVCache:
    """The expert cache row of each pair (``expert_ids`` maps pairs to expert videos; None: one video each)."""
    if expert_ids is not None:
        return cache.index_select(expert_ids)
    if experts != pairs:
        raise ValueError(f"{experts} expert videos for {pairs} agent frames need expert_ids")
    return cache


def waypoint_set(rows: torch.Tensor, n: int) -> torch.Tensor:
    """The n-waypoint set (…, n, D) out of stacked rows (…, R, D)."""
    start = n * (n - 1) // 2
    return rows[..., start : start + n, :]


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
