"""Forking a stored rollout: its physics states are kept, and ticks 0 … k restore the rollout exactly."""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np
import pytest

from studio.data.forks import STATES_FILE, CannotFork, fork_source, read_states
from studio.data.store import EpisodeStore
from studio.eval.oracle import OraclePlanner
from studio.eval.rollout import run_rollout, store_rollout
from studio.sim.env import SimEnv
from studio.sim.physics_state import STATE_SPEC, state_size

TASK = "pick_place/bar->blue"


@pytest.fixture(scope="module")
def stored(tmp_path_factory, miss_planner):
    root = tmp_path_factory.mktemp("forks")
    env = SimEnv("pick_place", "panda")
    frames = np.zeros((10, 240, 320, 3), np.uint8)
    try:
        failed = run_rollout(env, miss_planner, frames, TASK, 5)
        solved = run_rollout(env, OraclePlanner(env), frames, TASK, 5)
    finally:
        env.close()
    with EpisodeStore(root) as store:
        a = store_rollout(store, failed, expert_episode_id=None, checkpoint_id=None)
        b = store_rollout(store, solved, expert_episode_id=None, checkpoint_id=None, keep=False)
    return root, failed, a.id, b.id


def test_a_rollout_keeps_the_physics_state_of_every_tick(stored):
    root, failed, rid, _ = stored
    with EpisodeStore(root) as store:
        record = store.catalog.get_rollout(rid)
        states = read_states(record.path)
        _, _, arrays = store.load_arrays(record.episode_id)
    assert not failed.success and failed.failure_stage == "reach"
    assert states is not None and states.dtype == np.float64
    assert len(states) == len(arrays["time"]) == failed.recording.num_steps
    np.testing.assert_array_equal(states, failed.states)
    np.testing.assert_allclose(states[:, 0], arrays["time"])  # the state's first number is the time


def test_fork_source_restores_the_rollout_at_the_chosen_tick(stored):
    root, failed, rid, _ = stored
    k = failed.recording.num_steps // 2
    with EpisodeStore(root) as store:
        src = fork_source(store, rid, k)
    assert (src.scene, src.robot, src.task, src.seed, src.step) == ("pick_place", "panda", TASK, 5, k)
    assert len(src.states) == k + 1 and all(len(a) == k + 1 for a in src.arrays.values())
    assert src.origin == {"rollout": rid, "step": k, "episode": src.episode_id}
    assert src.control_dt == pytest.approx(failed.recording.control_dt)
    env = SimEnv(src.scene, src.robot, control_dt=src.control_dt)
    try:
        env.restore(src.task, src.seed, src.states, src.gripper)
        now = np.empty(state_size(env.model))
        mujoco.mj_getState(env.model, env.data, now, STATE_SPEC)
        np.testing.assert_array_equal(now, failed.states[k])
        # A recorded row reads positions mj_step computed before its last integration: one 2 ms substep behind.
        np.testing.assert_allclose(env.ee_pos, src.arrays["ee_pos_world"][-1], atol=1e-4)
    finally:
        env.close()


def test_what_cannot_be_forked_says_why(stored, tmp_path):
    root, failed, rid, unkept = stored
    with EpisodeStore(root) as store:
        with pytest.raises(CannotFork, match="no rollout"):
            fork_source(store, "r-nope", 0)
        with pytest.raises(CannotFork, match="without its recording"):
            fork_source(store, unkept, 0)
        n = failed.recording.num_steps
        with pytest.raises(CannotFork, match=f"ticks 0 … {n - 1}; cannot fork at tick {n}"):
            fork_source(store, rid, n)
        path = store.catalog.get_rollout(rid).path
    moved = os.path.join(path, STATES_FILE)
    os.replace(moved, tmp_path / "kept.npz")
    try:
        with EpisodeStore(root) as store, pytest.raises(CannotFork, match="without its physics states"):
            fork_source(store, rid, 0)
    finally:
        os.replace(tmp_path / "kept.npz", moved)
