"""Episode metadata validation, conversion from recordings, and the three files of an episode."""

from __future__ import annotations

import numpy as np
import pytest
from data_fixtures import make_recording

from studio.data.episode import (
    Episode,
    EpisodeError,
    EpisodeMeta,
    new_episode_id,
    read_episode,
    write_episode_files,
)
from studio.sim.recording import ARRAY_FIELDS


def test_from_recording_fills_metadata():
    rec = make_recording(robot="sawyer", seed=7, steps=40, num_frames=10)
    ep = Episode.from_recording(rec, role="expert", source="scripted", collect_seed=3, collect_index=5)
    m = ep.meta
    assert (m.task, m.scene, m.embodiment, m.role, m.source, m.seed, m.success) == (
        "pick_place/cube->red",
        "pick_place",
        "sawyer",
        "expert",
        "scripted",
        7,
        True,
    )
    assert (m.num_frames, m.num_steps, m.height, m.width) == (10, 40, 48, 64)
    assert (m.collect_seed, m.collect_index) == (3, 5)
    np.testing.assert_allclose(ep.frame_times, rec.arrays["time"][rec.frame_steps])
    # frames every 39/9 steps of 0.02 s
    assert m.fps == pytest.approx(1 / (0.02 * np.median(np.diff(rec.frame_steps))))


def test_ids_unique_and_sortable():
    ids = [new_episode_id(1000.0 + i) for i in range(5)]
    assert len(set(ids)) == 5
    assert ids == sorted(ids)


@pytest.mark.parametrize(
    "changes",
    [
        {"embodiment": "ur5"},
        {"role": "teacher"},
        {"source": "web"},
        {"embodiment": "human", "role": "agent"},
        {"task": "no-scene"},
        {"collect_seed": 1},
    ],
)
def test_invalid_metadata_rejected(changes):
    base = Episode.from_recording(make_recording(), role="agent", source="scripted").meta.to_dict()
    with pytest.raises(EpisodeError):
        EpisodeMeta.from_dict({**base, **changes})


def test_inconsistent_arrays_rejected():
    ep = Episode.from_recording(make_recording(), role="agent", source="scripted")
    arrays = dict(ep.arrays)
    arrays["qpos"] = arrays["qpos"][:-1]
    with pytest.raises(EpisodeError, match="qpos"):
        Episode(ep.meta, ep.camera, ep.frames, ep.frame_times, ep.frame_steps, arrays)
    with pytest.raises(EpisodeError, match="frames"):
        Episode(ep.meta, ep.camera, ep.frames[:-1], ep.frame_times, ep.frame_steps, ep.arrays)


def test_files_round_trip(tmp_path):
    rec = make_recording(seed=3)
    ep = Episode.from_recording(rec, role="agent", source="teleop", extra={"note": "x"})
    write_episode_files(ep, tmp_path)
    back = read_episode(tmp_path)
    assert back.meta == ep.meta
    np.testing.assert_array_equal(back.camera.K, ep.camera.K)
    np.testing.assert_array_equal(back.camera.T_world_cam, ep.camera.T_world_cam)
    np.testing.assert_array_equal(back.frame_steps, ep.frame_steps)
    np.testing.assert_array_equal(back.frame_times, ep.frame_times)
    for k in ARRAY_FIELDS:
        np.testing.assert_array_equal(back.arrays[k], rec.arrays[k])
        assert back.arrays[k].dtype == rec.arrays[k].dtype
    assert np.abs(back.frames.astype(int) - rec.frames).mean() < 4
    rec2 = back.to_recording()
    assert (rec2.robot, rec2.task, rec2.seed, rec2.object_names) == (
        "panda",
        rec.task,
        3,
        ["cube", "cylinder"],
    )


def test_hand_recordings_are_human_episodes_with_robot_state():
    ep = Episode.from_recording(make_recording(robot="hand", seed=4), role="expert", source="scripted")
    assert (ep.meta.embodiment, ep.meta.role, ep.meta.seed) == ("human", "expert", 4)
    assert ep.meta.has_arrays
    assert ep.to_recording().robot == "hand"  # the simulated hand replays it
    with pytest.raises(EpisodeError, match="human"):
        Episode.from_recording(make_recording(robot="hand"), role="agent", source="scripted")
