"""The training view of the store: every (expert episode, agent episode) pair of a task as an OSVI-WM sample.

:class:`PairDataset` pairs each expert demonstration with each agent trajectory of the same task (the
combinatorial pairing of the paper) and yields the "training sample" dicts of the shared contract:

* ``expert_frames`` uint8 (N, 3, H, W): stratified random frames — frame i drawn uniformly from the i-th
  of N equal brackets, first and last frame always kept; redrawn per (seed, epoch, index);
* ``agent_frames`` uint8 (M, 3, H, W): evenly spaced, first and last included;
* ``path`` float32 (P, 4): the agent's end-effector position in the external camera frame (x right,
  y down, z forward, metres) and its gripper state, binary as in the paper (1 where the recorded command is
  above :data:`GRIPPER_CLOSED_ABOVE`, else 0; ``gripper_labels="recorded"`` keeps the command itself), at P evenly
  spaced control steps over the whole episode;
* ``K`` float32 (3, 3) intrinsics at the sample's (H, W); ``T_world_cam`` float32 (4, 4);
* ``task_index``, ``expert_index``, ``agent_index`` int64.

Splits: ``train`` and ``val`` draw from the split file's training tasks (``val`` = a fixed, hash-chosen
fraction of each task's expert and agent episodes, ``train`` = the rest), ``test`` from its held-out tasks.

Frames are decoded once per episode and training size into ``cache/frames/<H>x<W>/<episode id>.npy``
(uint8 (F, 3, H, W), opened memory-mapped), so training never decodes video. Episodes are immutable, so a
cache file stays valid as long as its episode exists; building a dataset decodes the episodes that have
no cache file yet and removes the files of deleted episodes. :meth:`PairDataset.fingerprint` changes
whenever the set of episodes (or the image size) does.

Which episodes make the pairs — successful (or unknown-outcome) episodes of the split's tasks, agents with their
recorded states, the validation hold-out — is decided in one place, :func:`select_task`, which both
:class:`PairDataset` and :func:`count_pairs` (the pair count the studio shows before anything trains, with the
reasons episodes are left out) call.
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
from studio.data.atomic_files import atomic_write
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


GRIPPER_CLOSED_ABOVE = 0.5
"""A recorded gripper command above this is a closed gripper in the training labels. Meta-World's experts that do
not grasp (button presses, pushes) record exactly 0.5 — effort 0 — which is open; labels of 0.5 would leave the
model to predict a probability at the controller's threshold, a coin flip between opening and closing."""

GRIPPER_LABELS = ("binary", "recorded")
"""How a path's gripper column is made: ``binary`` (the paper's: closed above :data:`GRIPPER_CLOSED_ABOVE`) or
``recorded`` (the recorded command itself, 0..1; Meta-World's effort-0 experts then give 0.5). The shipped
Meta-World policy was trained on ``recorded`` labels, before they were made binary (docs/experiments.md)."""

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


@dataclass(frozen=True)
class TaskSelection:
    """One task's episodes as the pairs of a split use them, and those left out with the reason.

    Attributes:
        task: the task name.
        experts, agents: the episodes paired (every expert with every agent) in the split asked for.
        val_experts, val_agents: how many usable episodes the validation hold-out took (``train``) or left to
            training (``val``); 0 for ``test``.
        failed_experts, failed_agents: episodes whose success predicate said they failed.
        stateless_agents: agent episodes stored without their recorded states (nothing to learn a path from).
    """

    task: str
    experts: tuple[EpisodeMeta, ...]
    agents: tuple[EpisodeMeta, ...]
    val_experts: int = 0
    val_agents: int = 0
    failed_experts: int = 0
    failed_agents: int = 0
    stateless_agents: int = 0

    @property
    def pairs(self) -> int:
        return len(self.experts) * len(self.agents)


def select_task(
    store: EpisodeStore, spec: SplitSpec, split: str, task: str, selection: _Selection
) -> TaskSelection:
    """The episodes of ``task`` that make ``split``'s pairs (see :class:`PairDataset`), with what is left out."""

    def side(roles: tuple[str, ...], embodiments: tuple[str, ...] | None) -> list[EpisodeMeta]:
        return store.catalog.episodes(
            task=task, role=list(roles), embodiment=embodiments, source=list(selection.sources)
        )

    all_experts = side(selection.expert_roles, selection.expert_embodiments)
    all_agents = side(selection.agent_roles, selection.agent_embodiments)
    experts = [m for m in all_experts if m.success is not False]
    ok_agents = [m for m in all_agents if m.success is not False]
    agents = [m for m in ok_agents if m.has_arrays]
    ok_experts, stateless = len(experts), len(ok_agents) - len(agents)
    val_e = val_a = 0
    if split in ("train", "val"):
        held_e = validation_ids([m.id for m in experts], spec.val_fraction)
        held_a = validation_ids([m.id for m in agents], spec.val_fraction)
        keep = split == "val"
        kept_e = [m for m in experts if (m.id in held_e) == keep]
        kept_a = [m for m in agents if (m.id in held_a) == keep]
        val_e, val_a = len(experts) - len(kept_e), len(agents) - len(kept_a)
        experts, agents = kept_e, kept_a
    return TaskSelection(
        task,
        tuple(experts),
        tuple(agents),
        val_experts=val_e,
        val_agents=val_a,
        failed_experts=len(all_experts) - ok_experts,
        failed_agents=len(all_agents) - len(ok_agents),
        stateless_agents=stateless,
    )


def _plural(n: int, word: str, many: str | None = None) -> str:
    return f"{n} {word if n == 1 else (many or word + 's')}"


def _short(task: str) -> str:
    return task.split("/", 1)[-1]


@dataclass(frozen=True)
class PairCount:
    """How many training pairs a store gives a split's tasks, and why episodes are left out (:func:`count_pairs`).

    Attributes:
        tasks: one :class:`TaskSelection` per training task, for the ``train`` split.
        held_out: episodes stored for each of the split's held-out tasks (never trained on).
    """

    tasks: tuple[TaskSelection, ...]
    held_out: dict[str, int]

    @property
    def pairs(self) -> int:
        """Training pairs: what ``len(PairDataset(..., "train"))`` is for the same store and selection."""
        return sum(t.pairs for t in self.tasks)

    @property
    def val_pairs(self) -> int:
        """Validation pairs: the held-back episodes of each task paired with each other."""
        return sum(t.val_experts * t.val_agents for t in self.tasks)

    @property
    def experts(self) -> int:
        return sum(len(t.experts) for t in self.tasks)

    @property
    def agents(self) -> int:
        return sum(len(t.agents) for t in self.tasks)

    def summary(self) -> str:
        """One line: the pairs, from how many episodes of which tasks."""
        used = [t for t in self.tasks if t.pairs]
        if not used:
            return "**0 training pairs**"
        names = ", ".join(_short(t.task) for t in used[:4]) + (
            f" and {len(used) - 4} more" if len(used) > 4 else ""
        )
        val = f" (+ {_plural(self.val_pairs, 'pair')} for validation)" if self.val_pairs else ""
        return (
            f"**{_plural(self.pairs, 'training pair')}**{val}: "
            f"{_plural(sum(len(t.experts) for t in used), 'demonstration')} × "
            f"{_plural(sum(len(t.agents) for t in used), 'agent episode')} of {names}"
        )

    def left_out(self) -> list[str]:
        """Why stored episodes are not in the training pairs, one short phrase per reason."""
        out = []
        failed = sum(t.failed_experts + t.failed_agents for t in self.tasks)
        if failed:
            out.append(f"{_plural(failed, 'failed episode')} (success unticked)")
        lonely_e = [t for t in self.tasks if t.experts and not t.agents]
        if lonely_e:
            n = sum(len(t.experts) for t in lonely_e)
            out.append(
                f"{_plural(n, 'demonstration')} of {', '.join(_short(t.task) for t in lonely_e)}: "
                "no agent episodes of the task to pair with"
            )
        lonely_a = [t for t in self.tasks if t.agents and not t.experts]
        if lonely_a:
            n = sum(len(t.agents) for t in lonely_a)
            out.append(
                f"{_plural(n, 'agent episode')} of {', '.join(_short(t.task) for t in lonely_a)}: "
                "no demonstrations of the task to pair with"
            )
        stateless = sum(t.stateless_agents for t in self.tasks)
        if stateless:
            out.append(f"{_plural(stateless, 'agent episode')} without recorded states")
        val = sum(t.val_experts + t.val_agents for t in self.tasks)
        if val:
            out.append(f"{_plural(val, 'episode')} held back for validation")
        held = sum(self.held_out.values())
        if held:
            names = ", ".join(_short(t) for t, n in self.held_out.items() if n)
            out.append(f"{_plural(held, 'episode')} of held-out tasks ({names}): never trained on")
        return out

    def what_to_record(self) -> str | None:
        """One sentence saying what to record when there is no training pair (None when there is one)."""
        if self.pairs:
            return None
        alone_e = next((t for t in self.tasks if t.experts or t.val_experts), None)
        alone_a = next((t for t in self.tasks if t.agents or t.val_agents), None)
        if alone_e is not None:
            return (
                f"No training pairs yet: record a successful agent (Panda) episode of {_short(alone_e.task)} in "
                "Teleop to pair with its demonstration, or collect scripted episodes in Data."
            )
        if alone_a is not None:
            return (
                f"No training pairs yet: record a successful demonstration (Sawyer or hand) of "
                f"{_short(alone_a.task)} in Teleop to pair with its agent episode, or collect scripted episodes "
                "in Data."
            )
        return (
            "No training pairs yet: record a successful demonstration (Sawyer or hand) and a successful agent "
            "(Panda) episode of the same training task in Teleop, or collect scripted episodes in Data."
        )


def count_pairs(
    root: str | os.PathLike | EpisodeStore | None = None,
    *,
    scene: str = "pick_place",
    split_spec: SplitSpec | str | os.PathLike | None = None,
    expert_roles: Sequence[str] = ("expert",),
    agent_roles: Sequence[str] | None = None,
    expert_embodiments: Sequence[str] | None = None,
    agent_embodiments: Sequence[str] | None = None,
    sources: Sequence[str] = DEFAULT_SOURCES,
) -> PairCount:
    """The training pairs :class:`PairDataset` would make of the store (same arguments), without decoding a frame,
    and the episodes it leaves out with the reason."""
    store = root if isinstance(root, EpisodeStore) else EpisodeStore(root)
    spec = _spec_of(scene, split_spec)
    selection = _selection_of(spec, expert_roles, agent_roles, expert_embodiments, agent_embodiments, sources)
    tasks = tuple(select_task(store, spec, "train", t, selection) for t in spec.tasks("train"))
    held = {t: len(store.catalog.episodes(task=t, source=list(sources))) for t in spec.test}
    return PairCount(tasks, held)


def _spec_of(scene: str, split_spec: SplitSpec | str | os.PathLike | None) -> SplitSpec:
    if isinstance(split_spec, SplitSpec):
        return split_spec
    if split_spec is None:
        return load_split(scene)
    return load_split(split_spec if isinstance(split_spec, str) else Path(split_spec))


def _selection_of(
    spec: SplitSpec,
    expert_roles: Sequence[str],
    agent_roles: Sequence[str] | None,
    expert_embodiments: Sequence[str] | None,
    agent_embodiments: Sequence[str] | None,
    sources: Sequence[str],
) -> _Selection:
    if agent_roles is None:
        agent_roles = ("expert",) if spec.scene in SAME_POOL_SCENES else ("agent",)
    return _Selection(
        expert_roles=tuple(expert_roles),
        agent_roles=tuple(agent_roles),
        expert_embodiments=None if expert_embodiments is None else tuple(expert_embodiments),
        agent_embodiments=None if agent_embodiments is None else tuple(agent_embodiments),
        sources=tuple(sources),
    )


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
        gripper_labels: str = "binary",
    ) -> None:
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        if n_expert < 2 or n_agent < 2 or path_points < 2:
            raise ValueError("n_expert, n_agent and path_points must be at least 2 (first and last are kept)")
        if gripper_labels not in GRIPPER_LABELS:
            raise ValueError(f"gripper_labels must be one of {GRIPPER_LABELS}, got {gripper_labels!r}")
        self.gripper_labels = gripper_labels
        self._store = root if isinstance(root, EpisodeStore) else EpisodeStore(root)
        self._episodes_dir = self._store.episodes_dir
        self.spec = _spec_of(scene, split_spec)
        self.split = split
        self.image_size = (int(image_size[0]), int(image_size[1]))
        self.n_expert, self.n_agent, self.path_points = n_expert, n_agent, path_points
        self.seed = seed
        self.epoch = 0
        self._selection = _selection_of(
            self.spec, expert_roles, agent_roles, expert_embodiments, agent_embodiments, sources
        )
        self._progress = progress
        self.cache_dir = self._store.cache_dir / "frames" / f"{self.image_size[0]}x{self.image_size[1]}"
        self._build()

    # ------------------------------------------------------------------ building
    def _build(self) -> None:
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
            chosen = select_task(self._store, self.spec, self.split, task, self._selection)
            e_idx = [idx(m) for m in chosen.experts]
            a_idx = [idx(m) for m in chosen.agents]
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
        atomic_write(path, lambda fh: np.save(fh, frames))

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
        command = arrays["gripper_cmd"][steps, None]
        closed = command > GRIPPER_CLOSED_ABOVE if self.gripper_labels == "binary" else command
        return np.concatenate([arrays["ee_pos_cam"][steps], closed], axis=1).astype(np.float32)

    def _load_camera(self, episode_index: int) -> tuple[np.ndarray, np.ndarray]:
        _, model = read_meta(self._episodes_dir / self.episodes[episode_index].id)
        model = model.resized(*self.image_size)
        return model.K.astype(np.float32), model.T_world_cam.astype(np.float32)

    def path(self, agent_index: int) -> np.ndarray:
        """(P, 4) float32: camera-frame end-effector xyz and gripper state (``gripper_labels``) at P evenly spaced
        steps."""
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
