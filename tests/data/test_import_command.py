"""`studio import lerobot` through the CLI table, with a task map."""

from __future__ import annotations

from data_fixtures import make_recording

from studio.cli import main
from studio.data.lerobot import export_lerobot
from studio.data.store import EpisodeStore


def test_import_cli(tmp_path, capsys):
    store = EpisodeStore(tmp_path / "a")
    store.add_episode(make_recording(seed=0), role="agent", source="scripted")
    export_lerobot(store, tmp_path / "lr")
    dest = str(tmp_path / "b")
    argv = ["import", "lerobot", str(tmp_path / "lr"), "--data-dir", dest]
    assert main([*argv, "--task-map", "pick_place/cube->red=pick_place/cube->purple"]) == 2
    assert "not studio tasks" in capsys.readouterr().err
    assert EpisodeStore(dest).episodes() == []
    assert main([*argv, "--task-map", "pick_place/cube->red=pick_place/prism->blue"]) == 0
    assert "imported 1 episodes" in capsys.readouterr().out
    (meta,) = EpisodeStore(dest).episodes()
    assert (meta.task, meta.source, meta.role) == ("pick_place/prism->blue", "import", "agent")
