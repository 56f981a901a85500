"""Human video import: containers, normalisation, trim, and every rejection leaving the store untouched."""

from __future__ import annotations

import argparse
from fractions import Fraction

import av
import numpy as np
import pytest
from data_fixtures import synthetic_frames

from studio.data import video_import
from studio.data.store import EpisodeStore
from studio.data.video_import import ImportLimits, VideoImportError, fit_affine, import_video

TASK = "pick_place/cube->red"


def make_video(path, n=30, size=(90, 160), fps=30, fmt="mp4", codec="libx264", faststart=True, seed=0):
    frames = synthetic_frames(np.random.default_rng(seed), n, *size)
    options = {"movflags": "+faststart"} if faststart and fmt in ("mp4", "mov") else {}
    with av.open(str(path), "w", format=fmt, options=options) as c:
        s = c.add_stream(codec, rate=Fraction(fps))
        s.height, s.width = size
        s.pix_fmt = "yuv420p"
        for f in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return frames


def _assert_nothing_written(store: EpisodeStore) -> None:
    assert store.episodes() == []
    assert list(store.episodes_dir.iterdir()) == []
    assert list(store.tmp_dir.iterdir()) == []


@pytest.fixture
def store(tmp_path):
    return EpisodeStore(tmp_path / "store")


def test_mp4_letterboxed_into_store(tmp_path, store):
    path = tmp_path / "demo.mp4"
    src = make_video(path, n=30, size=(90, 160), fps=10)
    meta = import_video(store, path, TASK)
    assert (meta.embodiment, meta.role, meta.source, meta.num_steps) == ("human", "expert", "upload", 0)
    assert (meta.height, meta.width, meta.num_frames) == (240, 320, 30)
    assert meta.seed is None and meta.success is None
    assert meta.extra["original_name"] == "demo.mp4" and meta.extra["fit"] == "letterbox"
    assert meta.extra["camera_nominal"] and meta.extra["source_size"] == [90, 160]
    ep = store.load(meta.id)
    assert ep.arrays == {} and ep.frame_steps is None
    np.testing.assert_allclose(ep.frame_times, np.arange(30) / 10, atol=1e-3)
    # 16:9 into 4:3: scaled by 2, black bars of 30 rows above and below.
    assert ep.frames[:, :25].max() < 20 and ep.frames[:, -25:].max() < 20
    inner = ep.frames[0, 40:200:2, ::2].astype(float)
    assert np.abs(inner - src[0, 5:85]).mean() < 12
    # The nominal camera follows the letterbox: the image centre stays the principal point.
    assert ep.camera.K[0, 2] == pytest.approx(160) and ep.camera.K[1, 2] == pytest.approx(120)
    assert store.check().ok


def test_crop_fills_frame(tmp_path, store):
    path = tmp_path / "demo.mp4"
    make_video(path, size=(90, 160))
    meta = import_video(store, path, TASK, fit="crop")
    frames = store.load_frames(meta.id)
    assert frames[:, :10].max() > 50 and frames[:, -10:].max() > 50  # no bars
    A = fit_affine((90, 160), (240, 320), "crop")
    assert A[0, 0] == pytest.approx(240 / 90) and A[0, 2] < 0


@pytest.mark.parametrize(
    ("suffix", "fmt", "codec"),
    [("webm", "webm", "libvpx-vp9"), ("mov", "mov", "libx264"), ("avi", "avi", "mpeg4")],
)
def test_other_containers(tmp_path, store, suffix, fmt, codec):
    path = tmp_path / f"demo.{suffix}"
    make_video(path, n=12, size=(120, 160), fps=10, fmt=fmt, codec=codec)
    meta = import_video(store, path, TASK)
    assert meta.num_frames == 12
    assert store.load(meta.id).frames.shape == (12, 240, 320, 3)


def test_trim_and_fps_cap(tmp_path, store):
    path = tmp_path / "demo.mp4"
    make_video(path, n=30, size=(120, 160), fps=10)
    meta = import_video(store, path, TASK, trim=(1.0, 2.5))
    times, _, _ = store.load_arrays(meta.id)
    assert meta.num_frames == 15 and meta.extra["trim"] == [1.0, 2.5]
    np.testing.assert_allclose(times, np.arange(15) / 10, atol=1e-3)
    fast = tmp_path / "fast.mp4"
    make_video(fast, n=60, size=(120, 160), fps=30)
    thinned = import_video(store, fast, TASK)
    assert thinned.num_frames == 30 and thinned.fps == pytest.approx(15, rel=0.05)
    full = import_video(store, fast, TASK, fps_cap=None)
    assert full.num_frames == 60


def _bad_cases(tmp_path):
    cases = {}
    p = tmp_path / "empty.mp4"
    p.write_bytes(b"")
    cases["empty"] = (p, {}, "empty")
    p = tmp_path / "notes.mp4"
    p.write_text("meeting notes, definitely not a video\n" * 50)
    cases["renamed text"] = (p, {}, "not a video file")
    p = tmp_path / "noise.mp4"
    p.write_bytes(np.random.default_rng(0).integers(0, 256, 50_000, dtype=np.uint8).tobytes())
    cases["random bytes"] = (p, {}, "not a video file")
    good = tmp_path / "good.mp4"
    make_video(good, n=60, size=(120, 160), fps=10)
    data = good.read_bytes()
    p = tmp_path / "truncated.mp4"
    p.write_bytes(data[: len(data) // 2])
    cases["truncated"] = (p, {}, "truncated or corrupt")
    slow = tmp_path / "index_at_end.mp4"
    make_video(slow, n=60, size=(120, 160), fps=10, faststart=False)
    p = tmp_path / "truncated_no_index.mp4"
    p.write_bytes(slow.read_bytes()[: len(slow.read_bytes()) // 2])
    cases["truncated, index lost"] = (p, {}, "not a video file")
    p = tmp_path / "short.mp4"
    make_video(p, n=8, size=(120, 160))
    cases["too few frames"] = (p, {}, "only 8 frames")
    cases["short trim"] = (good, {"trim": (1.0, 1.5)}, "only 5 frames between")
    cases["trim past end"] = (good, {"trim": (9.0, 12.0)}, "past the end")
    cases["bad trim"] = (good, {"trim": (2.0, 1.0)}, "trim needs")
    cases["too large"] = (good, {"limits": ImportLimits(max_bytes=1000)}, "over the size limit")
    cases["too long"] = (good, {"limits": ImportLimits(max_duration_s=3.0)}, "over the duration limit")
    cases["unknown task"] = (good, {"known_tasks": ["pick_place/bar->red"]}, "unknown task")
    cases["missing"] = (tmp_path / "nope.mp4", {}, "no such file")
    return cases


BAD_CASES = [
    "empty",
    "renamed text",
    "random bytes",
    "truncated",
    "truncated, index lost",
    "too few frames",
    "short trim",
    "trim past end",
    "bad trim",
    "too large",
    "too long",
    "unknown task",
    "missing",
]


@pytest.mark.parametrize("label", BAD_CASES)
def test_bad_video_rejected_with_nothing_written(tmp_path, store, label):
    cases = _bad_cases(tmp_path)
    assert sorted(cases) == sorted(BAD_CASES)
    path, kwargs, message = cases[label]
    with pytest.raises(VideoImportError, match=message):
        import_video(store, path, TASK, **kwargs)
    _assert_nothing_written(store)


def test_cli_run(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    video_import.add_arguments(parser)
    path = tmp_path / "demo.webm"
    make_video(path, n=12, size=(120, 160), fps=10, fmt="webm", codec="libvpx-vp9")
    root = tmp_path / "cli_store"
    args = parser.parse_args([str(path), "--task", TASK, "--data-dir", str(root), "--trim", "0", "1.1"])
    assert video_import.run(args) == 0
    assert "stored human demonstration" in capsys.readouterr().out
    assert len(EpisodeStore(root).episodes()) == 1
    args = parser.parse_args([str(path), "--task", "pick_place/cube->purple", "--data-dir", str(root)])
    assert video_import.run(args) == 2
    assert "unknown task" in capsys.readouterr().err
    assert len(EpisodeStore(root).episodes()) == 1
