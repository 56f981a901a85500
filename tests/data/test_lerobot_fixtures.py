"""Datasets written by the real LeRobot library (fixtures/lerobot, see make_fixtures.py there) import.

Video (AV1 and H.264) and image features import as demonstration videos of a task the user names, the
studio's own feature names as trajectories, a studio export edited by LeRobot's ``delete_episodes`` as
trajectories again; the statistics the studio writes are those LeRobot computes on the same data.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from data_fixtures import make_recording

from studio.cli import main
from studio.data.lerobot import LeRobotError, export_lerobot, import_lerobot, validate_dataset
from studio.data.lerobot.reader import read_lerobot
from studio.data.lerobot.validate import as_matrix, read_tasks
from studio.data.lerobot.writer import _image_stats, _stats
from studio.data.store import EpisodeStore
from studio.data.video import probe_video

FIXTURES = Path(__file__).parent / "fixtures" / "lerobot"
NAMES = ("av1-video", "h264-video", "image", "studio-features", "studio-export-deleted", "hand-push")
PUSH = "push/blue-backward"


def _make_fixtures_module():
    spec = importlib.util.spec_from_file_location("make_fixtures", FIXTURES / "make_fixtures.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_fixtures_were_written_by_lerobot_and_stay_small():
    assert (FIXTURES / "LEROBOT_VERSION").read_text().strip() == "0.4.4"
    for name in NAMES:
        size = sum(f.stat().st_size for f in (FIXTURES / name).rglob("*") if f.is_file())
        assert size < 200 * 1024, (name, size)


@pytest.mark.parametrize("name", NAMES)
def test_every_fixture_validates_with_lerobots_unnamed_task_index(name):
    root = FIXTURES / name
    assert validate_dataset(root) == []
    assert pd.read_parquet(root / "meta/tasks.parquet").index.name is None  # as LeRobot writes it
    assert all(isinstance(t, str) and t for t in read_tasks(root))


@pytest.mark.parametrize(
    ("name", "decoders"), [("av1-video", ("av1", "libdav1d")), ("h264-video", ("h264",))]
)
def test_a_video_feature_imports_as_demonstration_videos(tmp_path, name, decoders):
    root = FIXTURES / name
    assert probe_video(root / "videos/observation.images.top/chunk-000/file-000.mp4").codec in decoders
    with pytest.raises(LeRobotError, match="--task"):
        read_lerobot(root)
    with pytest.raises(LeRobotError, match="lacks the studio's per-step features"):
        read_lerobot(root, kind="trajectories", task=PUSH)
    store = EpisodeStore(tmp_path / "store")
    metas = import_lerobot(store, root, task=PUSH)
    assert [(m.role, m.embodiment, m.source, m.task, m.num_steps) for m in metas] == [
        ("expert", "human", "import", PUSH, 0)
    ] * 2
    assert [m.num_frames for m in metas] == [12, 13]  # 10 fps: nothing thinned
    for i, m in enumerate(metas):
        assert (
            m.extra["lerobot"]["episode_index"] == i
            and m.extra["lerobot"]["camera"] == "observation.images.top"
        )
        assert m.extra["lerobot_task"] == "move the red square to the right" and m.extra["camera_nominal"]
        frames = store.load_frames(m.id)
        assert frames.shape[1:] == (240, 320, 3)
        # The red square crosses the view from left to right, as the dataset shows it.
        red = (frames[..., 0] > 150) & (frames[..., 1] < 90) & (frames[..., 2] < 90)
        xs = [np.flatnonzero(r.any(axis=0)).mean() for r in red]
        assert np.all(np.diff(xs) > 0) and xs[0] < 60 and xs[-1] > 260


def test_an_image_feature_imports_its_frames_exactly(tmp_path):
    fx = _make_fixtures_module()
    store = EpisodeStore(tmp_path / "store")
    (meta,) = import_lerobot(store, FIXTURES / "image", task=PUSH)
    assert meta.extra["lerobot"]["camera"] == "observation.image" and meta.num_frames == 12
    plan = read_lerobot(FIXTURES / "image", task=PUSH, size=(32, 40))  # the frames at their own size
    expected = np.stack([fx._camera(i, 32, 40, 12) for i in range(12)])
    np.testing.assert_array_equal(plan.episodes[0].frames, expected)  # PNG: lossless


def test_the_studios_feature_names_import_as_trajectories(tmp_path):
    store = EpisodeStore(tmp_path / "store")
    metas = import_lerobot(store, FIXTURES / "studio-features")
    assert [m.task for m in metas] == [
        "pick_place/cube->red",
        "pick_place/bar->blue",
    ]  # from the instructions
    assert [m.num_steps for m in metas] == [40, 30]
    for meta, (task, seed, steps) in zip(
        metas, (("pick_place/cube->red", 0, 40), ("pick_place/bar->blue", 1, 30))
    ):
        rec = make_recording(task=task, seed=seed, steps=steps, num_frames=10)
        ep = store.load(meta.id)
        assert meta.extra["camera_nominal"] and meta.role == "agent"
        for name in ("qpos", "ee_pos_world", "object_poses", "time", "gripper_cmd"):
            # LeRobot stores the float32 columns; without the studio's exact columns that is what comes back
            np.testing.assert_array_equal(ep.arrays[name], rec.arrays[name].astype(np.float32))
        np.testing.assert_array_equal(ep.frame_steps, rec.frame_steps)  # from osvi.frame_rendered
        assert np.abs(ep.frames.astype(int) - rec.frames.astype(int)).mean() < 8


def test_a_studio_export_edited_by_lerobots_delete_episodes_imports(tmp_path):
    root = FIXTURES / "studio-export-deleted"
    assert pq.read_table(root / "meta/tasks.parquet").column_names == ["task_index", "__index_level_0__"]
    metas = import_lerobot(EpisodeStore(tmp_path / "store"), root)
    assert [m.task for m in metas] == [
        "pick_place/cube->red",
        "pick_place/bar->blue",
    ]  # the middle one deleted
    assert all(not m.extra.get("camera_nominal") for m in metas)  # the shared camera of the video's info

    # The same recordings exported here and imported first: LeRobot's edit (re-indexed rows, a re-encoded
    # video) leaves the same trajectories, which are not stored twice.
    source = EpisodeStore(tmp_path / "source")
    for seed, task in enumerate(("pick_place/cube->red", "pick_place/cube->blue", "pick_place/bar->blue")):
        source.add_episode(
            make_recording(task=task, seed=seed, steps=30, num_frames=10), role="agent", source="scripted"
        )
    export_lerobot(source, tmp_path / "fresh")
    dest = EpisodeStore(tmp_path / "dest")
    assert len(import_lerobot(dest, tmp_path / "fresh")) == 3
    assert import_lerobot(dest, root) == [] and len(dest.episodes()) == 3


def test_the_studios_statistics_are_those_lerobot_computes(tmp_path):
    """LeRobot computed the fixture's per-episode stats (quantiles included) on these very columns."""
    root = FIXTURES / "studio-features"
    info = json.loads((root / "meta/info.json").read_text())
    data = pq.read_table(root / "data/chunk-000/file-000.parquet")
    eps = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    checked = 0
    for e in eps:
        lo, hi = e["dataset_from_index"], e["dataset_to_index"]
        for name, ft in info["features"].items():
            if ft["dtype"] == "video" or f"stats/{name}/q50" not in e:
                continue
            ours = _stats(as_matrix(data.column(name))[lo:hi], ft["dtype"])
            for key in ("min", "max", "mean", "q01", "q10", "q50", "q90", "q99"):
                np.testing.assert_allclose(
                    ours[key], np.ravel(e[f"stats/{name}/{key}"]), atol=1e-5, err_msg=f"{name} {key}"
                )
            # LeRobot takes E[x²] - E[x]² in float32 (the column's dtype), which cancels where the spread is
            # small beside the values; the studio's float64 std agrees to that precision.
            np.testing.assert_allclose(ours["std"], np.ravel(e[f"stats/{name}/std"]), rtol=2e-3, atol=1e-5)
            checked += 1
    assert checked >= 2 * 12
    # Images: the image fixture's frames come back exactly (PNG), so their stats must match LeRobot's.
    plan = read_lerobot(FIXTURES / "image", task=PUSH, size=(32, 40), fps_cap=None)
    ours = _image_stats(plan.episodes[0].frames)
    (e,) = pq.read_table(FIXTURES / "image/meta/episodes/chunk-000/file-000.parquet").to_pylist()
    for key in ("min", "max", "mean", "count", "q01", "q10", "q50", "q90", "q99"):
        np.testing.assert_allclose(
            np.ravel(ours[key]), np.ravel(e[f"stats/observation.image/{key}"]), atol=1e-6
        )
    assert (
        np.ravel(e["stats/observation.image/std"]).max() == 0
    )  # LeRobot 0.4.4 squares uint8 pixels: it wraps
    assert np.ravel(ours["std"]).min() > 0.05


def test_reimporting_is_detected_and_a_failed_import_creates_nothing(tmp_path, capsys):
    data = tmp_path / "new-store"
    root = str(FIXTURES / "av1-video")
    assert main(["import", "lerobot", root, "--data-dir", str(data)]) == 2
    assert "--task" in capsys.readouterr().err
    assert not data.exists(), "a failed import creates no store"
    assert main(["import", "lerobot", root, "--task", "push/nowhere", "--data-dir", str(data)]) == 2
    assert "not studio tasks" in capsys.readouterr().err and not data.exists()
    argv = ["import", "lerobot", root, "--task", PUSH, "--data-dir", str(data)]
    assert main(argv) == 0
    assert "imported 2 episodes" in capsys.readouterr().out
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "imported 0 episodes" in out and "skipped 2 episodes already in the store" in out
    assert len(EpisodeStore(data).episodes()) == 2
    assert main([*argv, "--episodes", "1", "7"]) == 2
    assert "no episodes [7]" in capsys.readouterr().err


def test_import_help_says_which_features_import_as_what(capsys):
    with pytest.raises(SystemExit):
        main(["import", "--help"])
    text = capsys.readouterr().out
    assert "trajectories" in text and "observation.qpos" in text and "demonstrations" in text
    assert "video or an image feature" in text


def test_episodes_longer_than_a_demonstration_may_last_are_refused(monkeypatch):
    from studio.data.lerobot import reader
    from studio.data.video_import import ImportLimits

    monkeypatch.setattr(reader, "ImportLimits", lambda: ImportLimits(max_duration_s=1.25))
    with pytest.raises(LeRobotError, match=r"episodes \[1\] are longer than the 1 s"):
        read_lerobot(FIXTURES / "av1-video", task=PUSH)
    assert len(read_lerobot(FIXTURES / "av1-video", task=PUSH, episodes=[0]).episodes) == 1


def test_names_given_as_a_dict_are_accepted(tmp_path):
    """Many LeRobot datasets name a vector's entries as {"motors": [...]}."""
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(FIXTURES / "av1-video", root)
    info = json.loads((root / "meta/info.json").read_text())
    info["features"]["observation.state"]["names"] = {"axes": ["x", "y"]}
    (root / "meta/info.json").write_text(json.dumps(info))
    assert validate_dataset(root) == []
    assert len(import_lerobot(EpisodeStore(tmp_path / "store"), root, task=PUSH)) == 2
