"""Writing a file so that a crash leaves either the old file or the whole new one, never a torn one.

:func:`atomic_write` writes to a uniquely named temporary file in the destination's directory (a rename is atomic
only within one file system), flushes and fsyncs it, renames it over the destination and fsyncs the directory so
the rename itself survives a power cut. Concurrent writers of the same path each use their own temporary file:
the last rename wins with a complete file. On any error the temporary file is removed and the destination is left
as it was. :func:`fsync_path` flushes one file or directory entry to disk, for writers that build a directory
before renaming it (the episode store).

Every layer above the simulator writes its files through here: the episode store and its caches, training runs,
plans, calibrations and the job queue's journal.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

#: What :func:`atomic_write` writes: the bytes, a text (UTF-8), or a function writing to the open binary file.
Content = bytes | str | Callable[[BinaryIO], object]


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: The file-creation mask, read once at import: ``mkstemp`` creates files 0600, and the files written here get the
#: permissions ``open`` would give them.
_UMASK = _read_umask()


def fsync_path(path: str | os.PathLike[str], directory: bool = False) -> None:
    """Flush the file or directory at ``path`` to disk. Raises OSError."""
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike[str], content: Content) -> None:
    """Replace ``path`` by ``content`` atomically and durably (its directory must exist). Raises what writing raises
    (OSError, or the writer function's own errors), with ``path`` unchanged and no temporary file left behind."""
    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    tmp = Path(tmp_name)
    try:
        with os.fdopen(fd, "wb") as f:
            if isinstance(content, bytes):
                f.write(content)
            elif isinstance(content, str):
                f.write(content.encode("utf-8"))
            else:
                content(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_path(path.parent, directory=True)
