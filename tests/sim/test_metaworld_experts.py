"""Meta-World scripted experts: metaworld's policies succeed through our stepping, truncated after success."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest
from metaworld_cases import TEST_AND_TWINS

from studio.data.store import EpisodeStore
from studio.sim.metaworld_env import MetaWorldEnv
from studio.sim.metaworld_experts import AFTER_SUCCESS, record_expert

SIZE = (48, 48)


@pytest.fixture(scope="module")
def env():
    e = MetaWorldEnv(image_size=SIZE)
    yield e
    e.close()


@pytest.mark.parametrize("task", TEST_AND_TWINS)
def test_expert_succeeds_and_stops_after_success(env, task):
    rec = record_expert("metaworld", "sawyer", task, 5, image_size=SIZE, min_frames=20, env=env)
    assert rec.success and rec.task == task and rec.robot == "sawyer" and rec.scene == "metaworld"
    assert rec.frames.shape == (20, *SIZE, 3) and rec.frame_steps[-1] == rec.num_steps - 1
    assert rec.camera.width == SIZE[1] and rec.control_dt == env.control_dt
    # One row at reset, one per tick; the episode ends AFTER_SUCCESS ticks after the first success.
    ticks = rec.num_steps - 1
    assert env.steps == ticks and env.success()
    assert np.all(np.diff(rec.arrays["time"]) > 0)
    g = rec.arrays["gripper_cmd"]
    assert np.all((g >= 0) & (g <= 1))


def test_recording_is_deterministic(env):
    a = record_expert("metaworld", "sawyer", "metaworld/window-open-v3", 3, image_size=SIZE, env=env)
    record_expert("metaworld", "sawyer", "metaworld/door-lock-v3", 3, image_size=SIZE, env=env)
    b = record_expert("metaworld", "sawyer", "metaworld/window-open-v3", 3, image_size=SIZE, env=env)
    assert a.num_steps == b.num_steps and np.array_equal(a.frames, b.frames)
    for key in a.arrays:
        assert np.array_equal(a.arrays[key], b.arrays[key]), key


def test_truncation_point(env):
    rec = record_expert("metaworld", "sawyer", "metaworld/reach-v3", 2, image_size=SIZE, env=env)
    env.reset("metaworld/reach-v3", 2)
    # Replay the recorded hand path's success signal: it first came on AFTER_SUCCESS ticks before the end.
    from studio.sim.metaworld_experts import run_expert

    first = run_expert(env, after_success=0)
    assert first is not None and rec.num_steps - 1 == first + AFTER_SUCCESS


def test_bad_arguments(env):
    with pytest.raises(ValueError, match="scene 'metaworld'"):
        record_expert("push", "sawyer", "metaworld/reach-v3", 0, image_size=SIZE, env=env)
    with pytest.raises(ValueError, match="renders"):
        record_expert("metaworld", "sawyer", "metaworld/reach-v3", 0, image_size=(32, 32), env=env)


def test_episode_round_trips_through_the_store(env, tmp_path):
    rec = record_expert("metaworld", "sawyer", "metaworld/door-unlock-v3", 9, image_size=SIZE, env=env)
    with EpisodeStore(tmp_path) as store:
        meta = store.add_episode(rec, role="expert", source="scripted")
        ep = store.load(meta.id)
        assert ep.meta.task == "metaworld/door-unlock-v3" and ep.meta.scene == "metaworld"
        assert ep.meta.role == "expert" and ep.meta.embodiment == "sawyer" and ep.meta.success
        assert tuple(ep.meta.object_names) == ("object0",)
        for key, value in rec.arrays.items():
            assert np.array_equal(ep.arrays[key], value), key
        frames = store.load_frames(meta.id)
        assert frames.shape == rec.frames.shape
        assert np.abs(frames.astype(int) - rec.frames.astype(int)).mean() < 8  # video is lossy
        cam = store.load_camera(meta.id)
        assert np.allclose(cam.K, rec.camera.K) and np.allclose(cam.T_world_cam, rec.camera.T_world_cam)
    with EpisodeStore(tmp_path) as store:  # reopened: the catalog kept it
        assert [m.id for m in store.episodes(task="metaworld/door-unlock-v3", role="expert")] == [meta.id]
