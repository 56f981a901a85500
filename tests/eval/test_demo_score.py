"""The demonstration score: its arithmetic, its threshold rule, its file, and the shipped policies' calibrations
against real held-out demonstrations and meaningless videos."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from studio.data.paths import SHIPPED_POLICY_DIR
from studio.eval import demo_score as ds

SHIPPED = sorted(p for p in SHIPPED_POLICY_DIR.glob("*.pt") if not p.name.endswith(".decoder.pt"))


def test_nearest_distances_are_root_mean_square_distances_to_the_closest_reference_row():
    ref = np.array([[0.0, 0.0], [3.0, 4.0]])
    got = ds.nearest_distances(np.array([[0.0, 0.0], [3.0, 3.0], [10.0, 0.0]]), ref)
    want = np.array([0.0, 1.0, np.hypot(7.0, 4.0)]) / np.sqrt(2)
    assert np.allclose(got, want)


def test_the_threshold_sits_between_held_out_and_synthetic_scores_or_just_above_the_held_out_ones():
    assert ds.choose_threshold([0.2, 0.5], [2.0, 8.0]) == pytest.approx(1.0)  # sqrt(0.5 · 2.0)
    assert ds.choose_threshold([0.2, 0.5], [0.4, 8.0]) == pytest.approx(
        0.55
    )  # overlap: no held-out one warned
    assert ds.choose_threshold([0.5], []) == pytest.approx(0.55)
    with pytest.raises(ValueError, match="held-out"):
        ds.choose_threshold([], [1.0])


def test_synthetic_videos_are_blobs_noise_and_flat_colours_of_the_asked_size():
    videos = ds.synthetic_videos((48, 64), seed=3)
    kinds = [k for k, _ in videos]
    assert kinds.count("blob") == 8 and kinds.count("noise") == 3 and kinds.count("flat") == 3
    assert all(v.shape == (24, 48, 64, 3) and v.dtype == np.uint8 for _, v in videos)
    blob = videos[0][1]
    assert len(np.unique(blob[0].reshape(-1, 3), axis=0)) == 2 and not np.array_equal(blob[0], blob[-1])
    assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(videos, ds.synthetic_videos((48, 64), seed=3)))


def test_sampled_takes_evenly_spaced_frames_first_and_last_kept():
    frames = np.arange(25)[:, None, None, None] * np.ones((1, 2, 2, 3), np.uint8)
    assert ds.sampled(frames, 5)[:, 0, 0, 0].tolist() == [0, 6, 12, 18, 24]
    with pytest.raises(ValueError, match="T, H, W, 3"):
        ds.sampled(np.zeros((4, 4, 3), np.uint8), 5)


@pytest.fixture(scope="module")
def tiny_planner(tmp_path_factory):
    from studio.model.planner import Planner

    from .tiny_checkpoint import write_tiny_checkpoint

    path = write_tiny_checkpoint(tmp_path_factory.mktemp("tiny") / "run" / "best.pt")
    return path, Planner.load(path)


def scene_like(rng, n: int = 12) -> np.ndarray:
    """A 'scene' video: a grey gradient table with a small dark square moving a little."""
    h, w = 48, 64
    base = np.linspace(90, 170, w)[None, :, None] * np.ones((h, 1, 3))
    out = np.empty((n, h, w, 3), np.uint8)
    y, x = rng.integers(10, 30, 2)
    for t in range(n):
        frame = base.copy()
        frame[y : y + 8, x + t : x + t + 8] = 40
        out[t] = np.clip(frame + rng.normal(0, 2, frame.shape), 0, 255)
    return out


def test_calibrate_sets_the_threshold_from_held_out_videos_and_saves_it_beside_the_checkpoint(tiny_planner):
    path, planner = tiny_planner
    rng = np.random.default_rng(0)
    reference = [scene_like(rng) for _ in range(6)]
    held_out = [scene_like(rng) for _ in range(4)]
    cal = ds.calibrate(planner.model, reference, held_out, checkpoint_stamp=ds.checkpoint_stamp(path))
    assert cal.source == "held-out demonstrations" and len(cal.positives) == 4 and len(cal.negatives) == 14
    assert cal.threshold == pytest.approx(ds.choose_threshold(cal.positives, cal.negatives))
    assert cal.reference.shape[0] == 6 * planner.cfg.n_expert_frames
    assert all(ds.score_demonstration(planner.model, cal, v).familiar for v in held_out)
    file = ds.calibration_path(path)
    assert file == path.with_name("best.demo-score.npz")
    cal.save(file)
    back = ds.Calibration.load(file)
    assert back.threshold == cal.threshold and back.negative_kinds == cal.negative_kinds
    assert back.checkpoint_stamp == ds.checkpoint_stamp(path)
    video = held_out[0]
    assert ds.score_demonstration(planner.model, back, video).score == pytest.approx(
        ds.score_demonstration(planner.model, cal, video).score, rel=1e-2
    )  # the reference is stored in float16
    assert (
        ds.load_or_calibrate(planner.model, path).threshold == back.threshold
    )  # the file is current: no store


def test_without_held_out_videos_each_training_video_is_scored_against_the_others(tiny_planner):
    _, planner = tiny_planner
    rng = np.random.default_rng(1)
    cal = ds.calibrate(planner.model, [scene_like(rng) for _ in range(5)], [])
    assert cal.source.startswith("training demonstrations") and len(cal.positives) == 5
    with pytest.raises(ValueError, match="at least two"):
        ds.calibrate(planner.model, [scene_like(rng)], [])


def test_a_stale_or_foreign_calibration_file_is_not_used(tiny_planner, tmp_path):
    path, planner = tiny_planner
    copy = tmp_path / "other.pt"
    shutil.copy(path, copy)
    ds.calibration_path(copy).write_bytes(b"not an npz")
    with pytest.raises(ValueError, match="no demonstration-score calibration"):
        ds.load_or_calibrate(planner.model, copy)
    with pytest.raises(ValueError, match="not a demonstration-score file"):
        ds.Calibration.load(ds.calibration_path(copy))
    rng = np.random.default_rng(2)
    ds.calibrate(
        planner.model, [scene_like(rng) for _ in range(3)], [], checkpoint_stamp="someone else's"
    ).save(ds.calibration_path(copy))
    with pytest.raises(ValueError, match="no demonstration-score calibration"):
        ds.load_or_calibrate(planner.model, copy)  # made for other bytes, and no store to make it again


def test_a_checkpoint_without_tasks_has_no_score_and_says_why(tiny_planner, tmp_path):
    from studio.data.store import EpisodeStore

    path, planner = tiny_planner
    copy = tmp_path / "untitled.pt"
    shutil.copy(path, copy)
    with EpisodeStore(tmp_path / "data") as store:
        got = ds.worker_score(planner.model, str(copy), "ep-1", scene_like(np.random.default_rng(3)), store)
    assert "names no tasks" in got["unavailable"]


# ---------------------------------------------------------------------------------------------- shipped
@pytest.mark.parametrize("policy", SHIPPED, ids=lambda p: p.stem)
def test_every_shipped_policy_carries_a_current_calibration_that_separates_held_out_from_synthetic(policy):
    cal = ds.Calibration.load(ds.calibration_path(policy))
    assert cal.checkpoint_stamp == ds.checkpoint_stamp(policy), "calibrated on these very bytes"
    assert cal.source == "held-out demonstrations" and len(cal.positives) >= 8
    assert cal.positives.max() < cal.threshold < cal.negatives.min()
    assert sorted(set(cal.negative_kinds)) == ["blob", "flat", "noise"]


@pytest.fixture(scope="module")
def pick_place_policy():
    from studio.model.planner import Planner

    path = SHIPPED_POLICY_DIR / "pick-place-cpu.pt"
    planner = Planner.load(path)
    return path, planner, ds.load_or_calibrate(planner.model, path)


def test_a_fresh_held_out_demonstration_passes_and_a_blob_video_is_flagged(pick_place_policy):
    """Demonstrations the calibration never saw: a scripted Sawyer demonstration of a held-out task on a new seed,
    rendered at the simulator's size, and a blob video at a phone's size (another aspect ratio)."""
    from studio.data.collect import DEFAULT_RECORDER, MIN_FRAMES, load_recorder
    from studio.sim.env import default_image_size

    _, planner, cal = pick_place_policy
    record = load_recorder(DEFAULT_RECORDER)
    demo = record(
        "pick_place", "sawyer", "pick_place/bar->yellow", 4242, default_image_size("pick_place"), MIN_FRAMES
    )
    assert demo.success
    real = ds.score_demonstration(planner.model, cal, demo.frames)
    assert real.familiar and real.score < 0.8 * cal.threshold, real
    blob = np.full((72, 360, 480, 3), (235, 20, 200), np.uint8)
    yy, xx = np.mgrid[0:360, 0:480]
    for t in range(72):
        blob[t][(yy - 150) ** 2 + (xx - 100 - 4 * t) ** 2 < 60**2] = (30, 200, 60)
    flagged = ds.score_demonstration(planner.model, cal, blob)
    assert not flagged.familiar and flagged.score > 1.5 * cal.threshold, flagged
    assert flagged.to_dict() == {
        "score": flagged.score,
        "threshold": cal.threshold,
        "familiar": False,
        "calibration": "held-out demonstrations",
    }


def test_the_calibration_command_prints_its_figures(tmp_path, capsys):
    """``python -m studio.eval.demo_score`` on a store with a policy's training and held-out demonstrations."""
    from studio.data.collect import DEFAULT_RECORDER, MIN_FRAMES, load_recorder
    from studio.data.store import EpisodeStore
    from studio.sim.env import default_image_size

    record = load_recorder(DEFAULT_RECORDER)
    with EpisodeStore(tmp_path / "data") as store:
        for task, seeds in (
            ("push/red-forward", (1, 2)),
            ("push/blue-forward", (3,)),
            ("push/blue-backward", (4,)),
        ):
            for seed in seeds:
                rec = record("push", "sawyer", task, seed, default_image_size("push"), MIN_FRAMES)
                assert rec.success
                store.add_episode(rec, role="expert", source="scripted")
    out = tmp_path / "push.demo-score.npz"
    code = ds.main(
        [str(SHIPPED_POLICY_DIR / "push-cpu.pt"), "--data-dir", str(tmp_path / "data"), "--out", str(out)]
    )
    assert code == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["reference_demonstrations"] == 3 and figures["held_out"] == 1
    assert figures["source"] == "held-out demonstrations" and Path(figures["out"]) == out
    assert ds.Calibration.load(out).threshold == pytest.approx(figures["threshold"])


def test_the_demonstrations_calibrated_on_are_chosen_by_what_they_are_not_by_when_they_were_stored(
    tiny_planner, tmp_path, monkeypatch
):
    import torch

    from studio.data.episode import EpisodeMeta

    path, _ = tiny_planner
    ckpt = torch.load(path, weights_only=False)
    ckpt["tasks"] = ["pick_place/cube->red"]
    torch.save(ckpt, tmp_path / "named.pt")

    class Store:
        """Four scripted demonstrations of each task, stored in the reverse of their collection slots."""

        def episodes(self, task, role, embodiment=None):
            return [
                EpisodeMeta(
                    id=f"{9 - i}-{task}",
                    task=task,
                    role=role,
                    embodiment="sawyer",
                    scene="pick_place",
                    source="scripted",
                    seed=100 + i,
                    success=True,
                    created=1e9 - i,
                    num_frames=12,
                    num_steps=40,
                    height=48,
                    width=64,
                    fps=10.0,
                    collect_seed=0,
                    collect_index=i,
                )
                for i in range(4)
            ]

        def load_frames(self, episode_id):
            return episode_id

    monkeypatch.setattr(ds, "REFERENCE_PER_TASK", 2)
    monkeypatch.setattr(ds, "HELD_OUT_PER_TASK", 1)
    reference, held_out = ds.store_demonstrations(Store(), tmp_path / "named.pt")
    assert reference == ["9-pick_place/cube->red", "8-pick_place/cube->red"]  # slots 0 and 1
    assert held_out and all(v.startswith("9-") for v in held_out)
