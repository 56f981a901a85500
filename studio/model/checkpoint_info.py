"""What a checkpoint or policy file says about itself (its tasks, hence its scene), read without torch.

The studio's viewers never import torch (:mod:`studio.eval.latents`), yet the browser studio must know which
scene each checkpoint was trained on, so that a push task is never planned by a pick-and-place model. A file
written by ``torch.save`` is a zip archive whose ``data.pkl`` holds the checkpoint's dictionary, with each tensor
replaced by a reference to a separate storage entry. :func:`read_checkpoint_info` unpickles that dictionary
alone: tensors come back as :data:`TENSOR` placeholders, their bytes are never read, and no module is imported
on the file's behalf (every class outside a short allowlist becomes a placeholder too). The scene comes from
the checkpoint's ``tasks`` (written by ``studio train`` from the dataset it trained on, kept by ``studio
export-policy``), so it cannot drift from what the model learnt.
"""

from __future__ import annotations

import collections
import io
import os
import pickle
import threading
import zipfile
from collections.abc import Iterable
from typing import Any


class _Opaque:
    """Stands for anything the metadata does not need: tensors, storages, classes outside the allowlist."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        pass

    def __repr__(self) -> str:
        return "<tensor or object>"


#: What every tensor and unknown object of a checkpoint reads as.
TENSOR = _Opaque

_ALLOWED: dict[tuple[str, str], Any] = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("torch.torch_version", "TorchVersion"): str,  # a str subclass
    ("builtins", "set"): set,
    ("builtins", "frozenset"): frozenset,
    ("builtins", "complex"): complex,
    ("builtins", "slice"): slice,
}


class _MetadataUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        return _ALLOWED.get((module, name), _Opaque)

    def persistent_load(self, pid: Any) -> Any:
        return _Opaque()


_CACHE: dict[tuple[str, int, int], dict[str, Any]] = {}
_LOCK = threading.Lock()


def read_checkpoint_info(path: str | os.PathLike) -> dict[str, Any]:
    """The top-level entries of a checkpoint or policy file, tensors as :data:`TENSOR` placeholders.

    Re-read only when the file changed (size or modification time). Raises ``ValueError`` when the file is not
    a zip-format torch file, ``FileNotFoundError`` when it is missing.
    """
    st = os.stat(path)
    key = (str(path), st.st_size, st.st_mtime_ns)
    with _LOCK:
        hit = _CACHE.get(key)
    if hit is not None:
        return hit
    try:
        with zipfile.ZipFile(path) as zf:
            names = [n for n in zf.namelist() if n.count("/") == 1 and n.endswith("/data.pkl")]
            if len(names) != 1:
                raise ValueError(f"{path} is not a torch checkpoint (no data.pkl)")
            data = zf.read(names[0])
        info = _MetadataUnpickler(io.BytesIO(data), encoding="utf-8").load()
    except (zipfile.BadZipFile, pickle.UnpicklingError, EOFError) as exc:
        raise ValueError(f"{path} is not a torch checkpoint: {exc}") from exc
    if not isinstance(info, dict):
        raise ValueError(f"{path} does not hold a checkpoint dictionary")
    with _LOCK:
        if len(_CACHE) > 256:
            _CACHE.clear()
        _CACHE[key] = info
    return info


def scene_of_tasks(tasks: Iterable[str]) -> str | None:
    """The one scene all ``tasks`` (``<scene>/<task>`` names) belong to; None when there are none or several."""
    scenes = {str(t).partition("/")[0] for t in tasks if "/" in str(t)}
    return scenes.pop() if len(scenes) == 1 else None


def checkpoint_scene(path: str | os.PathLike) -> str | None:
    """The scene the checkpoint at ``path`` was trained on (from its ``tasks``); None when that cannot be told:
    the file is missing or no checkpoint, names no tasks, or tasks of several scenes."""
    try:
        tasks = read_checkpoint_info(path).get("tasks")
    except (OSError, ValueError):
        return None
    if not isinstance(tasks, (list, tuple)):
        return None
    return scene_of_tasks(tasks)


def checkpoint_demonstrators(path: str | os.PathLike) -> tuple[str, ...]:
    """The embodiments whose demonstrations the checkpoint at ``path`` learnt to imitate: its configuration's
    ``train.expert_embodiments``. Empty when it names none (it trained on every expert demonstration of its data,
    which the file does not list) or the file cannot be read."""
    try:
        config = read_checkpoint_info(path).get("config")
    except (OSError, ValueError):
        return ()
    train = config.get("train") if isinstance(config, dict) else None
    named = train.get("expert_embodiments") if isinstance(train, dict) else None
    if not isinstance(named, (list, tuple)):
        return ()
    return tuple(str(e) for e in named)
