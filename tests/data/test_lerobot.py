"""LeRobot v3.0: export follows the documented schema, import brings every used field back."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from data_fixtures import make_recording

from studio.data.episode import Episode
from studio.data.lerobot import (
    CODEBASE_VERSION,
    INFO_PATH,
    VIDEO_KEY,
    LeRobotError,
    export_lerobot,
    import_lerobot,
    validate_dataset,
)
from studio.data.lerobot.command import parse_task_map
from studio.data.store import EpisodeStore
from studio.sim.recording import ARRAY_FIELDS

T1, T2 = "pick_place/cube->red", "pick_place/bar->red"


@pytest.fixture
def source(tmp_path):
    store = EpisodeStore(tmp_path / "a")
    metas = [
        store.add_episode(
            make_recording(seed=0), role="agent", source="scripted", collect_seed=0, collect_index=0
        ),
        store.add_episode(
            make_recording(task=T2, seed=1, steps=45, num_frames=25),
            role="agent",
            source="teleop",
            extra={"operator": "ana"},
        ),
        store.add_episode(
            make_recording(robot="sawyer", seed=2, success=False), role="expert", source="scripted"
        ),
    ]
    return store, metas


def _psnr(a, b):
    mse = np.mean((a.astype(float) - b.astype(float)) ** 2)
    return 10 * np.log10(255**2 / mse)


def test_round_trip_keeps_every_field(tmp_path, source):
    store, metas = source
    report = export_lerobot(store, tmp_path / "lr")
    assert (report.episodes, report.frames, report.tasks) == (3, 60 + 45 + 60, [T1, T2])
    assert validate_dataset(tmp_path / "lr") == []
    dest = EpisodeStore(tmp_path / "b")
    imported = import_lerobot(dest, tmp_path / "lr")
    assert len(imported) == 3
    for before, after in zip(metas, imported):
        a, b = store.load(before.id), dest.load(after.id)
        for name in (
            "task",
            "scene",
            "embodiment",
            "role",
            "seed",
            "success",
            "created",
            "num_frames",
            "num_steps",
            "height",
            "width",
            "fps",
            "control_dt",
            "object_names",
        ):
            assert getattr(after, name) == getattr(before, name), name
        assert after.source == "import" and after.extra["original_source"] == before.source
        assert after.extra["original_id"] == before.id
        assert {
            k: v for k, v in after.extra.items() if k not in ("original_id", "original_source", "lerobot")
        } == before.extra
        np.testing.assert_array_equal(b.camera.K, a.camera.K)
        np.testing.assert_array_equal(b.camera.T_world_cam, a.camera.T_world_cam)
        np.testing.assert_array_equal(b.frame_steps, a.frame_steps)
        np.testing.assert_array_equal(b.frame_times, a.frame_times)
        for k in ARRAY_FIELDS:
            np.testing.assert_array_equal(b.arrays[k], a.arrays[k])
            assert b.arrays[k].shape == a.arrays[k].shape
        assert _psnr(b.frames, a.frames) > 28
    assert dest.check().ok


def test_schema_details(tmp_path, source):
    store, metas = source
    export_lerobot(store, tmp_path / "lr")
    root = tmp_path / "lr"
    info = json.loads((root / INFO_PATH).read_text())
    assert info["codebase_version"] == CODEBASE_VERSION and info["fps"] == 50
    assert info["robot_type"] == "panda,sawyer"
    video = info["features"][VIDEO_KEY]
    assert video["dtype"] == "video" and video["shape"] == [48, 64, 3]
    assert video["info"]["video.codec"] == "av1" and video["info"]["video.pix_fmt"] == "yuv420p"
    np.testing.assert_array_equal(video["info"]["camera.K"], store.load_camera(metas[0].id).K)
    eps = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert [e["dataset_from_index"] for e in eps] == [0, 60, 105]
    assert eps[1][f"videos/{VIDEO_KEY}/from_timestamp"] == pytest.approx(60 / 50)
    assert eps[0]["stats/observation.ee_pos_cam/mean"] == pytest.approx(
        store.load_arrays(metas[0].id)[2]["ee_pos_cam"].mean(0).tolist()
    )
    stats = json.loads((root / "meta/stats.json").read_text())
    assert stats["index"]["max"] == [164] and stats["index"]["count"] == [165]
    for feature in ("observation.state", "action", "observation.qpos", VIDEO_KEY):
        assert set(stats[feature]) == {
            "min",
            "max",
            "mean",
            "std",
            "count",
            "q01",
            "q10",
            "q50",
            "q90",
            "q99",
        }
        lo, mid, hi = (np.asarray(stats[feature][q]) for q in ("q01", "q50", "q99"))
        assert (lo <= mid).all() and (mid <= hi).all()
    assert np.asarray(stats[VIDEO_KEY]["q50"]).shape == (3, 1, 1)
    import pandas as pd

    tasks = pd.read_parquet(root / "meta/tasks.parquet")
    assert list(tasks.index) == [
        "pick up the cube and place it in the red zone",
        "pick up the bar and place it in the red zone",
    ] and tasks["task_index"].tolist() == [0, 1]
    assert [e["osvi/task"] for e in eps] == [T1, T2, T1]
    assert eps[1]["tasks"] == ["pick up the bar and place it in the red zone"]
    # Every observation.* feature is a policy input LeRobot can normalise: numbers, no flags.
    features = info["features"]
    observations = {k: f["dtype"] for k, f in features.items() if k.startswith("observation.")}
    assert set(observations.values()) == {"float32", "video"}, observations
    assert features["osvi.frame_rendered"]["dtype"] == "bool" and "observation.frame_rendered" not in features
    assert {f["dtype"] for f in features.values()} <= {"float32", "int64", "bool", "video"}
    data = pq.read_table(root / "data/chunk-000/file-000.parquet")
    assert data.schema.field("observation.qpos").type.value_type == pa.float32()
    qpos = store.load_arrays(metas[0].id)[2]["qpos"]
    np.testing.assert_array_equal(eps[0]["osvi/exact/qpos"], qpos.ravel())  # float64, for the round trip
    # Encoded as LeRobot encodes: AV1, a keyframe every 2 frames.
    import av

    with av.open(str(root / f"videos/{VIDEO_KEY}/chunk-000/file-000.mp4")) as container:
        keys = [p.is_keyframe for p in container.demux(video=0) if p.size]
        assert container.streams.video[0].codec_context.name in ("libdav1d", "av1")
    assert len(keys) == 165 and sum(keys) >= 165 // 2


def test_multiple_files_and_chunks(tmp_path, source):
    store, metas = source
    export_lerobot(store, tmp_path / "lr", chunks_size=2, data_files_size_in_mb=0, video_files_size_in_mb=0)
    root = tmp_path / "lr"
    assert (root / "data/chunk-001/file-000.parquet").is_file()
    assert (root / f"videos/{VIDEO_KEY}/chunk-001/file-000.mp4").is_file()
    assert validate_dataset(root) == []
    imported = import_lerobot(EpisodeStore(tmp_path / "b"), root)
    assert [m.num_steps for m in imported] == [m.num_steps for m in metas]


def _rewrite_data(root, fn):
    path = root / "data/chunk-000/file-000.parquet"
    pq.write_table(fn(pq.read_table(path)), path)


def _shift_timestamps(table):
    shifted = pa.array(table.column("timestamp").to_numpy() + np.float32(0.5), type=pa.float32())
    return table.set_column(table.column_names.index("timestamp"), "timestamp", shifted)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (
            lambda r: (r / INFO_PATH).write_text((r / INFO_PATH).read_text().replace('"v3.0"', '"v2.1"')),
            "codebase",
        ),
        (lambda r: _rewrite_data(r, lambda t: t.drop(["observation.qpos"])), "data columns"),
        (lambda r: _rewrite_data(r, _shift_timestamps), "timestamps"),
        (lambda r: (r / f"videos/{VIDEO_KEY}/chunk-000/file-000.mp4").unlink(), "missing video"),
        (lambda r: (r / "meta/tasks.parquet").unlink(), "tasks.parquet"),
        (lambda r: (r / "meta/stats.json").unlink(), "stats.json"),
    ],
)
def test_validation_catches_damage(tmp_path, source, damage, message):
    store, _ = source
    export_lerobot(store, tmp_path / "lr")
    damage(tmp_path / "lr")
    problems = validate_dataset(tmp_path / "lr")
    assert any(message in p for p in problems), problems
    if message != "stats.json":
        dest = EpisodeStore(tmp_path / "b")
        with pytest.raises(LeRobotError):
            import_lerobot(dest, tmp_path / "lr")
        assert dest.episodes() == []


def test_export_refusals(tmp_path, source):
    store, metas = source
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    with pytest.raises(LeRobotError, match="not empty"):
        export_lerobot(store, tmp_path / "full")
    with pytest.raises(LeRobotError, match="no episodes"):
        export_lerobot(store, tmp_path / "none", tasks=["pick_place/prism->red"])
    store.add_episode(make_recording(seed=5, size=(32, 32)), role="agent", source="scripted")
    with pytest.raises(LeRobotError, match="frame size differs"):
        export_lerobot(store, tmp_path / "mixed")
    report = export_lerobot(store, tmp_path / "ids", episode_ids=[metas[0].id])
    assert report.episodes == 1


def test_human_videos_skipped(tmp_path, source):
    store, _ = source
    ep = Episode.from_recording(make_recording(seed=9), role="expert", source="upload")
    meta = {**ep.meta.to_dict(), "embodiment": "human", "num_steps": 0, "control_dt": None}
    store.add_episode(Episode(ep.meta.__class__(**meta), ep.camera, ep.frames, ep.frame_times))
    report = export_lerobot(store, tmp_path / "lr")
    assert report.episodes == 3 and len(report.skipped) == 1 and "skipped 1" in report.summary()


def test_task_map_and_unknown_tasks(tmp_path, source):
    store, _ = source
    export_lerobot(store, tmp_path / "lr")
    dest = EpisodeStore(tmp_path / "b")
    known = [T1, T2, "pick_place/cube->blue"]
    with pytest.raises(LeRobotError, match="not studio tasks"):
        import_lerobot(dest, tmp_path / "lr", known_tasks=known[1:])
    assert dest.episodes() == []
    task_map = parse_task_map([f"{T1}=pick_place/cube->blue"])
    metas = import_lerobot(dest, tmp_path / "lr", task_map=task_map, known_tasks=known, role="agent")
    assert [m.task for m in metas] == ["pick_place/cube->blue", T2, "pick_place/cube->blue"]
    assert all(m.role == "agent" for m in metas)
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({"a": "b/c"}))
    assert parse_task_map([str(mapping), "x y=s/t"]) == {"a": "b/c", "x y": "s/t"}
    with pytest.raises(LeRobotError):
        parse_task_map(["no-equals-sign"])


def test_foreign_dataset_without_studio_features(tmp_path, source):
    store, _ = source
    export_lerobot(store, tmp_path / "lr")
    root = tmp_path / "lr"
    info = json.loads((root / INFO_PATH).read_text())
    del info["features"]["observation.ee_pos_cam"]
    (root / INFO_PATH).write_text(json.dumps(info))
    _rewrite_data(root, lambda t: t.drop(["observation.ee_pos_cam"]))
    assert validate_dataset(root) == []  # still a valid LeRobot dataset...
    with pytest.raises(LeRobotError, match="lacks the studio's per-step features"):  # ...not trajectories
        import_lerobot(EpisodeStore(tmp_path / "b"), root, kind="trajectories")
    with pytest.raises(LeRobotError, match="--task"):  # ...but its camera stream, once the task is named
        import_lerobot(EpisodeStore(tmp_path / "b"), root)
    (demo,) = import_lerobot(EpisodeStore(tmp_path / "b"), root, task=T1, episodes=[0])
    assert (demo.role, demo.embodiment, demo.source, demo.num_steps) == ("expert", "human", "import", 0)
    assert demo.extra["camera_nominal"] and demo.extra["lerobot"]["episode_index"] == 0


def test_a_failure_while_storing_removes_the_episodes_already_added(tmp_path, source, monkeypatch):
    store, _ = source
    export_lerobot(store, tmp_path / "lr")
    dest = EpisodeStore(tmp_path / "b")
    real_add, calls = dest.add_episode, []

    def add_then_fail(ep, **kwargs):
        calls.append(ep.meta.id)
        if len(calls) == 3:
            raise OSError("disk full")
        return real_add(ep, **kwargs)

    monkeypatch.setattr(dest, "add_episode", add_then_fail)
    with pytest.raises(OSError, match="disk full"):
        import_lerobot(dest, tmp_path / "lr")
    assert len(calls) == 3 and dest.episodes() == [] and dest.check().ok


def test_exports_of_earlier_versions_still_import(tmp_path, source):
    """Earlier exports named the studio's columns observation.gripper_cmd / .time / .frame_rendered (float64)."""
    store, metas = source
    root = tmp_path / "lr"
    export_lerobot(store, root)
    info = json.loads((root / INFO_PATH).read_text())
    old = {"osvi.gripper_cmd": "observation.gripper_cmd", "osvi.time": "observation.time"}
    old["osvi.frame_rendered"] = "observation.frame_rendered"
    info["features"] = {old.get(k, k): v for k, v in info["features"].items()}
    (root / INFO_PATH).write_text(json.dumps(info))
    _rewrite_data(root, lambda t: t.rename_columns([old.get(c, c) for c in t.column_names]))
    assert validate_dataset(root) == []
    imported = import_lerobot(EpisodeStore(tmp_path / "b"), root)
    for before, after in zip(metas, imported):
        a, b = store.load(before.id), EpisodeStore(tmp_path / "b").load(after.id)
        np.testing.assert_array_equal(b.frame_steps, a.frame_steps)
        np.testing.assert_array_equal(b.arrays["time"], a.arrays["time"])


def test_without_rendered_rows_the_frames_are_evenly_spaced(tmp_path, source):
    store, metas = source
    root = tmp_path / "lr"
    export_lerobot(store, root, episode_ids=[metas[0].id])
    none = pa.array(np.zeros(60, dtype=bool))
    _rewrite_data(
        root, lambda t: t.set_column(t.column_names.index("osvi.frame_rendered"), "osvi.frame_rendered", none)
    )
    (meta,) = import_lerobot(EpisodeStore(tmp_path / "b"), root)
    ep = EpisodeStore(tmp_path / "b").load(meta.id)
    np.testing.assert_array_equal(ep.frame_steps, np.round(np.linspace(0, 59, 20)).astype(int))
