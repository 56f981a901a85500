"""The episode store: adding, finding, loading and deleting episodes without ever exposing a half-written one.

Adding an episode follows one protocol (safe against a process killed at any instruction):

1. take an exclusive ``flock`` on ``tmp/<id>.lock`` (the kernel drops it when the process dies);
2. write the files into ``tmp/<id>/``, ``fsync`` each file and the directory;
3. ``rename`` the directory to ``episodes/<id>/`` (atomic) and ``fsync`` both parents;
4. insert the catalog row in one transaction (plus, for rollouts, the rollout row);
5. remove the lock file.

An episode is visible only through its catalog row, so a crash before step 4 leaves nothing any
reader can see. :meth:`EpisodeStore.check` (run by every data command at start-up) reports and removes
what crashes leave behind: temporary directories whose writer is gone, episode directories without a
row (their lock is free, so no writer is between steps 3 and 4), rows whose directory is missing or
incomplete, and stale lock files. Deleting removes the row first, then the files, so the same check
finishes an interrupted delete.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import secrets
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from studio.data import video
from studio.data.atomic_files import fsync_path
from studio.data.catalog import Catalog, RolloutRecord
from studio.data.episode import (
    EPISODE_FILES,
    FRAMES_FILE,
    Episode,
    EpisodeMeta,
    read_arrays,
    read_episode,
    read_meta,
    write_episode_files,
)
from studio.data.paths import CACHE_DIR, CATALOG_NAME, EPISODES_DIR, TMP_DIR, resolve_data_dir
from studio.sim.recording import Recording


class StoreError(RuntimeError):
    """An episode could not be added, found or deleted."""


def _lock(path: Path, blocking: bool, create: bool = True) -> int | None:
    """An exclusive flock on ``path``; None if ``blocking`` is False and it is held, or if ``create`` is
    False and there is no such file.

    Re-checks after locking that ``path`` still names the locked file, since a cleaner may unlink a lock
    file between our open and our flock.
    """
    while True:
        try:
            fd = os.open(path, os.O_RDWR | (os.O_CREAT if create else 0), 0o644)
        except FileNotFoundError:
            return None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except OSError as e:
            os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                return None
            raise
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


def _unlock(path: Path, fd: int) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    os.close(fd)


@dataclass
class CheckReport:
    """What :meth:`EpisodeStore.check` found (and removed, unless it ran with ``clean=False``)."""

    temp_dirs: list[str] = field(default_factory=list)
    orphan_dirs: list[str] = field(default_factory=list)
    missing_dirs: list[str] = field(default_factory=list)
    incomplete_dirs: list[str] = field(default_factory=list)
    stale_locks: list[str] = field(default_factory=list)
    cleaned: bool = True

    @property
    def ok(self) -> bool:
        return not (self.temp_dirs or self.orphan_dirs or self.missing_dirs or self.incomplete_dirs)

    def summary(self) -> str:
        if self.ok and not self.stale_locks:
            return "store check: consistent"
        verb = "removed" if self.cleaned else "found"
        parts = [
            f"{len(self.temp_dirs)} unfinished temporary writes",
            f"{len(self.orphan_dirs)} episode directories without a catalog row",
            f"{len(self.missing_dirs)} catalog rows without an episode directory",
            f"{len(self.incomplete_dirs)} catalog rows with incomplete files",
            f"{len(self.stale_locks)} stale lock files",
        ]
        return f"store check: {verb} " + ", ".join(parts)


class EpisodeStore:
    """All episodes under one dataset root.

    Args:
        root: dataset root; None resolves ``STUDIO_DATA_DIR`` or the user data directory.
        crf: H.264 quality of stored videos (lower is better; 18 is visually lossless for renders).
        stage_hook: called with ``"files_written"``, ``"renamed"`` and ``"committed"`` while an episode is
            being added (crash tests stop a writer at each stage; a UI may show progress).
    """

    def __init__(
        self,
        root: str | os.PathLike | None = None,
        crf: int = 18,
        stage_hook: Callable[[str], None] | None = None,
    ) -> None:
        self.root = resolve_data_dir(root)
        self.episodes_dir = self.root / EPISODES_DIR
        self.tmp_dir = self.root / TMP_DIR
        self.cache_dir = self.root / CACHE_DIR
        for d in (self.episodes_dir, self.tmp_dir, self.cache_dir):
            d.mkdir(parents=True, exist_ok=True)
        self.catalog = Catalog(self.root / CATALOG_NAME)
        self.crf = crf
        self._stage_hook = stage_hook

    def close(self) -> None:
        self.catalog.close()

    def __enter__(self) -> EpisodeStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ adding
    def add_episode(
        self,
        item: Recording | Episode,
        *,
        role: str | None = None,
        source: str | None = None,
        embodiment: str | None = None,
        collect_seed: int | None = None,
        collect_index: int | None = None,
        extra: dict | None = None,
    ) -> EpisodeMeta:
        """Store a recording (``role`` and ``source`` required) or a complete :class:`Episode`.

        Returns the stored metadata once the episode is durable and visible. Raises :class:`StoreError`
        (with nothing left behind) if it cannot be stored, e.g. when its collection slot is already filled.
        """
        if isinstance(item, Recording):
            if role is None or source is None:
                raise StoreError("adding a Recording needs role= and source=")
            ep = Episode.from_recording(
                item,
                role=role,
                source=source,
                embodiment=embodiment,
                collect_seed=collect_seed,
                collect_index=collect_index,
                extra=extra,
            )
        elif isinstance(item, Episode):
            changes: dict[str, Any] = {
                k: v
                for k, v in dict(role=role, source=source, embodiment=embodiment).items()
                if v is not None
            }
            if collect_index is not None:
                changes.update(collect_seed=collect_seed, collect_index=collect_index)
            if extra:
                changes["extra"] = {**item.meta.extra, **extra}
            ep = item.with_meta(**changes) if changes else item
            ep.validate()
        else:
            raise TypeError(f"add_episode takes a Recording or an Episode, got {type(item).__name__}")
        self._commit(ep, rollout=None)
        return ep.meta

    def add_rollout(self, rollout: RolloutRecord, recording: Recording | None = None) -> RolloutRecord:
        """Store a rollout row, and with it (same transaction) its recording as an agent episode."""
        if recording is None:
            with self.catalog.transaction():
                self.catalog.add_rollout(rollout)
            return rollout
        ep = Episode.from_recording(
            recording, role="agent", source="rollout", extra={"rollout_id": rollout.id}
        )
        rollout.episode_id = ep.meta.id
        self._commit(ep, rollout=rollout)
        return rollout

    def add_episode_files(
        self, directory: str | os.PathLike, rollout: RolloutRecord | None = None
    ) -> EpisodeMeta:
        """Store, byte for byte and under its own id, an episode whose files another store wrote (``directory``
        holds them, e.g. as received from a worker's store); ``rollout`` is the row of the rollout it records."""
        directory = Path(directory)
        meta, _ = read_meta(directory)
        read_arrays(directory)  # refuses a malformed arrays file before anything is stored
        if rollout is not None:
            rollout.episode_id = meta.id

        def copy_files(work: Path) -> list[Path]:
            return [Path(shutil.copyfile(directory / name, work / name)) for name in EPISODE_FILES]

        self._commit_files(meta, rollout, copy_files)
        return meta

    def _stage(self, name: str) -> None:
        if self._stage_hook is not None:
            self._stage_hook(name)

    def _commit(self, ep: Episode, rollout: RolloutRecord | None) -> None:
        self._commit_files(ep.meta, rollout, lambda work: write_episode_files(ep, work, crf=self.crf))

    def _commit_files(
        self, meta: EpisodeMeta, rollout: RolloutRecord | None, write_files: Callable[[Path], list[Path]]
    ) -> None:
        eid = meta.id
        if "/" in eid or eid.startswith("."):
            raise StoreError(f"invalid episode id {eid!r}")
        lock_path = self.tmp_dir / f"{eid}.lock"
        work = self.tmp_dir / eid
        final = self.episodes_dir / eid
        fd = _lock(lock_path, blocking=True)
        assert fd is not None  # a blocking lock that may create its file waits; it never gives up
        try:
            if final.exists():
                raise StoreError(f"episode {eid} already exists")
            work.mkdir()
            try:
                for path in write_files(work):
                    fsync_path(path)
                fsync_path(work, directory=True)
            except BaseException:
                shutil.rmtree(work, ignore_errors=True)
                raise
            self._stage("files_written")
            os.rename(work, final)
            fsync_path(self.episodes_dir, directory=True)
            fsync_path(self.tmp_dir, directory=True)
            self._stage("renamed")
            try:
                with self.catalog.transaction():
                    self.catalog.insert_episode(meta)
                    if rollout is not None:
                        self.catalog.add_rollout(rollout)
            except BaseException as e:
                self._remove_dir(final)
                if isinstance(e, Exception):
                    raise StoreError(f"episode {eid} ({meta.task}) was not stored: {e}") from e
                raise
            self._stage("committed")
        finally:
            _unlock(lock_path, fd)

    # ------------------------------------------------------------------ finding and loading
    def episodes(self, **filters) -> list[EpisodeMeta]:
        """Episodes matching filters of :meth:`Catalog.episodes` (task, role, embodiment, source, ...)."""
        return self.catalog.episodes(**filters)

    def get(self, episode_id: str) -> EpisodeMeta:
        meta = self.catalog.get_episode(episode_id)
        if meta is None:
            raise KeyError(f"no episode {episode_id!r} in {self.root}")
        return meta

    def episode_dir(self, episode_id: str) -> Path:
        return self.episodes_dir / episode_id

    def video_path(self, episode_id: str) -> Path:
        """The episode's MP4 (browser-playable), e.g. to serve to the UI."""
        return self.episode_dir(episode_id) / FRAMES_FILE

    def load(self, episode_id: str) -> Episode:
        """The whole episode, frames decoded."""
        self.get(episode_id)
        return read_episode(self.episode_dir(episode_id))

    def load_frames(self, episode_id: str) -> np.ndarray:
        """(F, H, W, 3) uint8 frames."""
        meta = self.get(episode_id)
        return video.read_video(self.video_path(episode_id), size=(meta.height, meta.width)).frames

    def load_arrays(self, episode_id: str) -> tuple[np.ndarray, np.ndarray | None, dict[str, np.ndarray]]:
        """(frame_times, frame_steps or None, per-step arrays) without decoding the video."""
        self.get(episode_id)
        return read_arrays(self.episode_dir(episode_id))

    def load_camera(self, episode_id: str):
        self.get(episode_id)
        return read_meta(self.episode_dir(episode_id))[1]

    # ------------------------------------------------------------------ deleting
    def delete_episode(self, episode_id: str) -> EpisodeMeta:
        """Delete one episode (row first, then files and cached frames); returns its metadata."""
        meta = self.catalog.get_episode(episode_id)
        with self.catalog.transaction():
            existed = self.catalog.delete_episode(episode_id)
        if meta is None or not existed:
            raise KeyError(f"no episode {episode_id!r} in {self.root}")
        self._remove_dir(self.episode_dir(episode_id))
        for cached in self.cache_dir.glob(f"frames/*/{episode_id}.npy"):
            cached.unlink(missing_ok=True)
        return meta

    def delete_last(self, **filters) -> EpisodeMeta | None:
        """Delete the most recently added episode matching the filters (e.g. ``task=...``); None if none."""
        newest = self.catalog.episodes(newest_first=True, limit=1, **filters)
        return self.delete_episode(newest[0].id) if newest else None

    def _remove_dir(self, path: Path) -> None:
        """Move a directory into tmp/ (one atomic step out of sight), then delete it."""
        if not path.exists():
            return
        trash = self.tmp_dir / f"deleted-{path.name}-{secrets.token_hex(3)}"
        os.rename(path, trash)
        fsync_path(path.parent, directory=True)
        shutil.rmtree(trash, ignore_errors=True)

    # ------------------------------------------------------------------ start-up check
    def check(self, clean: bool = True) -> CheckReport:
        """Find (and with ``clean``, remove) what interrupted writes and deletes left behind.

        Safe to run while other processes write: anything whose lock a live writer holds is left alone.
        """
        report = CheckReport(cleaned=clean)
        # Temporary directories and lock files.
        for entry in sorted(self.tmp_dir.iterdir()):
            if entry.suffix == ".lock":
                continue
            lock_path = self.tmp_dir / f"{entry.name}.lock"
            fd = _lock(lock_path, blocking=False)
            if fd is None:
                continue  # a live writer owns it
            try:
                if not entry.exists():
                    continue  # its writer finished (and renamed it) while we listed
                report.temp_dirs.append(entry.name)
                if clean:
                    shutil.rmtree(entry, ignore_errors=True) if entry.is_dir() else entry.unlink(
                        missing_ok=True
                    )
            finally:
                _unlock(lock_path, fd)
        # Episode directories without a row: only if no writer is between rename and commit.
        ids = self.catalog.episode_ids()
        for entry in sorted(self.episodes_dir.iterdir()):
            if entry.name in ids:
                continue
            lock_path = self.tmp_dir / f"{entry.name}.lock"
            fd = _lock(lock_path, blocking=False)
            if fd is None:
                continue
            try:
                if self.catalog.get_episode(entry.name) is None:
                    report.orphan_dirs.append(entry.name)
                    if clean:
                        self._remove_dir(entry)
            finally:
                _unlock(lock_path, fd)
        # Rows whose files are missing or incomplete.
        for eid in sorted(ids):
            d = self.episodes_dir / eid
            if d.is_dir() and all((d / f).is_file() and (d / f).stat().st_size > 0 for f in EPISODE_FILES):
                continue
            if self.catalog.get_episode(eid) is None:
                continue  # deleted meanwhile by another process
            (report.incomplete_dirs if d.is_dir() else report.missing_dirs).append(eid)
            if clean:
                with self.catalog.transaction():
                    self.catalog.delete_episode(eid)
                self._remove_dir(d)
        # Lock files nobody holds (a writer died after committing, or before creating its directory).
        for lock_path in sorted(self.tmp_dir.glob("*.lock")):
            if (self.tmp_dir / lock_path.stem).exists():
                continue
            fd = _lock(lock_path, blocking=False, create=False)
            if fd is None:
                continue  # held by a live writer, or released meanwhile
            report.stale_locks.append(lock_path.name)
            if clean:
                _unlock(lock_path, fd)
            else:
                os.close(fd)
        return report
