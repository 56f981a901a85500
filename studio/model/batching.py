"""What the training loop needs from a dataset, and how pairs become batches.

``PairSource`` is the small protocol the loop is written against: a map-style dataset of training-sample dicts
(the "Training sample" contract: ``expert_frames`` uint8 (N, 3, H, W), ``agent_frames`` uint8 (M, 3, H, W),
``path`` float32 (P, 4) camera-frame xyz + gripper, ``K`` (3, 3) at (H, W), ``T_world_cam`` (4, 4),
``task_index``, ``expert_index``, ``agent_index``), a ``tasks`` list and a ``fingerprint()``. A source may also
expose ``expert_indices`` (one expert episode index per pair, without loading any image; ``studio.data``'s
``PairDataset`` exposes it as column 0 of its ``pairs`` table) to let batches group pairs that share a
demonstration, and ``set_epoch(epoch)`` to redraw its random frame choices each epoch.

``BatchPlan`` turns that into deterministic batches of indices per epoch (seeded by (seed, epoch)), groups of
``pairs_per_expert`` pairs sharing an expert kept contiguous, so a data-parallel rank's contiguous slice keeps its
groups whole and a resumed run can skip to any step without loading the skipped samples. ``collate_pairs`` stacks
samples into a ``Batch``, storing each expert video once (``expert_ids`` maps pairs to them) and resizing frames
(and scaling K) when the source's image size differs from the model's.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch
from torch.nn import functional as F

from studio.model.geometry import resize_intrinsics


@runtime_checkable
class PairSource(Protocol):
    tasks: Sequence[str]

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> dict[str, Any]: ...

    def fingerprint(self) -> str: ...


@dataclass
class Batch:
    """A collated batch of B pairs over U ≤ B distinct expert videos."""

    expert_frames: torch.Tensor  # (U, N, 3, H, W) uint8
    agent_frames: torch.Tensor  # (B, M, 3, H, W) uint8
    path: torch.Tensor  # (B, P, 4) float32
    K: torch.Tensor  # (B, 3, 3) float32, at the frames' size
    T_world_cam: torch.Tensor  # (B, 4, 4) float32
    expert_ids: torch.Tensor  # (B,) int64 → row of expert_frames
    expert_tasks: torch.Tensor  # (U,) int64
    agent_tasks: torch.Tensor  # (B,) int64

    def to(self, device: torch.device | str) -> Batch:
        return Batch(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})

    @property
    def size(self) -> int:
        return int(self.agent_frames.shape[0])

    def all_frames(self) -> torch.Tensor:
        """Every expert frame, then every agent frame: (U·N + B·M, 3, H, W) uint8."""
        return torch.cat([self.expert_frames.flatten(0, 1), self.agent_frames.flatten(0, 1)], 0)


_REQUIRED = ("expert_frames", "agent_frames", "path", "K", "T_world_cam", "task_index", "expert_index")


def collate_pairs(
    samples: list[dict[str, Any]],
    image_size: tuple[int, int] | None = None,
    n_expert: int | None = None,
    n_agent: int | None = None,
) -> Batch:
    """Stack training-sample dicts; one expert video per distinct ``expert_index``."""
    for s in samples:
        missing = [k for k in _REQUIRED if k not in s]
        if missing:
            raise KeyError(f"training sample lacks {', '.join(missing)} (has {', '.join(sorted(s))})")
    first_of: dict[int, int] = {}
    expert_ids = []
    unique: list[dict[str, Any]] = []  # the first sample of each expert, in order of first appearance
    for s in samples:
        key = int(s["expert_index"])
        if key not in first_of:
            first_of[key] = len(first_of)
            unique.append(s)
        expert_ids.append(first_of[key])
    expert = torch.from_numpy(np.stack([np.asarray(s["expert_frames"]) for s in unique]))
    agent = torch.from_numpy(np.stack([np.asarray(s["agent_frames"]) for s in samples]))
    if (
        expert.dtype != torch.uint8
        or agent.dtype != torch.uint8
        or expert.shape[2] != 3
        or agent.shape[2] != 3
    ):
        raise ValueError(
            f"frames must be uint8 (T, 3, H, W); got expert {tuple(expert.shape[1:])} {expert.dtype}, "
            f"agent {tuple(agent.shape[1:])} {agent.dtype}"
        )
    if n_expert is not None and expert.shape[1] != n_expert:
        raise ValueError(
            f"the model expects {n_expert} expert frames per sample, the dataset gives {expert.shape[1]}"
        )
    if n_agent is not None and agent.shape[1] != n_agent:
        raise ValueError(
            f"the model expects {n_agent} agent frames per sample, the dataset gives {agent.shape[1]}"
        )
    K = torch.from_numpy(np.stack([np.asarray(s["K"], dtype=np.float32) for s in samples]))
    size = (int(agent.shape[-2]), int(agent.shape[-1]))
    if image_size is not None and size != tuple(image_size):
        expert = _resize(expert, image_size)
        agent = _resize(agent, image_size)
        K = resize_intrinsics(K, size, image_size)
    tasks = torch.tensor([int(s["task_index"]) for s in samples], dtype=torch.long)
    return Batch(
        expert_frames=expert,
        agent_frames=agent,
        path=torch.from_numpy(np.stack([np.asarray(s["path"], dtype=np.float32) for s in samples])),
        K=K,
        T_world_cam=torch.from_numpy(
            np.stack([np.asarray(s["T_world_cam"], dtype=np.float32) for s in samples])
        ),
        expert_ids=torch.tensor(expert_ids, dtype=torch.long),
        expert_tasks=torch.tensor([int(s["task_index"]) for s in unique], dtype=torch.long),
        agent_tasks=tasks,
    )


def validation_batches(
    source: PairSource,
    batch_size: int,
    max_batches: int,
    image_size: tuple[int, int],
    n_expert: int,
    n_agent: int,
) -> Iterator[Batch]:
    """Up to ``max_batches`` (0: all) batches of consecutive samples, spread evenly over ``source``: the
    validation batches of the decoder and encoder trainers."""
    bs = min(batch_size, len(source))
    n = len(source) // bs
    if max_batches > 0:
        n = min(n, max_batches)
    for s in np.linspace(0, len(source) - bs, n).round().astype(int):
        yield collate_pairs([source[int(i)] for i in range(s, s + bs)], image_size, n_expert, n_agent)


def _resize(frames: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    b, t = frames.shape[:2]
    flat = frames.reshape(b * t, *frames.shape[2:]).float()
    out = F.interpolate(flat, size=tuple(size), mode="bilinear", antialias=True, align_corners=False)
    return out.round().clamp(0, 255).to(torch.uint8).reshape(b, t, 3, *size)


def expert_indices_of(source: PairSource) -> np.ndarray | None:
    """The expert episode index of every pair, when the source can tell without loading samples."""
    explicit = getattr(source, "expert_indices", None)
    if explicit is not None:
        return np.asarray(explicit)
    pairs = getattr(source, "pairs", None)
    if isinstance(pairs, np.ndarray) and pairs.ndim == 2 and pairs.shape == (len(source), 2):
        return pairs[:, 0]
    return None


class BatchPlan:
    """Deterministic batches of dataset indices for each epoch, grouped by expert when possible."""

    def __init__(
        self,
        n: int,
        batch_size: int,
        seed: int,
        expert_indices: Sequence[int] | np.ndarray | None = None,
        pairs_per_expert: int = 1,
    ) -> None:
        if n < batch_size:
            raise ValueError(f"the dataset has {n} pairs, fewer than one batch of {batch_size}")
        self.n = n
        self.batch_size = batch_size
        self.seed = seed
        self.pairs_per_expert = pairs_per_expert
        self.expert_indices = None if expert_indices is None else np.asarray(expert_indices)
        if self.expert_indices is not None and len(self.expert_indices) != n:
            raise ValueError(f"expert_indices has {len(self.expert_indices)} entries for {n} pairs")

    @property
    def batches_per_epoch(self) -> int:
        return self.n // self.batch_size

    def epoch(self, epoch: int) -> list[list[int]]:
        rng = np.random.default_rng([self.seed, epoch])
        if self.expert_indices is None or self.pairs_per_expert <= 1:
            order = rng.permutation(self.n)
        else:
            by_expert = np.argsort(self.expert_indices, kind="stable")
            starts = np.flatnonzero(np.diff(self.expert_indices[by_expert], prepend=np.nan))
            groups = []
            k = self.pairs_per_expert
            for members in np.split(by_expert, starts[1:]):
                members = rng.permutation(members)
                groups += [members[i : i + k] for i in range(0, len(members), k)]
            order = np.concatenate([groups[i] for i in rng.permutation(len(groups))])
        bs = self.batch_size
        return [order[i * bs : (i + 1) * bs].tolist() for i in range(self.batches_per_epoch)]
