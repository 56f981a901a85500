"""The training view of the store: every (expert episode, agent episode) pair of a task as an OSVI-WM sample.

:class:`PairDataset` pairs each expert demonstration with each agent trajectory of the same task (the
combinatorial pairing of the paper) and yields the "training sample" dicts of the shared contract:

* ``expert_frames`` uint8 (N, 3, H, W): stratified random frames — frame i drawn uniformly from the i-th
  of N equal brackets, first and last frame always kept; redrawn per (seed, epoch, index);
* ``agent_frames`` uint8 (M, 3, H, W): evenly spaced, first and last included;
* ``path`` float32 (P, 4): the agent's end-effector position in the external camera frame (x right,
  y down, z forward, metres) and its gripper command (0 open, 1 closed), at P evenly spaced control steps
  over the whole episode;
* ``K`` float32 (3, 3) intrinsics at the sample's (H, W); ``T_world_cam`` float32 (4, 4);
* ``task_index``, ``expert_index``, ``agent_index`` int64.

Splits: ``train`` and ``val`` draw from the split file's training tasks (``val`` = a fixed, hash-chosen
fraction of each task's expert and agent episodes, ``train`` = the rest), ``test`` from its held-out tasks.

Frames are decoded once per episode and training size into ``cache/frames/<H>x<W>/<episode id>.npy``
(uint8 (F, 3, H, W), opened memory-mapped), so training never decodes video. Episodes are immutable, so a
cache file stays valid as long as its episode exists; building a dataset decodes the episodes that have
no cache file yet and removes the files of deleted episodes. :meth:`PairDataset.fingerprint` changes
whenever the set of episodes (or the image size) does.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from studio.data import video
from studio.data.episode import FRAMES_FILE, EpisodeMeta, read_arrays, read_meta
from studio.data.splits import SPLITS, SplitSpec, load_split, validation_ids
from studio.data.store import EpisodeStore

DEFAULT_SOURCES = ("scripted", "teleop", "upload", "import")


def stratified_indices(length: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """N frame indices, one uniformly from each of N equal brackets of [0, length); first and last kept."""
    edges = np.floor(np.arange(n + 1) * length / n).astype(np.int64)
    lo = edges[:-1]
    hi = np.maximum(edges[1:], lo + 1)
    idx = rng.integers(lo, hi)
    idx[0], idx[-1] = 0, length - 1
    return np.minimum(idx, length - 1)


def even_indices(length: int, n: int) -> np.ndarray:
    """N evenly spaced indices over [0, length), first and last included."""
    return np.round(np.linspace(0, length - 1, n)).astype(np.int64)


def resize_frames(frames: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(F, H, W, 3) -> (F, 3, h, w) uint8, area-averaged when shrinking."""
    h, w = size
    if frames.shape[1:3] == (h, w):
        out = frames
    else:
        shrink = h < frames.shape[1] or w < frames.shape[2]
        interp = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
        out = np.stack([cv2.resize(f, (w, h), interpolation=interp) for f in frames])
    return np.ascontiguousarray(out.transpose(0, 3, 1, 2))


SAME_POOL_SCENES = frozenset({"metaworld"})
"""Scenes whose training pairs take both sides from the stored ``expert`` demonstrations (the paper's Meta-World)."""


@dataclass(frozen=True)
class _Selection:
    """Which episodes of a task make up the two sides of a pair."""

    expert_roles: tuple[str, ...]
    agent_roles: tuple[str, ...]
    expert_embodiments: tuple[str, ...] | None
    agent_embodiments: tuple[str, ...] | None
    sources: tuple[str, ...]


class PairDataset:
    """(expert, agent) pairs of one split, as OSVI-WM training samples (a map-style dataset).

    Args:
        root: dataset root or an open :class:`EpisodeStore` (None: the default root).
        split: ``"train"``, ``"val"`` or ``"test"``.
        image_size: (H, W) of the returned frames.
        n_expert, n_agent, path_points: N, M and P of the sample.
        seed: seed of the expert-frame sampling (see :meth:`set_epoch`).
        scene: scene whose split file is used, unless ``split_spec`` is given.
        split_spec: a :class:`SplitSpec`, a path to a split JSON, or None for ``studio/splits/<scene>.json``.
        expert_roles, agent_roles: catalog roles of the two sides. ``agent_roles=None`` takes the scene's own:
            ``("agent",)`` on the tabletop (Sawyer experts, Panda agents), ``("expert",)`` for Meta-World, where
            expert and agent come from one pool of Sawyer demonstrations as in the paper (``SAME_POOL_SCENES``).
        expert_embodiments, agent_embodiments: restrict the sides to these embodiments (None: any).
        sources: episode sources used (rollouts are excluded by default).
        progress: show a progress bar while decoding frames into the cache.
    """

    def __init__(
        self,
        root: str | os.PathLike | EpisodeStore | None = None,
        split: str = "train",
        image_size: tuple[int, int] = (240, 320),
        n_expert: int = 10,
        n_agent: int = 6,
        path_points: int = 50,
        seed: int = 0,
        scene: str = "pick_place",
        split_spec: SplitSpec | str | os.PathLike | None = None,
        expert_roles: Sequence[str] = ("expert",),
        agent_roles: Sequence[str] | None = None,
        expert_embodiments: Sequence[str] | None = None,
        agent_embodiments: Sequence[str] | None = None,
        sources: Sequence[str] = DEFAULT_SOURCES,
        progress: bool = False,
    ) -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if n_expert < 2 or n_agent < 2 or path_points < 2:
            raise ValueError("n_expert, n_agent and path_points must be at least 2 (first and last are kept)")
        self._store = root if isinstance(root, EpisodeStore) else EpisodeStore(root)
        self._episodes_dir = self._store.episodes_dir
        if isinstance(split_spec, SplitSpec):
            self.spec = split_spec
        elif split_spec is None:
            self.spec = load_split(scene)
        else:
            self.spec = load_split(split_spec if isinstance(split_spec, str) else Path(split_spec))
        if agent_roles is None:
            agent_roles = ("expert",) if self.spec.scene in SAME_POOL_SCENES else ("agent",)
        self.split = split
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.n_expert, self.n_agent, self.path_points = n_expert, n_agent, path_points
        self.seed = seed
        self.epoch = 0
        self._selection = _Selection(
            expert_roles=tuple(expert_roles),
            agent_roles=tuple(agent_roles),
            expert_embodiments=None if expert_embodiments is None else tuple(expert_embodiments),
            agent_embodiments=None if agent_embodiments is None else tuple(agent_embodiments),
            sources=tuple(sources),
        )
        self._progress = progress
        self.cache_dir = self._store.cache_dir / "frames" / f"{self.image_size[0]}x{self.image_size[1]}"
        self._build()

    # ------------------------------------------------------------------ building
    def _side(self, task: str, roles, embodiments, need_arrays: bool) -> list[EpisodeMeta]:
        metas = self._store.catalog.episodes(
            task=task, role=list(roles), embodiment=embodiments, source=list(self._selection.sources)
        )
        metas = [m for m in metas if m.success is not False]
        if need_arrays:
            metas = [m for m in metas if m.has_arrays]
        return metas

    def _build(self) -> None:
        sel = self._selection
        self.tasks: list[str] = list(self.spec.tasks(self.split))
        episodes: dict[str, EpisodeMeta] = {}
        pairs, pair_tasks = [], []
        index_of: dict[str, int] = {}

        def idx(m: EpisodeMeta) -> int:
            if m.id not in index_of:
                index_of[m.id] = len(episodes)
                episodes[m.id] = m
            return index_of[m.id]

        for t, task in enumerate(self.tasks):
            experts = self._side(task, sel.expert_roles, sel.expert_embodiments, need_arrays=False)
            agents = self._side(task, sel.agent_roles, sel.agent_embodiments, need_arrays=True)
            if self.split in ("train", "val"):
                held_e = validation_ids([m.id for m in experts], self.spec.val_fraction)
                held_a = validation_ids([m.id for m in agents], self.spec.val_fraction)
                keep = self.split == "val"
                experts = [m for m in experts if (m.id in held_e) == keep]
                agents = [m for m in agents if (m.id in held_a) == keep]
            e_idx = [idx(m) for m in experts]
            a_idx = [idx(m) for m in agents]
            for e in e_idx:
                for a in a_idx:
                    pairs.append((e, a))
                    pair_tasks.append(t)
        self.episodes: list[EpisodeMeta] = list(episodes.values())
        self.pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        self.pair_tasks = np.asarray(pair_tasks, dtype=np.int64)
        self._frames: dict[int, np.ndarray] = {}
        agent_indices = sorted(set(self.pairs[:, 1].tolist()))
        self._paths = {a: self._load_path(a) for a in agent_indices}
        self._cameras = {i: self._load_camera(i) for i in range(len(self.episodes))}
        self._build_cache()

    def _cache_file(self, meta: EpisodeMeta) -> Path:
        return self.cache_dir / f"{meta.id}.npy"

    def _cache_valid(self, meta: EpisodeMeta) -> bool:
        path = self._cache_file(meta)
        if not path.is_file():
            return False
        try:
            arr = np.load(path, mmap_mode="r")
        except (ValueError, OSError):
            return False
        return arr.shape == (meta.num_frames, 3, *self.image_size) and arr.dtype == np.uint8

    def _write_cache(self, meta: EpisodeMeta) -> None:
        decoded = video.read_video(self._episodes_dir / meta.id / FRAMES_FILE, size=(meta.height, meta.width))
        frames = resize_frames(decoded.frames, self.image_size)
        path = self._cache_file(meta)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.save(fh, frames)
        os.replace(tmp, path)

    def _build_cache(self) -> None:
        from tqdm import tqdm

        self.cache_dir.mkdir(parents=True, exist_ok=True)
        live = self._store.catalog.episode_ids()
        for stale in self.cache_dir.glob("*.npy"):
            if stale.stem not in live:
                stale.unlink(missing_ok=True)
        todo = [m for m in self.episodes if not self._cache_valid(m)]
        for meta in tqdm(
            todo, desc=f"decode frames {self.image_size}", unit="ep", disable=not self._progress
        ):
            self._write_cache(meta)

    def refresh(self) -> bool:
        """Re-read the catalog; True (and the view rebuilt) if the set of episodes changed.

        Call it in the main process (a copy sent to a DataLoader worker has no catalog connection).
        """
        if self._store is None:
            raise RuntimeError("refresh() needs the catalog: call it on the main process's dataset")
        before = self.fingerprint()
        self._build()
        return self.fingerprint() != before

    # ------------------------------------------------------------------ identity
    def fingerprint(self) -> str:
        """Hash of what the samples are made of: the split's episodes and pairs, the image size and N/M/P."""
        doc = {
            "split": self.split,
            "tasks": self.tasks,
            "image_size": self.image_size,
            "n": [self.n_expert, self.n_agent, self.path_points],
            "episodes": [m.id for m in self.episodes],
            "pairs": hashlib.sha256(self.pairs.tobytes()).hexdigest(),
        }
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]

    # ------------------------------------------------------------------ components
    def frames(self, episode_index: int) -> np.ndarray:
        """All cached frames of an episode, (F, 3, H, W) uint8, memory-mapped."""
        arr = self._frames.get(episode_index)
        if arr is None:
            meta = self.episodes[episode_index]
            if not self._cache_valid(meta):
                self._write_cache(meta)
            arr = np.load(self._cache_file(meta), mmap_mode="r")
            self._frames[episode_index] = arr
        return arr

    def expert_frames(self, expert_index: int, rng: np.random.Generator) -> np.ndarray:
        """N stratified random frames of an expert episode, (N, 3, H, W) uint8."""
        f = self.frames(expert_index)
        return np.asarray(f[stratified_indices(len(f), self.n_expert, rng)])

    def agent_frames(self, agent_index: int) -> np.ndarray:
        """M evenly spaced frames of an agent episode, (M, 3, H, W) uint8."""
        f = self.frames(agent_index)
        return np.asarray(f[even_indices(len(f), self.n_agent)])

    def _load_path(self, agent_index: int) -> np.ndarray:
        meta = self.episodes[agent_index]
        _, _, arrays = read_arrays(self._episodes_dir / meta.id)
        steps = even_indices(meta.num_steps, self.path_points)
        p = np.concatenate([arrays["ee_pos_cam"][steps], arrays["gripper_cmd"][steps, None]], axis=1)
        return p.astype(np.float32)

    def _load_camera(self, episode_index: int) -> tuple[np.ndarray, np.ndarray]:
        _, model = read_meta(self._episodes_dir / self.episodes[episode_index].id)
        model = model.resized(*self.image_size)
        return model.K.astype(np.float32), model.T_world_cam.astype(np.float32)

    def path(self, agent_index: int) -> np.ndarray:
        """(P, 4) float32: camera-frame end-effector xyz and gripper command at P evenly spaced steps."""
        return self._paths[agent_index]

    def camera(self, episode_index: int) -> tuple[np.ndarray, np.ndarray]:
        """(K at the dataset's image size, T_world_cam) of an episode, float32."""
        return self._cameras[episode_index]

    def agent_sample(self, agent_index: int) -> dict[str, np.ndarray]:
        """The agent side of a sample: agent_frames, path, K, T_world_cam."""
        K, T = self.camera(agent_index)
        return {
            "agent_frames": self.agent_frames(agent_index),
            "path": self.path(agent_index),
            "K": K,
            "T_world_cam": T,
        }

    def agents_of_expert(self, expert_index: int) -> np.ndarray:
        """Indices (into :attr:`pairs`) of the pairs sharing one expert episode."""
        return np.flatnonzero(self.pairs[:, 0] == expert_index)

    def task_index(self, episode_index: int) -> int:
        return self.tasks.index(self.episodes[episode_index].task)

    # ------------------------------------------------------------------ map-style dataset
    def set_epoch(self, epoch: int) -> None:
        """Expert frames are redrawn per epoch; sample i of epoch e is the same in every process."""
        self.epoch = int(epoch)

    def sample_rng(self, index: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, self.epoch, int(index)])

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> dict[str, np.ndarray]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"pair {index} out of range for {len(self)} pairs")
        index = int(index) % len(self)
        e, a = (int(v) for v in self.pairs[index])
        sample = {"expert_frames": self.expert_frames(e, self.sample_rng(index)), **self.agent_sample(a)}
        sample["task_index"] = np.int64(self.pair_tasks[index])
        sample["expert_index"] = np.int64(e)
        sample["agent_index"] = np.int64(a)
        return sample

    def __getstate__(self) -> dict:
        # Workers re-open memory maps in their own process and never touch the catalog.
        state = dict(self.__dict__)
        state["_frames"] = {}
        state["_store"] = None
        return state

    def __repr__(self) -> str:
        return (
            f"PairDataset(split={self.split!r}, tasks={len(self.tasks)}, episodes={len(self.episodes)}, "
            f"pairs={len(self)}, image_size={self.image_size})"
        )
