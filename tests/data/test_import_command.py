"""`studio import lerobot` through the CLI table: a task map, a round trip detected when repeated."""

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
    assert not (tmp_path / "b").exists(), "a refused import creates no store"
    # The dataset's task is an instruction; a map keyed on it works as well as one keyed on the studio name.
    instruction = "pick up the cube and place it in the red zone"
    assert main([*argv, "--task-map", f"{instruction}=pick_place/prism->blue"]) == 0
    out = capsys.readouterr().out
    assert "imported 1 episodes" in out and "as trajectories" in out
    (meta,) = EpisodeStore(dest).episodes()
    assert (meta.task, meta.source, meta.role) == ("pick_place/prism->blue", "import", "agent")


def test_the_same_export_imported_twice_is_stored_once(tmp_path, capsys):
    store = EpisodeStore(tmp_path / "a")
    store.add_episode(make_recording(seed=0), role="agent", source="scripted")
    store.add_episode(make_recording(seed=1, task="pick_place/bar->blue"), role="agent", source="scripted")
    export_lerobot(store, tmp_path / "lr")
    export_lerobot(store, tmp_path / "lr-again")  # another copy of the same episodes
    dest = str(tmp_path / "b")
    assert main(["import", "lerobot", str(tmp_path / "lr"), "--data-dir", dest, "--episodes", "1"]) == 0
    capsys.readouterr()
    assert main(["import", "lerobot", str(tmp_path / "lr-again"), "--data-dir", dest]) == 0
    out = capsys.readouterr().out
    assert "imported 1 episodes" in out and "skipped 1 episodes already in the store" in out
    assert sorted(m.task for m in EpisodeStore(dest).episodes()) == [
        "pick_place/bar->blue",
        "pick_place/cube->red",
    ]
