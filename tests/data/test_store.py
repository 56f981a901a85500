"""The episode store: round trip, crash safety under SIGKILL, concurrent writers, delete, start-up check."""

from __future__ import annotations

import multiprocessing as mp
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from data_fixtures import make_recording

from studio.data.catalog import RolloutRecord
from studio.data.episode import ARRAYS_FILE, FRAMES_FILE, Episode
from studio.data.splits import SplitSpec
from studio.data.store import EpisodeStore, StoreError
from studio.data.training_view import PairDataset
from studio.sim.recording import ARRAY_FIELDS

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]


def _assert_consistent(store: EpisodeStore) -> None:
    """Every catalogued episode loads completely, and the training view builds and yields samples."""
    metas = store.episodes()
    for meta in metas:
        ep = store.load(meta.id)
        assert len(ep.frames) == meta.num_frames
    spec = SplitSpec("pick_place", train=("pick_place/cube->red",), test=(), val_fraction=0.0)
    ds = PairDataset(store, image_size=(24, 32), split_spec=spec, expert_roles=("agent",))
    assert len(ds) == len(metas) ** 2
    if len(ds):
        assert ds[len(ds) - 1]["agent_frames"].shape == (6, 3, 24, 32)


def test_round_trip_every_field(tmp_path):
    store = EpisodeStore(tmp_path)
    rec = make_recording(robot="sawyer", seed=11, steps=50, num_frames=12, success=False)
    meta = store.add_episode(rec, role="expert", source="teleop", extra={"operator": "ana"})
    assert store.episodes() == [meta]
    ep = store.load(meta.id)
    assert ep.meta == meta
    assert (meta.embodiment, meta.role, meta.source, meta.seed, meta.success) == (
        "sawyer",
        "expert",
        "teleop",
        11,
        False,
    )
    assert meta.extra == {"operator": "ana"}
    assert abs(meta.created - time.time()) < 60
    np.testing.assert_array_equal(ep.camera.K, rec.camera.K)
    np.testing.assert_array_equal(ep.camera.T_world_cam, rec.camera.T_world_cam)
    assert (ep.camera.width, ep.camera.height) == (64, 48)
    np.testing.assert_array_equal(ep.frame_steps, rec.frame_steps)
    for k in ARRAY_FIELDS:
        np.testing.assert_array_equal(ep.arrays[k], rec.arrays[k])
    assert np.abs(ep.frames.astype(int) - rec.frames).mean() < 4
    assert list(ep.meta.object_names) == rec.object_names
    times, steps, arrays = store.load_arrays(meta.id)
    np.testing.assert_array_equal(steps, rec.frame_steps)
    np.testing.assert_array_equal(times, ep.frame_times)
    np.testing.assert_array_equal(arrays["qpos"], rec.arrays["qpos"])
    assert store.load_frames(meta.id).shape == rec.frames.shape
    assert store.video_path(meta.id).is_file()
    assert store.check().ok


def test_add_requires_role_and_source(tmp_path):
    store = EpisodeStore(tmp_path)
    with pytest.raises(StoreError, match="role"):
        store.add_episode(make_recording())
    with pytest.raises(TypeError):
        store.add_episode("not an episode")


def test_duplicate_collection_slot_rejected_and_nothing_left(tmp_path):
    store = EpisodeStore(tmp_path)
    store.add_episode(
        make_recording(seed=1), role="agent", source="scripted", collect_seed=0, collect_index=3
    )
    with pytest.raises(StoreError, match="not stored"):
        store.add_episode(
            make_recording(seed=2), role="agent", source="scripted", collect_seed=0, collect_index=3
        )
    assert len(store.episodes()) == 1
    assert len(list(store.episodes_dir.iterdir())) == 1
    assert list(store.tmp_dir.iterdir()) == []


def test_delete_one_and_last(tmp_path):
    store = EpisodeStore(tmp_path)
    a = store.add_episode(make_recording(seed=0), role="agent", source="scripted")
    b = store.add_episode(make_recording(seed=1, task="pick_place/bar->red"), role="agent", source="teleop")
    c = store.add_episode(make_recording(seed=2), role="agent", source="teleop")
    cached = store.cache_dir / "frames" / "8x8" / f"{a.id}.npy"
    cached.parent.mkdir(parents=True)
    cached.write_bytes(b"x")
    assert store.delete_episode(a.id) == a
    assert not store.episode_dir(a.id).exists() and not cached.exists()
    with pytest.raises(KeyError):
        store.delete_episode(a.id)
    with pytest.raises(KeyError):
        store.load(a.id)
    assert store.delete_last(task="pick_place/bar->red") == b
    assert store.delete_last(source="scripted") is None
    assert [m.id for m in store.episodes()] == [c.id]
    assert store.delete_last() == c
    assert store.episodes() == [] and list(store.episodes_dir.iterdir()) == []
    assert store.check().ok


def test_rollout_with_recording_is_one_transaction(tmp_path):
    store = EpisodeStore(tmp_path)
    expert = store.add_episode(make_recording(robot="sawyer"), role="expert", source="scripted")
    r = RolloutRecord(
        id="r1",
        task="pick_place/cube->red",
        expert_episode_id=expert.id,
        success=False,
        failure_stage="grasp",
    )
    store.add_rollout(r, make_recording(seed=5))
    (stored,) = store.catalog.rollouts(success=False)
    assert stored.episode_id is not None
    ep = store.get(stored.episode_id)
    assert (ep.role, ep.source, ep.extra["rollout_id"]) == ("agent", "rollout", "r1")
    # A rollout whose row cannot be inserted (duplicate id) leaves no episode behind.
    with pytest.raises(StoreError):
        store.add_rollout(r, make_recording(seed=6))
    assert len(store.episodes()) == 2 and len(list(store.episodes_dir.iterdir())) == 2


def test_check_finds_external_damage(tmp_path):
    store = EpisodeStore(tmp_path)
    a = store.add_episode(make_recording(seed=0), role="agent", source="scripted")
    b = store.add_episode(make_recording(seed=1), role="agent", source="scripted")
    c = store.add_episode(make_recording(seed=2), role="agent", source="scripted")
    shutil.rmtree(store.episode_dir(a.id))  # row without directory
    (store.episode_dir(b.id) / ARRAYS_FILE).unlink()  # incomplete directory
    (store.episodes_dir / "stray").mkdir()  # directory without row
    (store.tmp_dir / "old.lock").write_text("")  # stale lock
    report = store.check(clean=False)
    assert (report.missing_dirs, report.incomplete_dirs, report.orphan_dirs) == ([a.id], [b.id], ["stray"])
    assert len(store.episodes()) == 3  # nothing removed without clean
    report = store.check()
    assert not report.ok and "removed" in report.summary()
    assert [m.id for m in store.episodes()] == [c.id]
    assert sorted(p.name for p in store.episodes_dir.iterdir()) == [c.id]
    assert store.check().ok
    assert list(store.tmp_dir.iterdir()) == []


_KILL_SCRIPT = textwrap.dedent(
    """
    import sys, time
    sys.path[:0] = [{here!r}, {repo!r}]
    from data_fixtures import make_recording
    from studio.data.store import EpisodeStore
    stop_at, n_before = sys.argv[1], int(sys.argv[2])
    def hook(stage):
        if stage == stop_at and store.armed:
            print("stopped", flush=True)
            time.sleep(600)
    store = EpisodeStore(sys.argv[3], stage_hook=hook)
    store.armed = False
    for i in range(n_before):
        store.add_episode(make_recording(seed=i), role="agent", source="scripted")
    store.armed = True
    store.add_episode(make_recording(seed=99), role="agent", source="scripted")
    print("finished", flush=True)
    """
)


def _run_until(tmp_path: Path, stage: str, n_before: int) -> subprocess.Popen:
    script = _KILL_SCRIPT.format(here=str(HERE), repo=str(REPO))
    proc = subprocess.Popen(
        [sys.executable, "-c", script, stage, str(n_before), str(tmp_path)], stdout=subprocess.PIPE, text=True
    )
    line = proc.stdout.readline().strip()
    assert line == "stopped", line
    return proc


@pytest.mark.parametrize(("stage", "leftover"), [("files_written", "temp_dirs"), ("renamed", "orphan_dirs")])
def test_sigkill_mid_episode_leaves_store_consistent(tmp_path, stage, leftover):
    proc = _run_until(tmp_path, stage, n_before=2)
    # While the writer is alive (stopped mid-episode), a concurrent check must not touch its files.
    live = EpisodeStore(tmp_path)
    assert live.check().ok
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    store = EpisodeStore(tmp_path)
    assert len(store.episodes()) == 2  # the killed episode is not visible
    _assert_consistent(store)
    report = store.check()
    assert len(getattr(report, leftover)) == 1, report
    assert store.check().ok
    assert sorted(p.name for p in store.episodes_dir.iterdir()) == sorted(m.id for m in store.episodes())
    assert list(store.tmp_dir.iterdir()) == []


def test_sigkill_at_random_times(tmp_path):
    """Kill a writer of larger episodes at seeded random moments; the store stays loadable every time."""
    script = textwrap.dedent(
        f"""
        import sys
        sys.path[:0] = [{str(HERE)!r}, {str(REPO)!r}]
        from data_fixtures import make_recording
        from studio.data.store import EpisodeStore
        store = EpisodeStore(sys.argv[1])
        print("ready", flush=True)
        for i in range(1000):
            store.add_episode(make_recording(seed=i, size=(240, 320), num_frames=30), role="agent", source="scripted")
        """
    )
    rng = np.random.default_rng(0)
    for _ in range(3):
        proc = subprocess.Popen(
            [sys.executable, "-c", script, str(tmp_path)], stdout=subprocess.PIPE, text=True
        )
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(float(rng.uniform(0.05, 0.4)))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        store = EpisodeStore(tmp_path)
        _assert_consistent(store)
        store.check()
        assert store.check().ok
        assert sorted(p.name for p in store.episodes_dir.iterdir()) == sorted(m.id for m in store.episodes())


def _writer(root: str, offset: int, n: int) -> None:
    store = EpisodeStore(root)
    for i in range(n):
        store.add_episode(
            make_recording(seed=offset + i),
            role="agent",
            source="scripted",
            collect_seed=0,
            collect_index=offset + i,
        )


def _checker(root: str, stop) -> None:
    store = EpisodeStore(root)
    while not stop.is_set():
        report = store.check()
        assert report.ok, report


def test_concurrent_writers_and_checker(tmp_path):
    ctx = mp.get_context("spawn")
    stop = ctx.Event()
    checker = ctx.Process(target=_checker, args=(str(tmp_path), stop))
    writers = [ctx.Process(target=_writer, args=(str(tmp_path), k * 100, 6)) for k in range(2)]
    checker.start()
    for w in writers:
        w.start()
    for w in writers:
        w.join(120)
        assert w.exitcode == 0
    stop.set()
    checker.join(60)
    assert checker.exitcode == 0  # the checker never saw (or removed) an in-flight write
    store = EpisodeStore(tmp_path)
    metas = store.episodes()
    assert sorted(m.collect_index for m in metas) == [*range(6), *range(100, 106)]
    _assert_consistent(store)
    assert store.check().ok


def test_loader_ignores_unfinished_files(tmp_path):
    """A truncated video in tmp/ never reaches a reader."""
    store = EpisodeStore(tmp_path)
    ep = Episode.from_recording(make_recording(), role="agent", source="scripted")
    work = store.tmp_dir / ep.meta.id
    work.mkdir()
    (work / FRAMES_FILE).write_bytes(b"\x00\x00\x00\x18ftypmp42")
    assert store.episodes() == []
    assert store.check().temp_dirs == [ep.meta.id]
