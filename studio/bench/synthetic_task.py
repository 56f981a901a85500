"""A seeded synthetic follow-the-demonstration task: coloured squares moving to coloured targets.

Each scene shows four fixed coloured target markers on a grey table seen by a pinhole camera; a task is "move to
target t". An episode is a straight camera-frame path from a random start to the task's target (a small lift in
between, depth varying around 1 m), with the gripper closing half way. Expert episodes draw a blue square, agent
episodes a red one, so the agent's first frame does not tell the target: only the demonstration does. Samples
follow the "Training sample" contract of studio.data (uint8 frames (T, 3, H, W), path (P, 4) in the camera
frame, K at (H, W)) with configurable N, M, P and image size. Nothing is written to disk. Used by the model tests
and by `studio bench follow` (:mod:`studio.bench.follow`), which checks in seconds whether an architecture learns to read
demonstrations at all.

With ``shuffle_targets=True`` (the *match* variant) every episode places the four coloured markers in its own
random order over the four slots and task t means "go to the marker of colour t": the demonstration shows which
colour, the agent's first frame shows where that colour is now. This is the object-matching half of
pick-and-place (objects are shuffled there); copying the demonstration's end point is right one time in four.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from typing import Any

import numpy as np

TARGETS_CAM = np.array([[-0.25, 0.12, 1.05], [-0.08, 0.15, 1.0], [0.1, 0.12, 0.95], [0.27, 0.15, 1.0]])
TARGET_COLOURS = np.array([[40, 200, 40], [230, 230, 30], [200, 40, 200], [30, 200, 220]], dtype=np.uint8)


class SyntheticPairs:
    def __init__(
        self,
        n_tasks: int = 4,
        episodes_per_task: int = 3,
        image_size: tuple[int, int] = (48, 64),
        n_expert: int = 4,
        n_agent: int = 3,
        path_points: int = 20,
        seed: int = 0,
        split: str = "train",
        shuffle_targets: bool = False,
    ) -> None:
        self.h, self.w = image_size
        self.n_expert, self.n_agent, self.path_points = n_expert, n_agent, path_points
        self.seed = seed if split == "train" else seed + 1000
        self.n_tasks = n_tasks
        self.shuffle_targets = shuffle_targets
        self.tasks: Sequence[str] = [f"synthetic/target{t}" for t in range(n_tasks)]
        f = 0.9 * self.w
        self.K = np.array([[f, 0, self.w / 2], [0, f, self.h / 2], [0, 0, 1]], dtype=np.float32)
        self.T_world_cam = np.eye(4, dtype=np.float32)
        self.T_world_cam[:3, 3] = [0.0, 0.0, 1.5]
        self.pairs = [
            (t, e, a)
            for t in range(n_tasks)
            for e in range(episodes_per_task)
            for a in range(episodes_per_task)
        ]
        self.expert_indices = np.array([t * episodes_per_task + e for t, e, _ in self.pairs])
        self._key: tuple[object, ...] = (
            n_tasks,
            episodes_per_task,
            image_size,
            n_expert,
            n_agent,
            path_points,
            self.seed,
        )
        if shuffle_targets:
            self._key += ("shuffled",)

    def fingerprint(self) -> str:
        return "synthetic-" + hashlib.sha1(repr(self._key).encode()).hexdigest()[:12]

    def __len__(self) -> int:
        return len(self.pairs)

    def _layout(self, task: int, index: int, role: int) -> np.ndarray:
        """Slot of each colour's marker: the identity, or an episode's own shuffle with ``shuffle_targets``."""
        n = len(TARGETS_CAM)
        if not self.shuffle_targets:
            return np.arange(n)
        return np.random.default_rng([self.seed, task, index, role, 7]).permutation(n)

    def _episode(self, task: int, index: int, role: int) -> np.ndarray:
        rng = np.random.default_rng([self.seed, task, index, role])
        start = np.array([rng.uniform(-0.25, 0.25), rng.uniform(-0.2, -0.05), rng.uniform(0.9, 1.1)])
        target = TARGETS_CAM[self._layout(task, index, role)[task % len(TARGETS_CAM)]]
        s = np.linspace(0.0, 1.0, 200)[:, None]
        xyz = start + s * (target - start)
        xyz[:, 1] -= 0.05 * np.sin(np.pi * s[:, 0])
        grip = (s[:, 0] > 0.5).astype(float)[:, None]
        return np.concatenate([xyz, grip], axis=1)

    def _render(self, p_cam: np.ndarray, colour: tuple[int, int, int], layout: np.ndarray) -> np.ndarray:
        img = np.full((self.h, self.w, 3), 110, dtype=np.uint8)
        for slot, c in zip(layout, TARGET_COLOURS):
            self._square(img, TARGETS_CAM[slot], c, 2)
        self._square(img, p_cam, np.array(colour, dtype=np.uint8), 3)
        return img.transpose(2, 0, 1)

    def _square(self, img: np.ndarray, p: np.ndarray, colour: np.ndarray, r: int) -> None:
        u, v, w = self.K.astype(float) @ p
        u, v = int(u / w), int(v / w)
        img[max(v - r, 0) : max(v + r, 0), max(u - r, 0) : max(u + r, 0)] = colour

    def __getitem__(self, i: int) -> dict:
        task, e, a = self.pairs[i]
        expert = self._episode(task, e, 0)
        agent = self._episode(task, a, 1)
        ex_layout, ag_layout = self._layout(task, e, 0), self._layout(task, a, 1)
        ex_idx = np.linspace(0, len(expert) - 1, self.n_expert).round().astype(int)
        ag_idx = np.linspace(0, len(agent) - 1, self.n_agent).round().astype(int)
        path_idx = np.linspace(0, len(agent) - 1, self.path_points).round().astype(int)
        return {
            "expert_frames": np.stack(
                [self._render(expert[k, :3], (40, 40, 230), ex_layout) for k in ex_idx]
            ),
            "agent_frames": np.stack([self._render(agent[k, :3], (230, 40, 40), ag_layout) for k in ag_idx]),
            "path": agent[path_idx].astype(np.float32),
            "K": self.K.copy(),
            "T_world_cam": self.T_world_cam.copy(),
            "task_index": np.int64(task),
            "expert_index": np.int64(self.expert_indices[i]),
            "agent_index": np.int64(task * 1000 + a),
        }


def tiny_run_config(**train_overrides):
    """A RunConfig small enough for CPU tests on 48×64 synthetic pairs (N = 4, M = 3)."""
    from studio.model.config import ModelConfig, RunConfig, TrainConfig

    model = ModelConfig(
        image_size=(48, 64),
        n_expert_frames=4,
        n_agent_frames=3,
        encoder_stages=2,
        state_channels=16,
        action_blocks=1,
        action_heads=2,
        action_attn_dim=16,
        action_mlp_dim=32,
        wm_blocks=1,
        wm_heads=2,
        wm_width=32,
        wm_mlp_dim=64,
        head_hidden=64,
        head_dropout=0.0,
    )
    train: dict[str, Any] = dict(
        batch_size=8,
        max_steps=10,
        val_every=5,
        val_batches=2,
        checkpoint_every=5,
        log_every=1,
        num_workers=0,
        lr_max=1e-3,
        pairs_per_expert=2,
        sdtw_gamma=1e-2,
    )
    train.update(train_overrides)
    return RunConfig(model, TrainConfig(**train))
