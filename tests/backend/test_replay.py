"""Replaying a stored episode: forward kinematics of its arrays reproduce the recorded end-effector path."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from studio.backend.replay import EpisodeReplay
from studio.data.store import EpisodeStore
from studio.sim.experts import record_expert


def test_replay_poses_follow_the_recording(tmp_path):
    rec = record_expert("pick_place", "panda", "pick_place/cube->red", 1, (120, 160), 20)
    with EpisodeStore(tmp_path) as store:
        meta = store.add_episode(rec, role="agent", source="scripted")
        replay = EpisodeReplay(store, meta.id)
    assert replay.num_steps == rec.num_steps and len(replay.frame_steps) == len(rec.frames)
    names = replay.geometry.body_names
    cube = names.index("obj_cube")
    for t in (0, replay.num_steps // 2, replay.num_steps - 1):
        np.testing.assert_allclose(
            replay.poses_at(t)[cube, :3], rec.arrays["object_poses"][t, 0, :3], atol=1e-5
        )
    # The grasp site, carried by its body's replayed pose, is where the recording says the end effector was.
    from studio.sim.env import SimEnv

    with SimEnv("pick_place", "panda") as env:
        site = env.model.site(env.robot_info.grasp_site).id
        body, offset = int(env.model.site_bodyid[site]), env.model.site_pos[site].copy()
    for t in range(0, replay.num_steps, 7):
        pose = replay.poses_at(t)[body].astype(np.float64)
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, pose[3:])
        site_world = pose[:3] + rot.reshape(3, 3) @ offset
        np.testing.assert_allclose(site_world, rec.arrays["ee_pos_world"][t], atol=2e-3)
    assert replay.poses_at(10_000).shape == (len(names), 7)  # clamped to the last step


def test_replay_refuses_an_episode_without_robot_state(tmp_path):
    from studio.data.episode import Episode, EpisodeMeta
    from studio.sim.camera import CameraModel

    cam = CameraModel(32, 24, np.array([[30.0, 0, 16], [0, 30, 12], [0, 0, 1]]), np.eye(4))
    meta = EpisodeMeta(
        id="20250101-000000-000-abcdef",
        task="pick_place/cube->red",
        scene="pick_place",
        embodiment="human",
        role="expert",
        source="upload",
        seed=None,
        success=None,
        created=0.0,
        num_frames=12,
        num_steps=0,
        height=24,
        width=32,
        fps=10.0,
    )
    ep = Episode(meta, cam, np.zeros((12, 24, 32, 3), np.uint8), np.arange(12) / 10.0)
    with EpisodeStore(tmp_path) as store:
        store.add_episode(ep)
        with pytest.raises(ValueError, match="no robot state"):
            EpisodeReplay(store, meta.id)


def test_replay_of_a_hand_demonstration_moves_the_hand(tmp_path):
    rec = record_expert("pick_place", "hand", "pick_place/cube->red", 2, (60, 80), 20)
    with EpisodeStore(tmp_path) as store:
        meta = store.add_episode(rec, role="expert", source="scripted")
        assert meta.embodiment == "human"
        replay = EpisodeReplay(store, meta.id)
    hand = replay.geometry.body_names.index("hand")
    for t in (0, replay.num_steps // 2, replay.num_steps - 1):
        # The hand body's origin is its grasp site (recorded one physics step apart, as for the arms).
        np.testing.assert_allclose(replay.poses_at(t)[hand, :3], rec.arrays["ee_pos_world"][t], atol=2e-3)
