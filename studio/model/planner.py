"""The planning API: expert video + the agent's current frame → 5 attributed waypoints in the world frame.

``Planner.load(checkpoint).plan(expert_frames, agent_frame, K, T_world_cam)`` accepts uint8 frames in either
layout ((N, H, W, 3) or (N, 3, H, W); the agent frame (H, W, 3) or (3, H, W)) at any resolution: frames are
resized to the model's input size and the intrinsics scaled with them (K must belong to the agent frame's size).
A video with a different number of frames than the model's N is resampled to N evenly spaced frames (first and
last kept). The result holds the 5-waypoint set in camera and world coordinates — xyz in metres plus the gripper
probability (closed when > 0.5) — and the predicted latent trajectory (maps and pooled keypoints) for
visualisation with the latent decoder.

Re-planning with the same demonstration reuses the expert context (its encodings and the action model's cache):
only the new agent frame is encoded. Runs in eval mode under ``torch.inference_mode`` on a private copy of the
model whose encoder has its BatchNorms folded into the convolutions; ``precision="bf16"`` (opt-in) runs the
encoder — most of the planning time — under bfloat16 autocast, 2–3× faster on CPUs with AMX/AVX-512-BF16 at
~1 % relative error in the encodings; the small sequence models stay in float32.

A model whose configuration asks for demonstration guidance (``ModelConfig.guidance`` ≠ 1; ``guidance``) is
also planned from the null demonstration, whose context is computed once, and its rows combined with the
demonstration's; the latent trajectory returned is the demonstration's own, and the null plan comes back beside
the guided one (what the scene alone suggests: how far the demonstration moved the plan is read from the two).
With a world model, the demonstration's gain (``guidance.demonstration_gain``) is computed once per demonstration
and returned; a gated policy (``ModelConfig.guidance_gate``) guides only demonstrations whose gain reaches the gate.

A policy file with a guided branch (``studio export-policy --guided-from``; ``guidance``) holds a second set of
weights for π, 𝒲 and the waypoint head, on the same encoder: the branch computes the gain, and plans (guided) the
demonstrations that reach the gate; the policy's own weights plan the others, unguided. The frames are encoded once.
A policy with a surprise gate (``ModelConfig.surprise_gate``) also guides, with its own weights, the demonstrations
below the gate whose surprise (``guidance.demonstration_surprise``, read by its own weights) reaches that gate, at
its own scale (``ModelConfig.surprise_guidance``) when it has one.
"""

from __future__ import annotations

import copy
import hashlib
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from studio.model.checkpoint import (
    check_guided_branch,
    guided_model_from_checkpoint,
    load_checkpoint,
    model_from_checkpoint,
)
from studio.model.geometry import camera_to_world, resize_intrinsics
from studio.model.guidance import demonstration_gain, demonstration_surprise, guide, null_demonstration
from studio.model.osvi_wm import OSVIWM, waypoint_set
from studio.model.transformer import KVCache


@dataclass
class PlanResult:
    """One plan.

    Attributes:
        waypoints_world: (5, 4) x, y, z (world frame, metres) + gripper probability.
        waypoints_cam: (5, 4) the same in the camera frame (x right, y down, z forward).
        latent_states: (S, *state_shape) predicted latent states r_2..r_M.
        pooled_states: (S, 2C) their spatial-softmax keypoints (the latent decoder's input).
        timing: milliseconds of each stage (preprocess, encode, rollout, head, total).
        reused_expert_context: whether the expert context came from the previous call.
        null_waypoints_world: (5, 4) with demonstration guidance, the plan from the null demonstration alone
            (what the scene suggests; world frame, like ``waypoints_world``); None without guidance.
        guidance_gain: with guidance and a world model, the demonstration's gain (``guidance``); else None.
        guidance_surprise: with a surprise gate, the demonstration's surprise as the policy's own weights read it
            (``guidance.demonstration_surprise``); else None.
        guided: whether the returned plan is the guided one (False without guidance, or below both gates).
        guidance_scale: the guidance that made the returned plan (``ModelConfig.guidance``, or
            ``surprise_scale`` for a plan the surprise gate guided); None when it is not guided.
    """

    waypoints_world: np.ndarray
    waypoints_cam: np.ndarray
    latent_states: np.ndarray
    pooled_states: np.ndarray
    timing: dict[str, float] = field(default_factory=dict)
    reused_expert_context: bool = False
    null_waypoints_world: np.ndarray | None = None
    guidance_gain: float | None = None
    guidance_surprise: float | None = None
    guided: bool = False
    guidance_scale: float | None = None

    @property
    def gripper_closed(self) -> np.ndarray:
        return self.waypoints_world[:, 3] > 0.5


def _chw(frames: np.ndarray | torch.Tensor, what: str, video: bool) -> torch.Tensor:
    x = torch.as_tensor(np.asarray(frames))
    want = 4 if video else 3
    if x.ndim != want:
        raise ValueError(
            f"{what} must have {want} dimensions ({'N, ' if video else ''}H, W, 3 or 3, H, W), got {tuple(x.shape)}"
        )
    if x.dtype != torch.uint8:
        raise ValueError(f"{what} must be uint8 images, got {x.dtype}")
    if x.shape[-1] == 3 and x.shape[-3] != 3:
        x = x.movedim(-1, -3)
    if x.shape[-3] != 3:
        raise ValueError(f"{what} must have 3 colour channels, got shape {tuple(x.shape)}")
    return x if video else x.unsqueeze(0)


def _hw(size: Sequence[int]) -> tuple[int, int]:
    """(height, width) as ints (a config read from JSON holds a list)."""
    h, w = size
    return int(h), int(w)


def _resize(frames: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    if tuple(frames.shape[-2:]) == tuple(size):
        return frames
    out = F.interpolate(
        frames.float(), size=tuple(size), mode="bilinear", antialias=True, align_corners=False
    )
    return out.round().clamp(0, 255).to(torch.uint8)


class Planner:
    """A trained OSVI-WM model ready to plan."""

    def __init__(
        self,
        model: OSVIWM,
        device: str | torch.device = "cpu",
        precision: str = "fp32",
        guided_model: OSVIWM | None = None,
    ) -> None:
        """``guided_model``: the guided branch (module docstring): a network of ``model``'s architecture and
        encoder weights, whose π, 𝒲 and head plan the demonstrations the gate guides; needs guidance and a gate."""
        if precision not in ("fp32", "bf16"):
            raise ValueError(f"precision must be 'fp32' or 'bf16', got {precision!r}")
        self.device = torch.device(device)
        self.precision = precision
        self.model = copy.deepcopy(model).to(self.device).eval()
        self.guided_model: OSVIWM | None = None
        if guided_model is not None:
            check_guided_branch(model, guided_model)
            self.guided_model = copy.deepcopy(guided_model).to(self.device).eval()
        self.model.encoder = self.model.encoder.fused_for_inference()
        if self.guided_model is not None:
            self.guided_model.encoder = self.model.encoder  # the same weights (checked): encode once
        self.cfg = model.cfg
        self.tasks: list[str] = []  # the training tasks (from the checkpoint), which the task head names
        self._class_names: list[list[str]] | None = None
        self._context_key: str | None = None
        self._context: KVCache | None = None
        self._guided_context: KVCache | None = None
        # π's caches of the null demonstration, by branch: False the policy's own weights, True the guided branch
        self._null_contexts: dict[bool, KVCache] = {}
        self._gain: float | None = None
        self._surprise: float | None = None

    @classmethod
    def load(
        cls, checkpoint: str | Path, device: str | torch.device = "cpu", precision: str = "fp32"
    ) -> Planner:
        ckpt = load_checkpoint(checkpoint, "cpu")
        planner = cls(model_from_checkpoint(ckpt), device, precision, guided_model_from_checkpoint(ckpt))
        planner.tasks = list(ckpt.get("tasks") or [])
        return planner

    def clear_cache(self) -> None:
        self._context_key, self._context, self._guided_context, self._gain = None, None, None, None
        self._surprise = None

    @torch.inference_mode()
    def name_demonstration(self, expert_frames: np.ndarray | torch.Tensor) -> tuple[str, ...] | None:
        """What the demonstration-task head (``demo_task``; not in the paper) calls this demonstration: a training
        task's name, or one name per part (object, target). None when the model has no such head."""
        from studio.model.demo_task import class_names

        model = self.model
        if model.demo_task_head is None or not self.tasks:
            return None
        if self._class_names is None:
            self._class_names = class_names(self.tasks, self.cfg.demo_task_table)
        names = self._class_names
        expert = self._expert_input(expert_frames)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            encoded = model.encode(expert).float()
        _, outputs = model.action_model.context_and_outputs(encoded.unsqueeze(0))
        all_logits = model.demo_task_logits(outputs)
        assert all_logits is not None  # the model has the head (checked above)
        logits = all_logits[0]
        groups = list(self.cfg.demo_task_groups or (self.cfg.demo_task_classes,))
        return tuple(names[g][int(part.argmax())] for g, part in enumerate(logits.split(groups)))

    def _expert_input(self, expert_frames: np.ndarray | torch.Tensor) -> torch.Tensor:
        """The demonstration as the model takes it: N evenly spaced frames at the model's size, on the device."""
        expert = _chw(expert_frames, "expert_frames", video=True)
        n = self.cfg.n_expert_frames
        if expert.shape[0] < 1:
            raise ValueError("expert_frames is empty")
        if expert.shape[0] != n:
            expert = expert[np.round(np.linspace(0, expert.shape[0] - 1, n)).astype(int)]
        return _resize(expert, _hw(self.cfg.image_size)).to(self.device)

    def _branch(self, guided: bool) -> OSVIWM:
        """The network that plans: the guided branch for a guided plan when the policy has one, else its own."""
        return self.guided_model if guided and self.guided_model is not None else self.model

    def _null_context_for(self, expert: torch.Tensor, guided: bool = False) -> KVCache:
        """π's cache of the null demonstration in the branch ``_branch(guided)`` (made on the first call; it is the
        same for every demonstration)."""
        branch = self.guided_model is not None and guided
        if branch not in self._null_contexts:
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
                encoded = self.model.encode(null_demonstration(expert)).float()
            self._null_contexts[branch] = self._branch(branch).action_model.context(encoded.unsqueeze(0))
        return self._null_contexts[branch]

    @torch.inference_mode()
    def demonstration_gain(self, expert_frames: np.ndarray | torch.Tensor) -> float:
        """The demonstration's gain (``guidance.demonstration_gain``), as a plan with it would compute it (by the
        guided branch when there is one); used to set a policy's gate from the training demonstrations
        (``studio export-policy --gate-percentile``)."""
        judge = self._branch(True)
        expert, encoded = self._encode_demonstration(expert_frames)
        context = judge.action_model.context(encoded.unsqueeze(0))
        return demonstration_gain(judge, encoded, context, self._null_context_for(expert, True))

    @torch.inference_mode()
    def demonstration_surprise(self, expert_frames: np.ndarray | torch.Tensor) -> float:
        """The demonstration's surprise (``guidance.demonstration_surprise``) as the policy's own weights read it,
        which is how a plan compares it with the surprise gate; used to set that gate from the training
        demonstrations (``studio export-policy --surprise-percentile``)."""
        _, encoded = self._encode_demonstration(expert_frames)
        context = self.model.action_model.context(encoded.unsqueeze(0))
        return demonstration_surprise(self.model, encoded, context)

    def _encode_demonstration(
        self, expert_frames: np.ndarray | torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The demonstration as the model takes it, and its encoded frames (float32)."""
        expert = self._expert_input(expert_frames)
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            return expert, self.model.encode(expert).float()

    def _plan_without_demonstration(
        self, expert: torch.Tensor, agent_state: torch.Tensor, guided: bool
    ) -> torch.Tensor:
        """Raw rows planned from the null demonstration by the branch ``_branch(guided)``."""
        net = self._branch(guided)
        _, states = net.rollout_from_context(self._null_context_for(expert, guided), agent_state)
        return net.predict_waypoints(net.pool(states))

    @torch.inference_mode()
    def plan(
        self,
        expert_frames: np.ndarray | torch.Tensor,
        agent_frame: np.ndarray | torch.Tensor,
        K: np.ndarray,
        T_world_cam: np.ndarray,
    ) -> PlanResult:
        """Plan the 5 waypoints (see the module docstring)."""
        t0 = time.perf_counter()
        expert = self._expert_input(expert_frames)
        agent = _chw(agent_frame, "agent_frame", video=False)
        K = np.asarray(K, dtype=np.float64)
        T = np.asarray(T_world_cam, dtype=np.float64)
        if K.shape != (3, 3) or T.shape != (4, 4):
            raise ValueError(f"K must be (3, 3) and T_world_cam (4, 4), got {K.shape} and {T.shape}")
        n = self.cfg.n_expert_frames
        size = _hw(self.cfg.image_size)
        K_model = resize_intrinsics(torch.as_tensor(K), _hw(agent.shape[-2:]), size)
        agent = _resize(agent, size).to(self.device)
        key = hashlib.sha1(expert.cpu().numpy().tobytes()).hexdigest()
        t1 = time.perf_counter()

        model = self.model
        cached = self._context if key == self._context_key else None
        reused = cached is not None
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "bf16"):
            if cached is not None:
                agent_state = model.encode(agent).float()
            else:
                encoded = model.encode(torch.cat([expert, agent], 0)).float()
                agent_state = encoded[n:]
        if cached is None:
            expert_states = encoded[:n].unsqueeze(0)
            self._context_key, self._gain, self._surprise = key, None, None
            self._context = model.action_model.context(expert_states)
            self._guided_context = None
            if self.guided_model is not None:
                self._guided_context = self.guided_model.action_model.context(expert_states)
            judge = self._branch(True)
            if self.cfg.guidance != 1.0 and judge.world_model is not None:
                judged = self._context if self._guided_context is None else self._guided_context
                null = self._null_context_for(expert, True)
                self._gain = demonstration_gain(judge, encoded[:n], judged, null)
            if self.cfg.guidance != 1.0 and self.cfg.surprise_gate > 0.0:
                self._surprise = demonstration_surprise(model, encoded[:n], self._context)
        # the gate (read by the branch, when there is one) guides with the branch; the surprise gate with the
        # policy's own weights, the demonstrations the gate leaves
        guided = self.cfg.guidance != 1.0 and (self._gain is None or self._gain >= self.cfg.guidance_gate)
        surprised = not guided and self._surprise is not None and self._surprise >= self.cfg.surprise_gate
        net = self._branch(guided)
        context = self._guided_context if net is not self.model else self._context
        assert context is not None  # made above for this demonstration
        t2 = time.perf_counter()
        _, states = net.rollout_from_context(context, agent_state)
        pooled = net.pool(states)
        t3 = time.perf_counter()
        raw = net.predict_waypoints(pooled)
        K_dev, T_dev = K_model[None].to(self.device), torch.as_tensor(T, device=self.device)[None]
        null_world, scale = None, None
        if self.cfg.guidance != 1.0:
            null_raw = self._plan_without_demonstration(expert, agent_state, guided)
            null_world = torch.cat(self._waypoints(null_raw, K_dev, T_dev)[1:], 1).cpu().numpy()
            if guided or surprised:
                scale = self.cfg.guidance if guided else self.cfg.surprise_scale
                raw = guide(raw, null_raw, scale)
        p_cam, p_world, grip = self._waypoints(raw, K_dev, T_dev)
        t4 = time.perf_counter()
        ms = {
            "preprocess": 1e3 * (t1 - t0),
            "encode": 1e3 * (t2 - t1),
            "rollout": 1e3 * (t3 - t2),
            "head": 1e3 * (t4 - t3),
            "total": 1e3 * (t4 - t0),
        }
        return PlanResult(
            waypoints_world=torch.cat([p_world, grip], 1).cpu().numpy(),
            waypoints_cam=torch.cat([p_cam, grip], 1).cpu().numpy(),
            latent_states=states[0].float().cpu().numpy(),
            pooled_states=pooled[0].float().cpu().numpy(),
            timing=ms,
            reused_expert_context=reused,
            null_waypoints_world=null_world,
            guidance_gain=self._gain,  # computed only with guidance
            guidance_surprise=self._surprise,  # computed only with a surprise gate
            guided=guided or surprised,
            guidance_scale=scale,
        )

    def _waypoints(
        self, raw: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Raw rows (1, R, 4) → the waypoint set's camera and world positions (5, 3) and gripper (5, 1)."""
        decoded = self.model.decode_waypoints(waypoint_set(raw, self.cfg.max_waypoints), K)
        p_cam = decoded["position"][0].double()
        p_world = camera_to_world(p_cam[None], T_world_cam)[0]
        return p_cam, p_world, decoded["gripper"][0].double()[:, None]
