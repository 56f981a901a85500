"""The job queue's journal: the file a restarted hub reloads its jobs from.

One header line (``{"journal":"studio-jobs","version":2}``), then one JSON line per state change of a job
(:class:`JournalEntry`: its status and result; the last line of a job wins). :class:`JournalFile` appends
entries (flushed at once; :meth:`JournalFile.sync` makes them durable), reads them back (a line cut short by a
crash mid-append is dropped, and the file marked for compaction; the first format, one JSON document, is read
too) and compacts the file by rewriting it atomically with the live entries
(:func:`studio.data.atomic_files.atomic_write`). When to write, sync and compact is the queue's
(:mod:`studio.backend.job_queue`).
"""

from __future__ import annotations

import os
from pathlib import Path

import msgspec

from studio.backend import messages as msg
from studio.data.atomic_files import atomic_write

JOURNAL_VERSION = 2


class JournalEntry(msgspec.Struct):
    status: msg.JobStatus
    result: msg.JobResult | None = None


class _JournalHeader(msgspec.Struct):
    journal: str
    version: int


class _JournalV1(msgspec.Struct):
    """The journal's first format: the whole queue as one JSON document, rewritten on every change."""

    version: int
    jobs: list[JournalEntry]


_HEADER = _JournalHeader(journal="studio-jobs", version=JOURNAL_VERSION)


class JournalError(RuntimeError):
    """The journal cannot be read at all (not a journal of this format)."""


class JournalFile:
    """An append-only log of job entries: a header line, then one JSON entry per state change (the last entry
    of a job wins). :meth:`compact` rewrites it with the given entries only, atomically."""

    def __init__(self, path: Path):
        self.path = path
        self.lines = 0  # entries in the file
        self._unsynced = False

    def load(self) -> tuple[list[JournalEntry], bool]:
        """The entries (last per job), and whether the file should be compacted (old format, torn tail)."""
        data = self.path.read_bytes()
        if data.lstrip().startswith(b'{"version"'):
            try:
                old = msgspec.json.decode(data, type=_JournalV1)
            except msgspec.MsgspecError as e:
                raise JournalError(f"not a job journal: {e}") from None
            if old.version != 1:
                raise JournalError(f"journal version {old.version}, expected 1 or {JOURNAL_VERSION}")
            return old.jobs, True
        lines = data.split(b"\n")
        try:
            header = msgspec.json.decode(lines[0], type=_JournalHeader)
        except msgspec.MsgspecError as e:
            raise JournalError(f"not a job journal: {e}") from None
        if header.version != JOURNAL_VERSION:
            raise JournalError(f"journal version {header.version}, expected {JOURNAL_VERSION}")
        latest: dict[str, JournalEntry] = {}
        torn = False
        decoder = msgspec.json.Decoder(JournalEntry)
        for i, line in enumerate(lines[1:], start=1):
            if not line.strip():
                continue
            try:
                entry = decoder.decode(line)
            except msgspec.MsgspecError as e:
                if i >= len(lines) - 2:  # the last line, cut short by a crash mid-append
                    torn = True
                    continue
                raise JournalError(f"line {i + 1}: {e}") from None
            latest.pop(entry.status.job, None)  # re-insert: the dict's order is the order of last change
            latest[entry.status.job] = entry
            self.lines += 1
        return list(latest.values()), torn

    def append(self, entries: list[JournalEntry]) -> None:
        """Append entries and flush them to the OS (a crash of this process loses nothing; :meth:`sync` makes
        them durable against a crash of the machine). Raises OSError."""
        data = b"".join(msgspec.json.encode(e) + b"\n" for e in entries)
        if not self.path.parent.is_dir():
            self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "ab") as f:
            if f.tell() == 0:
                data = msgspec.json.encode(_HEADER) + b"\n" + data
                self.lines = 0
            f.write(data)
        self.lines += len(entries)
        self._unsynced = True

    def sync(self) -> None:
        if self._unsynced and self.path.exists():
            fd = os.open(self.path, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
            self._unsynced = False

    def compact(self, entries: list[JournalEntry]) -> None:
        """Rewrite the file as a header and ``entries``, durably (temporary file, fsync, rename). Raises OSError."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        lines = [msgspec.json.encode(_HEADER)] + [msgspec.json.encode(e) for e in entries]
        atomic_write(self.path, b"".join(line + b"\n" for line in lines))
        self.lines = len(entries)
        self._unsynced = False

    def close(self) -> None:
        try:
            self.sync()
        except OSError:
            pass
