"""`studio export-video`: a stored episode as an MP4 at any size and rate, its timing kept; and back in through
`studio import-video` as a human demonstration."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from data_fixtures import make_recording

from studio.cli import main
from studio.data import video
from studio.data.store import EpisodeStore
from studio.data.video_export import (
    VideoExportError,
    episode_duration,
    export_episode_video,
    resample_indices,
)

TASK = "pick_place/cube->red"


@pytest.fixture
def stored(tmp_path):
    """A store with one synthetic episode (20 frames over 60 control steps of 0.02 s, 48×64)."""
    root = tmp_path / "data"
    with EpisodeStore(root) as store:
        meta = store.add_episode(make_recording(task=TASK, robot="sawyer"), role="expert", source="scripted")
    return root, meta


def test_resample_picks_the_frame_in_force_at_each_output_time():
    times = np.array([0.0, 0.12, 0.26, 0.38])  # irregular, as a recording's frames are
    # 0.5 s at 10 fps: outputs at 0, .1, .2, .3, .4 s show frames 0, 0, 1, 2, 3
    assert resample_indices(times, 0.5, 10.0).tolist() == [0, 0, 1, 2, 3]
    # faster than the source: each source frame repeated for as long as it lasts
    assert resample_indices(times, 0.5, 50.0).tolist() == [0] * 6 + [1] * 7 + [2] * 6 + [3] * 6
    assert resample_indices(times + 5.0, 0.5, 10.0).tolist() == [0, 0, 1, 2, 3]  # relative to the first frame
    assert resample_indices(np.zeros(1), 0.01, 10.0).tolist() == [0]  # never empty


def test_export_has_the_requested_size_rate_and_the_episodes_duration(stored, tmp_path):
    root, meta = stored
    out = tmp_path / "demo.mp4"
    with EpisodeStore(root) as store:
        done = export_episode_video(store, meta.id, out, size=(36, 48), fps=24.0)
        times, _, _ = store.load_arrays(meta.id)
        src = store.load_frames(meta.id)
    duration = episode_duration(times, meta.fps)
    info = video.probe_video(out)
    assert (info.height, info.width, info.codec) == (36, 48, "h264")
    assert info.fps == pytest.approx(24.0)
    assert done.num_frames == round(duration * 24) and info.num_frames == done.num_frames
    assert info.duration_s == pytest.approx(duration, abs=1.5 / 24)
    # Each written frame is the source frame in force at its time (resized): the closest of all source frames.
    got = video.read_video(out).frames.astype(float)
    small = np.stack([cv2.resize(f, (48, 36), interpolation=cv2.INTER_AREA) for f in src]).astype(float)
    closest = [int(np.abs(small - g).mean(axis=(1, 2, 3)).argmin()) for g in got]
    assert closest == resample_indices(times, duration, 24.0).tolist()


def test_defaults_keep_the_episodes_size_and_rate(stored, tmp_path):
    root, meta = stored
    out = tmp_path / "same.mp4"
    with EpisodeStore(root) as store:
        export_episode_video(store, meta.id, out)
    info = video.probe_video(out)
    assert (info.height, info.width) == (meta.height, meta.width)
    assert info.fps == pytest.approx(meta.fps, rel=1e-3)


def test_cli_exports_and_rejects_bad_input_with_one_line(stored, tmp_path, capsys):
    root, meta = stored
    out = tmp_path / "cli.mp4"
    args = ["--data-dir", str(root)]
    assert main(["export-video", meta.id, str(out), "--size", "180", "240", "--fps", "24", *args]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    assert (video.probe_video(out).height, video.probe_video(out).width) == (180, 240)

    bad = {
        "unknown episode": ["export-video", "no-such-episode", str(tmp_path / "x.mp4"), *args],
        "odd size": ["export-video", meta.id, str(tmp_path / "x.mp4"), "--size", "181", "240", *args],
        "zero size": ["export-video", meta.id, str(tmp_path / "x.mp4"), "--size", "0", "240", *args],
        "negative size": ["export-video", meta.id, str(tmp_path / "x.mp4"), "--size", "-4", "240", *args],
        "zero fps": ["export-video", meta.id, str(tmp_path / "x.mp4"), "--fps", "0", *args],
        "negative fps": ["export-video", meta.id, str(tmp_path / "x.mp4"), "--fps", "-5", *args],
        "no store": ["export-video", meta.id, str(tmp_path / "x.mp4"), "--data-dir", str(tmp_path / "none")],
        "no directory": ["export-video", meta.id, str(tmp_path / "missing" / "x.mp4"), *args],
    }
    for label, argv in bad.items():
        assert main(argv) == 2, label
        err = capsys.readouterr().err.strip()
        assert err.startswith("studio export-video: ") and "\n" not in err, (label, err)
        assert not (tmp_path / "x.mp4").exists(), label
    assert not (tmp_path / "none").exists(), "a missing store is not created"
    with pytest.raises(SystemExit):  # not a number: argparse's own usage error (exit 2)
        main(["export-video", meta.id, str(tmp_path / "x.mp4"), "--size", "big", "240", *args])
    with EpisodeStore(root) as store, pytest.raises(VideoExportError, match="no episode 'nope'"):
        export_episode_video(store, "nope", tmp_path / "x.mp4")


def test_a_hand_demonstration_exported_at_another_size_and_rate_imports_as_a_human_demonstration(
    tmp_path, capsys
):
    """The loop of the upload path: the simulated hand's episode → an MP4 at 180×240, 24 fps (the simulator
    records 240×320 at about 8 fps) → `studio import-video` → an expert `human` episode of the same task whose
    frames are the hand's."""
    from studio.sim.experts import record_expert

    task = "push/blue-backward"
    root = tmp_path / "data"
    rec = record_expert("push", "hand", task, 1003, (240, 320), 20)
    assert rec.success
    with EpisodeStore(root) as store:
        hand = store.add_episode(rec, role="expert", source="scripted")
    assert (hand.embodiment, hand.role) == ("human", "expert")
    out = tmp_path / "hand.mp4"
    data = ["--data-dir", str(root)]
    assert main(["export-video", hand.id, str(out), "--size", "180", "240", "--fps", "24", *data]) == 0
    info = video.probe_video(out)
    assert (info.height, info.width) == (180, 240) and info.fps == pytest.approx(24.0)

    assert main(["import-video", str(out), "--task", task, *data]) == 0
    assert "stored human demonstration" in capsys.readouterr().out
    with EpisodeStore(root) as store:
        (up,) = store.episodes(source="upload")
        original = store.load(hand.id)
        imported = store.load(up.id)
    assert (up.task, up.embodiment, up.role, up.scene) == (task, "human", "expert", "push")
    assert up.extra["source_size"] == [180, 240] and up.extra["source_fps"] == pytest.approx(24.0)
    assert (up.height, up.width) == (240, 320)  # 3:4 like the simulator's: scaled, no bars
    # Same timing: the import (thinned to 15 fps) spans the hand's episode.
    span = original.frame_times[-1] - original.frame_times[0]
    assert imported.frame_times[-1] == pytest.approx(span, abs=0.15)
    # Same pictures: the first and last frames, side by side at the exported size.
    for i in (0, -1):
        a = cv2.resize(original.frames[i], (240, 180), interpolation=cv2.INTER_AREA).astype(float)
        b = cv2.resize(imported.frames[i], (240, 180), interpolation=cv2.INTER_AREA).astype(float)
        assert np.abs(a - b).mean() < 6.0, i
    # ... and not just any frame of the scene: the hand moved between first and last.
    first, last = original.frames[0].astype(float), original.frames[-1].astype(float)
    assert np.abs(first - last).mean() > 1.0
