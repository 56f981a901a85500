"""atomic_write: the destination is replaced whole or not at all, and no temporary file is left behind."""

from __future__ import annotations

import os
import stat

import pytest

from studio.data import atomic_files
from studio.data.atomic_files import atomic_write, fsync_path


def test_bytes_text_and_a_writer_replace_the_file(tmp_path):
    path = tmp_path / "f.json"
    atomic_write(path, b"one")
    assert path.read_bytes() == b"one"
    atomic_write(path, "twø")
    assert path.read_text(encoding="utf-8") == "twø"
    atomic_write(path, lambda f: f.write(b"three"))
    assert path.read_bytes() == b"three"
    assert os.listdir(tmp_path) == ["f.json"]


def test_a_failing_writer_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "f.bin"
    path.write_bytes(b"old")

    def half_then_fail(f):
        f.write(b"partial")
        raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError, match="disk on fire"):
        atomic_write(path, half_then_fail)
    assert path.read_bytes() == b"old" and os.listdir(tmp_path) == ["f.bin"]


def test_a_failing_rename_removes_the_temporary(tmp_path, monkeypatch):
    path = tmp_path / "f.bin"

    def refuse(src, dst):
        raise OSError("read-only file system")

    monkeypatch.setattr(atomic_files.os, "replace", refuse)
    with pytest.raises(OSError, match="read-only"):
        atomic_write(path, b"new")
    assert os.listdir(tmp_path) == []


def test_the_new_file_gets_the_permissions_open_would_give(tmp_path):
    path = tmp_path / "f.txt"
    atomic_write(path, "x")
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~atomic_files._UMASK


def test_a_missing_directory_is_an_error_not_a_created_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        atomic_write(tmp_path / "absent" / "f", b"x")
    assert os.listdir(tmp_path) == []


def test_fsync_path_flushes_files_and_directories(tmp_path):
    (tmp_path / "f").write_bytes(b"x")
    fsync_path(tmp_path / "f")
    fsync_path(tmp_path, directory=True)
    with pytest.raises(FileNotFoundError):
        fsync_path(tmp_path / "missing")
