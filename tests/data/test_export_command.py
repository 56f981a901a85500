"""`studio export lerobot` through the CLI table."""

from __future__ import annotations

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
