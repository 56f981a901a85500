"""`studio export lerobot` through the CLI table."""

from __future__ import annotations

import json

from data_fixtures import make_recording

from studio.cli import main
from studio.data.lerobot import validate_dataset
from studio.data.store import EpisodeStore


def test_export_cli(tmp_path, capsys):
    store = EpisodeStore(tmp_path / "store")
    store.add_episode(make_recording(seed=0), role="agent", source="scripted")
    store.add_episode(make_recording(seed=1, robot="sawyer"), role="expert", source="scripted")
    out = tmp_path / "lr"
    argv = ["export", "lerobot", "--out", str(out), "--data-dir", str(tmp_path / "store"), "--role", "agent"]
    assert main(argv) == 0
    assert "exported 1 episodes" in capsys.readouterr().out
    assert validate_dataset(out) == []
    assert main(argv) == 2  # refuses to write into a non-empty directory
    assert "not empty" in capsys.readouterr().err


def test_export_onto_a_file_is_one_line_and_touches_nothing(tmp_path, capsys):
    store = EpisodeStore(tmp_path / "store")
    store.add_episode(make_recording(seed=0), role="agent", source="scripted")
    target = tmp_path / "notes.txt"
    target.write_text("keep me")
    argv = ["export", "lerobot", "--out", str(target), "--data-dir", str(tmp_path / "store")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.strip().count("\n") == 0 and "is a file" in err and "Traceback" not in err
    assert target.read_text() == "keep me"


def test_export_with_h264(tmp_path, capsys):
    store = EpisodeStore(tmp_path / "store")
    store.add_episode(make_recording(seed=0), role="agent", source="scripted")
    out = tmp_path / "lr"
    argv = [
        "export",
        "lerobot",
        "--out",
        str(out),
        "--data-dir",
        str(tmp_path / "store"),
        "--codec",
        "libx264",
    ]
    assert main(argv) == 0
    info = json.loads((out / "meta/info.json").read_text())
    assert info["features"]["observation.images.external"]["info"]["video.codec"] == "h264"
    assert validate_dataset(out) == []
