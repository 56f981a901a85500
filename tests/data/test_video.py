"""H.264 writing (browser-playable settings), reading back, probing and rejecting bad files."""

from __future__ import annotations

import numpy as np
import pytest
from data_fixtures import synthetic_frames

from studio.data import video


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


def test_write_read_round_trip(tmp_path):
    frames = synthetic_frames(np.random.default_rng(0), 25, 48, 64)
    path = tmp_path / "a.mp4"
    video.write_video(path, frames, fps=12.5)
    out = video.read_video(path)
    assert out.frames.shape == frames.shape
    assert _psnr(out.frames, frames) > 30
    np.testing.assert_allclose(out.times, np.arange(25) / 12.5, atol=1e-3)
    info = video.probe_video(path)
    assert (info.width, info.height, info.codec) == (64, 48, "h264")
    assert info.fps == pytest.approx(12.5)
    assert info.num_frames == 25


def test_browser_settings(tmp_path):
    """yuv420p H.264 with the index (moov) before the media data, so browsers can stream it."""
    import av

    path = tmp_path / "a.mp4"
    video.write_video(path, synthetic_frames(np.random.default_rng(1), 5, 32, 32), fps=10)
    data = path.read_bytes()
    assert data[4:8] == b"ftyp"
    assert 0 < data.find(b"moov") < data.find(b"mdat")
    with av.open(str(path)) as c:
        assert c.streams.video[0].codec_context.pix_fmt == "yuv420p"


def test_odd_size_padded_and_cropped_back(tmp_path):
    frames = synthetic_frames(np.random.default_rng(2), 4, 31, 45)
    path = tmp_path / "odd.mp4"
    video.write_video(path, frames, fps=5)
    info = video.probe_video(path)
    assert (info.height, info.width) == (32, 46)
    out = video.read_video(path, size=(31, 45))
    assert out.frames.shape == frames.shape
    assert _psnr(out.frames, frames) > 28


def test_time_window_and_frame_limit(tmp_path):
    path = tmp_path / "a.mp4"
    video.write_video(path, synthetic_frames(np.random.default_rng(3), 20, 32, 32), fps=10)
    out = video.read_video(path, start_s=0.5, end_s=1.2)
    np.testing.assert_allclose(out.times, [0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1], atol=1e-3)
    with pytest.raises(video.VideoError, match="more than 5 frames"):
        video.read_video(path, max_frames=5)


@pytest.mark.parametrize(
    ("content", "message"),
    [(b"", "empty"), (b"this is a text file, not a video\n" * 20, "not a readable video")],
)
def test_bad_files_raise_video_error(tmp_path, content, message):
    path = tmp_path / "bad.mp4"
    path.write_bytes(content)
    with pytest.raises(video.VideoError, match=message):
        video.probe_video(path)
    with pytest.raises(video.VideoError, match=message):
        video.read_video(path)


def test_missing_file(tmp_path):
    with pytest.raises(video.VideoError, match="no such file"):
        video.probe_video(tmp_path / "nope.mp4")


def test_write_rejects_bad_frames(tmp_path):
    with pytest.raises(video.VideoError):
        video.write_video(tmp_path / "x.mp4", np.zeros((0, 8, 8, 3), np.uint8), fps=10)
    with pytest.raises(video.VideoError):
        video.write_video(tmp_path / "x.mp4", np.zeros((2, 8, 8), np.uint8), fps=10)
