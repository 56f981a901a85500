"""Recording drafts: the ticks of a teleop recording journaled as it happens, so a worker's death loses nothing.

While a session records, it sends its new ticks (physics states and recorded arrays) every fraction of a
second; the studio appends them here, under ``<data-dir>/drafts/<draft-id>/``:

* ``header.json`` — scene, robot, task, seed, control period, role, where the recording started from
  (``prefix``: the rollout and the number of its ticks a fork continues; none for a fresh recording) and
  ``forked_from`` for the saved episode;
* ``chunk-<first step>-<n>.npz`` — ``states`` (n, S) float64 and one array per recorded field, n ticks each.

When the episode is stored the draft is deleted. When the worker died first, :meth:`RecordingDrafts.load`
gives every tick received — the rollout prefix included — and a new session continues from the last one.
Chunks must arrive in order; a chunk after a gap is refused (the draft then ends where the gap starts).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from studio.data.atomic_files import atomic_write
from studio.data.forks import fork_source

DRAFTS_DIR = "drafts"
HEADER = "header.json"
_CHUNK = re.compile(r"^chunk-(\d{8})-(\d{6})\.npz$")
_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")


class DraftError(ValueError):
    """A draft that does not exist, or a chunk that does not fit it."""


@dataclass(frozen=True)
class Draft:
    """Every tick of a draft: the prefix it continues (if any) and the ticks journaled after it."""

    id: str
    header: dict
    states: np.ndarray  # (T, S) float64
    arrays: dict[str, np.ndarray]  # each (T, ...)

    @property
    def num_steps(self) -> int:
        return len(self.states)

    @property
    def gripper(self) -> float:
        return float(np.clip(self.arrays["gripper_cmd"][-1], 0.0, 1.0))


@dataclass(frozen=True)
class DraftInfo:
    """What a listing shows of a draft without loading its arrays."""

    id: str
    header: dict
    steps: int  # ticks journaled after the prefix
    updated: float


class RecordingDrafts:
    """The drafts of one data directory."""

    def __init__(self, data_dir: str | os.PathLike):
        self.root = Path(data_dir) / DRAFTS_DIR

    def _dir(self, draft_id: str) -> Path:
        if not _ID.match(draft_id):
            raise DraftError(f"not a draft id: {draft_id!r}")
        return self.root / draft_id

    # ------------------------------------------------------------------ writing
    def create(self, draft_id: str, header: dict) -> None:
        """Start draft ``draft_id``; ``header`` needs scene, robot, task, seed, control_dt and role."""
        missing = [k for k in ("scene", "robot", "task", "seed", "control_dt", "role") if k not in header]
        if missing:
            raise DraftError(f"a draft header needs {missing}")
        d = self._dir(draft_id)
        if (d / HEADER).is_file():
            raise DraftError(f"draft {draft_id} exists already")
        d.mkdir(parents=True, exist_ok=True)
        body = json.dumps({"prefix": None, "forked_from": None, **header, "created": time.time()}, indent=1)
        atomic_write(d / HEADER, body)

    def header(self, draft_id: str) -> dict:
        try:
            return json.loads((self._dir(draft_id) / HEADER).read_text())
        except FileNotFoundError:
            raise DraftError(f"no draft {draft_id}") from None
        except json.JSONDecodeError as e:
            raise DraftError(f"draft {draft_id} has an unreadable header: {e}") from None

    def _chunks(self, draft_id: str) -> list[tuple[int, int, Path]]:
        """(first tick, ticks, path) of every chunk, in order."""
        d = self._dir(draft_id)
        found = []
        for p in d.iterdir() if d.is_dir() else ():
            m = _CHUNK.match(p.name)
            if m:
                found.append((int(m.group(1)), int(m.group(2)), p))
        return sorted(found)

    def prefix_steps(self, draft_id: str) -> int:
        prefix = self.header(draft_id).get("prefix") or {}
        return int(prefix.get("steps", 0))

    def next_step(self, draft_id: str) -> int:
        """The tick the next chunk must start at."""
        chunks = self._chunks(draft_id)
        if not chunks:
            return self.prefix_steps(draft_id)
        first, n, _ = chunks[-1]
        return first + n

    def append(
        self, draft_id: str, first_step: int, states: np.ndarray, arrays: dict[str, np.ndarray]
    ) -> int:
        """Journal ticks ``first_step`` … of ``draft_id`` (fsynced); returns how many new ticks were kept.

        A chunk that repeats ticks already kept keeps only its new ones; one that starts after the next
        expected tick is refused (:class:`DraftError`), since the ticks in between are missing.
        """
        states = np.asarray(states, dtype=np.float64)
        if states.ndim != 2 or any(len(a) != len(states) for a in arrays.values()):
            raise DraftError("a draft chunk needs (n, S) states and n ticks of every array")
        expected = self.next_step(draft_id)
        if first_step > expected:
            raise DraftError(
                f"draft {draft_id}: a chunk starts at tick {first_step}, the draft ends at tick {expected}; "
                "the ticks in between never arrived"
            )
        skip = expected - first_step
        if skip >= len(states):
            return 0
        payload = {"states": states[skip:], **{f"a_{k}": np.asarray(v)[skip:] for k, v in arrays.items()}}
        path = self._dir(draft_id) / f"chunk-{expected:08d}-{len(states) - skip:06d}.npz"
        atomic_write(path, lambda f: np.savez(f, allow_pickle=False, **payload))
        return len(states) - skip

    def discard(self, draft_id: str) -> None:
        """Delete a draft (its episode was stored, or the user dropped it)."""
        shutil.rmtree(self._dir(draft_id), ignore_errors=True)

    # ------------------------------------------------------------------ reading
    def drafts(self) -> list[DraftInfo]:
        """Every draft, newest first."""
        out: list[DraftInfo] = []
        if not self.root.is_dir():
            return out
        for d in self.root.iterdir():
            if not d.is_dir() or not (d / HEADER).is_file():
                continue
            try:
                header = self.header(d.name)
                chunks = self._chunks(d.name)
                updated = max(
                    [p.stat().st_mtime for _, _, p in chunks], default=float(header.get("created", 0.0))
                )
            except (DraftError, FileNotFoundError):
                continue  # dropped (or just saved and cleaned up) while it was being listed
            steps = sum(n for _, n, _ in chunks)
            out.append(DraftInfo(d.name, header, steps, updated))
        return sorted(out, key=lambda i: -i.updated)

    def load(self, draft_id: str, store=None) -> Draft:
        """Every tick of the draft, its prefix included (read from ``store``'s rollout when it has one)."""
        header = self.header(draft_id)
        parts_s: list[np.ndarray] = []
        parts_a: list[dict[str, np.ndarray]] = []
        prefix = header.get("prefix")
        if prefix:
            if store is None:
                raise DraftError(
                    f"draft {draft_id} continues rollout {prefix.get('rollout')}: needs the store"
                )
            src = fork_source(store, str(prefix["rollout"]), int(prefix["steps"]) - 1)
            parts_s.append(src.states)
            parts_a.append(src.arrays)
        for _, _, path in self._chunks(draft_id):
            with np.load(path, allow_pickle=False) as data:
                parts_s.append(np.asarray(data["states"], dtype=np.float64))
                parts_a.append({k[2:]: np.asarray(data[k]) for k in data.files if k.startswith("a_")})
        if not parts_s:
            raise DraftError(f"draft {draft_id} holds no ticks yet")
        keys = set(parts_a[0])
        if any(set(a) != keys for a in parts_a):
            raise DraftError(f"draft {draft_id}: its chunks record different fields")
        arrays = {
            k: np.concatenate([np.asarray(a[k], dtype=np.float64) for a in parts_a]) for k in sorted(keys)
        }
        return Draft(draft_id, header, np.concatenate(parts_s), arrays)
