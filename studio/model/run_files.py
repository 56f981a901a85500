"""Run-directory bookkeeping shared by the training loops: atomic files, JSONL metrics, seeds, cancellation.

* ``atomic_save`` / ``write_json``: written through :func:`studio.data.atomic_files.atomic_write`, so a kill never
  leaves a torn file.
* ``read_torch_file``: read back any file ``torch.save`` wrote (checkpoints, decoders, policies) weights-only.
* ``append_jsonl`` / ``trim_metrics``: one JSON object per line; on resume, records of steps the checkpoint does
  not contain (work of a killed run) and lines cut short by the kill are dropped.
* ``step_seed``: the seed of optimiser step τ on a rank, so a resumed run draws the same randomness.
* ``is_cancelled``: polls a cancellation flag — a callable returning bool or an object with ``is_set()``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

from studio.data.atomic_files import atomic_write


def atomic_save(obj: Any, path: Path) -> None:
    """``torch.save`` ``obj`` to ``path`` atomically."""
    atomic_write(path, lambda f: torch.save(obj, f))


def read_torch_file(path: str | Path, map_location: str | torch.device = "cpu") -> Any:
    """The contents of a file written by ``torch.save`` — checkpoints, decoders, policy files, pretrained encoders —
    read with ``weights_only=True``: tensors and plain containers only, so a file a user names cannot run code."""
    from torch.torch_version import TorchVersion

    with torch.serialization.safe_globals([TorchVersion]):
        return torch.load(path, map_location=map_location, weights_only=True)


def write_json(path: Path, obj: Any) -> None:
    atomic_write(path, json.dumps(obj, indent=2, sort_keys=True))


def append_jsonl(path: Path, record: dict[str, Any]) -> None:
    with open(path, "a") as f:
        f.write(json.dumps(record, sort_keys=True) + "\n")


def trim_metrics(path: Path, step: int) -> None:
    """Keep only the records of steps ≤ ``step``; ``step == 0`` starts a fresh file."""
    if not path.exists():
        return
    if step == 0:
        path.unlink()
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if rec.get("step", 0) <= step:
            kept.append(line)
    atomic_write(path, "".join(k + "\n" for k in kept))


def step_seed(seed: int, step: int, rank: int = 0) -> int:
    return int(np.random.SeedSequence([seed, step, rank]).generate_state(1, dtype=np.uint64)[0] % (2**63))


def is_cancelled(cancel: Any) -> bool:
    if cancel is None:
        return False
    if hasattr(cancel, "is_set"):
        return bool(cancel.is_set())
    return bool(cancel())
