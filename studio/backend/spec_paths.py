"""Where the files a job spec names may be: inside the worker's data directory, or a policy shipped with the studio.

A job spec arrives over the bus, so every path in it is treated as untrusted input. A relative path is taken
relative to the worker's ``--data-dir``; an absolute one must resolve (symbolic links followed) inside it. A
checkpoint may also be a policy shipped in ``studio/policies/`` (or the file the worker's own environment names in
``STUDIO_DEFAULT_POLICY``), and ``"oracle"`` stands for the scripted planner. Anything else is refused with one
line saying which path, where it resolved to, and where it may be.
"""

from __future__ import annotations

import os
from pathlib import Path

from studio.data.paths import SHIPPED_POLICY_DIR

#: The checkpoint name of the scripted planner, which names no file.
ORACLE = "oracle"
#: Policies shipped with the studio.
SHIPPED_POLICIES = SHIPPED_POLICY_DIR


class SpecPathError(ValueError):
    """A path in a job spec that lies outside where the worker may read or write."""


def _within(path: Path, root: Path) -> bool:
    return path == root or root in path.parents


def inside_data_dir(data_dir: Path | None, value: str, what: str, kind: str) -> Path:
    """``value`` resolved inside ``data_dir`` (relative paths are relative to it); raises :class:`SpecPathError`."""
    if data_dir is None:
        raise SpecPathError(
            f"{kind} jobs need a worker started with --data-dir: the {what} a job names must lie in it"
        )
    root = Path(data_dir).resolve()
    if "\x00" in value:
        raise SpecPathError(f"the {what} {value!r} is not a path")
    path = (root / value).resolve()
    if not _within(path, root):
        raise SpecPathError(f"the {what} {value} resolves to {path}, outside the worker's data dir {root}")
    return path


def checkpoint_path(data_dir: Path | None, value: str, what: str, kind: str) -> str:
    """A spec's checkpoint as a path the worker may load: ``"oracle"``, a file inside ``data_dir``, or a shipped
    policy. Raises :class:`SpecPathError` for anything else (the file need not exist yet: loading says so)."""
    if value == ORACLE:
        return value
    if "\x00" in value:
        raise SpecPathError(f"the {what} {value!r} is not a path")
    if data_dir is not None:
        root = Path(data_dir).resolve()
        path = (root / value).resolve()
        if _within(path, root):
            return str(path)
    else:
        path = Path(value).resolve()
    shipped = [SHIPPED_POLICIES]
    named = os.environ.get("STUDIO_DEFAULT_POLICY")
    if named:
        shipped_file = Path(named).resolve()
        if path == shipped_file:
            return str(path)
    if any(_within(path, root) for root in shipped):
        return str(path)
    where = f"the worker's data dir {Path(data_dir).resolve()}" if data_dir is not None else "no data dir"
    raise SpecPathError(
        f"the {what} {value} of a {kind} job resolves to {path}, which is neither in {where} nor a shipped "
        f"policy ({SHIPPED_POLICIES})"
    )
