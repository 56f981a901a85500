"""Train / validation / test splits: which tasks are trained on, which are held out, and validation episodes.

Splits are by task (the method imitates *unseen* tasks): ``studio/splits/<scene>.json`` lists the training
tasks and the held-out test tasks of a scene. Validation uses held-out *episodes of the training tasks*
(a fixed fraction per task and role), so model selection never looks at the test tasks. Which episodes
are held out is decided by a hash of the episode id: stable across runs and machines, independent of
insertion order.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

SPLITS = ("train", "val", "test")
#: Words :func:`resolve_tasks` expands: every task of the scene, its split's training tasks, its held-out tasks.
SPLIT_WORDS = ("all", "train", "test", "held-out")


@dataclass(frozen=True)
class SplitSpec:
    """A scene's task split. ``val_fraction`` of each training task's episodes form the validation set."""

    scene: str
    train: tuple[str, ...]
    test: tuple[str, ...]
    val_fraction: float = 0.1
    description: str = ""
    test_groups: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Named groups of test tasks reported together (Meta-World: ``easy`` and ``hard``, as in the paper's Table 1)."""
    replan_groups: tuple[str, ...] = ()
    """Test groups the paper's protocol re-plans on (Meta-World: ``hard``); the other test tasks get one attempt.
    ``studio results`` adds a row per policy evaluated that way."""
    replan_budget: int = 0
    """Re-plans the protocol allows a task of ``replan_groups`` (Meta-World: 3, the paper's 2,000 steps in plans of
    500): what the studio's Imitate tab offers for such a task."""
    plan_ticks: int | None = None
    """Control ticks each plan may execute under the protocol (Meta-World: the paper's 500 steps); None: no bound.
    The default of ``studio eval``, ``studio results``, ``studio compare`` and the studio's rollouts in this scene."""

    def __post_init__(self) -> None:
        overlap = set(self.train) & set(self.test)
        if overlap:
            raise ValueError(f"split {self.scene!r}: tasks both in train and test: {sorted(overlap)}")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(f"split {self.scene!r}: val_fraction must be in [0, 1), got {self.val_fraction}")
        if not self.train:
            raise ValueError(f"split {self.scene!r} has no training tasks")
        for group, tasks in self.test_groups.items():
            stray = set(tasks) - set(self.test)
            if stray:
                raise ValueError(
                    f"split {self.scene!r}: test group {group!r} names non-test tasks {sorted(stray)}"
                )
        unknown = set(self.replan_groups) - set(self.test_groups)
        if unknown:
            raise ValueError(
                f"split {self.scene!r}: replan_groups names groups it does not define: {sorted(unknown)}"
            )
        if self.replan_budget < 0:
            raise ValueError(f"split {self.scene!r}: replan_budget must be >= 0, got {self.replan_budget}")
        if self.plan_ticks is not None and self.plan_ticks < 1:
            raise ValueError(
                f"split {self.scene!r}: plan_ticks must be >= 1 or absent, got {self.plan_ticks}"
            )

    def replanned_tasks(self) -> tuple[str, ...]:
        """The test tasks of ``replan_groups``, in test order."""
        chosen = {t for g in self.replan_groups for t in self.test_groups[g]}
        return tuple(t for t in self.test if t in chosen)

    def protocol_replans(self, task: str) -> int | None:
        """Re-plans the split's protocol allows ``task``: ``replan_budget`` for a task of ``replan_groups``, 0 for
        the other test tasks, None where the protocol says nothing (no ``replan_groups``, or a training task)."""
        if not self.replan_groups or task not in self.test:
            return None
        return self.replan_budget if task in self.replanned_tasks() else 0

    def tasks(self, split: str) -> tuple[str, ...]:
        """The tasks a split draws from: training tasks for ``train`` and ``val``, held-out ones for ``test``."""
        if split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
        return self.test if split == "test" else self.train

    @classmethod
    def from_dict(cls, d: dict) -> SplitSpec:
        return cls(
            scene=d["scene"],
            train=tuple(d["train"]),
            test=tuple(d.get("test", ())),
            val_fraction=float(d.get("val_fraction", 0.1)),
            description=d.get("description", ""),
            test_groups={str(k): tuple(v) for k, v in d.get("test_groups", {}).items()},
            replan_groups=tuple(d.get("replan_groups", ())),
            replan_budget=int(d.get("replan_budget", 0)),
            plan_ticks=None if d.get("plan_ticks") is None else int(d["plan_ticks"]),
        )


def _splits_dir():
    return resources.files("studio") / "splits"


def available_splits() -> list[str]:
    """Scenes with a split file shipped in ``studio/splits``."""
    return sorted(p.name[: -len(".json")] for p in _splits_dir().iterdir() if p.name.endswith(".json"))


def load_split(scene_or_path: str | Path) -> SplitSpec:
    """The split of a scene (``"pick_place"``), or of a JSON file given by path."""
    p = Path(scene_or_path)
    if p.suffix == ".json":
        return SplitSpec.from_dict(json.loads(p.read_text()))
    name = str(scene_or_path)
    ref = _splits_dir() / f"{name}.json"
    if not ref.is_file():
        raise ValueError(f"no split file for scene {name!r}; available: {available_splits()}")
    return SplitSpec.from_dict(json.loads(ref.read_text()))


def _rank_key(episode_id: str) -> str:
    return hashlib.sha1(episode_id.encode()).hexdigest()


def validation_ids(episode_ids: Iterable[str], fraction: float) -> set[str]:
    """The ids held out for validation among one task's episodes of one role.

    ``round(fraction * n)`` episodes, at least one when ``fraction > 0`` and there are two or more, and
    never all of them; the ones with the smallest id hashes.
    """
    ids = sorted(set(episode_ids), key=_rank_key)
    n = len(ids)
    if fraction <= 0 or n < 2:
        return set()
    k = min(max(1, round(fraction * n)), n - 1)
    return set(ids[:k])


def scene_of_task(name: str) -> str:
    """The scene family a task name belongs to: names are ``<scene>/<what>`` (``pick_place/cube->red``)."""
    scene, sep, what = name.strip().partition("/")
    if not sep or not scene or not what:
        raise ValueError(f"task names are <scene>/<task>, e.g. 'pick_place/cube->red'; got {name!r}")
    return scene


def resolve_tasks(scene: str, names: str | Sequence[str]) -> list[str]:
    """The task names ``names`` stands for in ``scene``, in order, each once.

    ``names`` is one string or several, each comma-separated (``"a,b"`` and ``["a", "b"]`` are the same). Besides
    task names of the scene, ``all`` is every task of the scene, ``train`` its split's training tasks and ``test``
    (or ``held-out``) its held-out tasks (``studio/splits/<scene>.json``). ``studio collect`` and ``studio eval``
    both resolve their ``--tasks`` here. Raises ValueError for a scene without tasks, a name of another scene's
    task, an unknown name, or nothing at all.
    """
    from studio.sim.tasks import (
        list_tasks,  # the registry loads the scenes (MuJoCo): only when tasks are resolved
    )

    known = list_tasks(scene)
    if not known:
        scenes = sorted({scene_of_task(t) for t in list_tasks()})
        raise ValueError(f"scene {scene!r} has no tasks; scenes: {', '.join(scenes)}")
    parts = [names] if isinstance(names, str) else list(names)
    words = [n.strip() for part in parts for n in part.split(",") if n.strip()]
    if not words:
        raise ValueError(f"no tasks given for scene {scene!r}; name tasks or one of {', '.join(SPLIT_WORDS)}")
    out: list[str] = []
    for name in words:
        if name == "all":
            out.extend(known)
        elif name in ("train", "test", "held-out"):
            out.extend(load_split(scene).tasks("test" if name == "held-out" else name))
        elif name in known:
            out.append(name)
        elif "/" in name and scene_of_task(name) != scene and name in list_tasks(scene_of_task(name)):
            raise ValueError(
                f"task {name!r} belongs to scene {scene_of_task(name)!r}, not {scene!r}: one scene at a time"
            )
        else:
            raise ValueError(
                f"unknown task {name!r} for scene {scene!r}; known: {', '.join(known)} "
                f"(or {', '.join(SPLIT_WORDS)})"
            )
    return list(dict.fromkeys(out))
