"""Forking a stored rollout into a teleop session on a real sim worker, and drafts that survive the worker.

A failed rollout is forked at a tick: the worker restores it, the user drives on and saves an episode whose
first ticks are the rollout's, linked to it. The worker is killed mid-fork: the draft the client kept
holds the recording, another worker continues it, and the saved episode has every tick.
"""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest

from studio.backend import bus
from studio.backend import messages as msg
from studio.backend.forking import DraftKeeper, fork_rollout, resume_draft
from studio.backend.hub import Hub
from studio.backend.teleop_client import TeleopClient
from studio.data.drafts import RecordingDrafts
from studio.data.forks import STATES_FILE, read_states
from studio.eval.rollout import run_rollout, store_rollout
from studio.sim.env import SimEnv

from .conftest import Workers, wait_gone, wait_worker

pytestmark = pytest.mark.timeout(240)

TASK = "pick_place/bar->blue"


@pytest.fixture(scope="module")
def site(tmp_path_factory, miss_planner):
    """A hub whose store holds one failed rollout, and a factory of sim workers sharing its data directory."""
    tmp = tmp_path_factory.mktemp("forking")
    port = bus.free_loopback_port()
    hub = Hub(bus.BusConfig.hub([bus.loopback_endpoint(port)]), data_dir=tmp / "data")
    env = SimEnv("pick_place", "panda")
    try:
        out = run_rollout(env, miss_planner, np.zeros((10, 240, 320, 3), np.uint8), TASK, 7)
    finally:
        env.close()
    record = store_rollout(hub.store, out, expert_episode_id=None, checkpoint_id=None)
    workers = Workers(bus.loopback_endpoint(port), tmp)
    try:
        yield hub, workers, record, out
    finally:
        workers.close()
        hub.close()


def _start_worker(site, name: str):
    hub, workers, _, _ = site
    proc = workers.start("sim", name, "--data-dir", str(hub.data_dir), handlers=())
    wait_worker(hub.directory, name)
    return proc


def _drive(client: TeleopClient, target, gripper: float, ticks: int) -> msg.PoseFrame:
    frame = None
    for _ in range(ticks):
        frame = client.wait_ack(client.set_target(target, gripper), timeout=3.0)
        assert frame is not None, "command not acknowledged"
    assert frame is not None
    return frame


def _recorded(client: TeleopClient, at_least: int, timeout: float = 10.0) -> int:
    state = client.state.wait_until(lambda s: s.recorded_steps >= at_least, timeout)
    assert state is not None, f"the session never reported {at_least} recorded steps"
    return state.recorded_steps


def test_a_forked_rollout_continues_where_it_was_and_is_saved_linked_to_it(site):
    hub, _, record, out = site
    _start_worker(site, "sim-fork")
    drafts = RecordingDrafts(hub.data_dir)
    keeper = DraftKeeper(drafts)
    k = out.recording.num_steps // 2
    go = fork_rollout(hub.store, drafts, record.id, k, role="agent")
    assert go.steps == k + 1 and (go.scene, go.robot, go.task, go.seed) == ("pick_place", "panda", TASK, 7)
    with TeleopClient(hub.session, "sim-fork", on_draft=keeper) as client:
        info = client.open(go.scene, go.robot, go.task, go.seed, fork=go.fork)
        assert info.control_dt == pytest.approx(out.recording.control_dt)  # the rollout's own rate
        first = client.poses.wait_until(lambda f: True, 5.0)
        np.testing.assert_allclose(first.ee_pos, out.recording.arrays["ee_pos_world"][k], atol=2e-3)
        assert _recorded(client, k + 1) >= k + 1
        # The correction: down to the bar and grasp it.
        bar = out.recording.arrays["object_poses"][k][0][:3]
        _drive(client, np.asarray(first.ee_pos), 0.0, 10)
        _drive(client, bar + np.array([0.0, 0.0, 0.002]), 0.0, 60)
        _drive(client, bar + np.array([0.0, 0.0, 0.002]), 1.0, 30)
        saved = client.stop_recording(timeout=120, success=False)
    assert isinstance(saved, msg.EpisodeSaved), saved
    assert saved.draft == go.fork.draft and saved.steps > k + 100
    meta = hub.store.get(saved.episode)
    assert meta.extra["forked_from"] == {"rollout": record.id, "step": k, "episode": record.episode_id}
    assert meta.role == "agent" and meta.embodiment == "panda" and meta.seed == 7
    _, _, arrays = hub.store.load_arrays(saved.episode)
    _, _, rolled = hub.store.load_arrays(record.episode_id)
    for name in ("time", "qpos", "object_poses", "gripper_cmd"):
        np.testing.assert_array_equal(arrays[name][: k + 1], rolled[name][: k + 1], err_msg=name)
    assert np.all(np.diff(arrays["time"]) > 0)  # one clock through the fork
    # The draft held the whole recording before it was stored: rollout prefix plus every new tick.
    assert keeper.broken == {} and keeper.kept[go.fork.draft] == saved.steps - (k + 1)
    draft = drafts.load(go.fork.draft, hub.store)
    assert draft.num_steps == saved.steps
    np.testing.assert_allclose(draft.arrays["qpos"], arrays["qpos"], atol=1e-6)


def test_a_worker_killed_mid_fork_loses_nothing_the_draft_received(site):
    hub, _, record, out = site
    proc = _start_worker(site, "sim-doomed")
    drafts = RecordingDrafts(hub.data_dir)
    keeper = DraftKeeper(drafts)
    k = out.recording.num_steps // 3
    go = fork_rollout(hub.store, drafts, record.id, k, role="expert")
    with TeleopClient(hub.session, "sim-doomed", on_draft=keeper) as client:
        first_info = client.open(go.scene, go.robot, go.task, go.seed, fork=go.fork)
        start = np.asarray(client.poses.wait_until(lambda f: True, 5.0).ee_pos)
        _drive(client, start + np.array([0.0, -0.05, -0.03]), 0.0, 40)
        time.sleep(0.5)  # the arm rests; its last ticks reach the draft
        steps_seen = _recorded(client, k + 41)
        os.kill(proc.pid, signal.SIGKILL)
        wait_gone(hub.directory, "sim-doomed", 30.0)
    journaled = drafts.next_step(go.fork.draft)
    assert keeper.broken == {}
    # Everything up to the kill but the last draft period (0.1 s of simulated time) is in the draft.
    assert journaled >= steps_seen - round(0.1 / first_info.control_dt) - 1
    _start_worker(site, "sim-rescue")
    again = resume_draft(hub.store, drafts, go.fork.draft)
    assert again.steps == journaled and again.fork.origin == go.fork.origin and again.fork.role == "expert"
    keeper2 = DraftKeeper(drafts)
    with TeleopClient(hub.session, "sim-rescue", on_draft=keeper2) as client:
        client.open(again.scene, again.robot, again.task, again.seed, fork=again.fork)
        assert _recorded(client, journaled) >= journaled
        pose = client.poses.wait_until(lambda f: True, 5.0)
        draft = drafts.load(go.fork.draft, hub.store)
        np.testing.assert_allclose(pose.ee_pos, draft.arrays["ee_pos_world"][-1], atol=2e-3)
        _drive(client, np.asarray(pose.ee_pos) + np.array([0.03, 0.0, 0.0]), 0.0, 30)
        saved = client.stop_recording(timeout=120)
    assert isinstance(saved, msg.EpisodeSaved), saved
    meta = hub.store.get(saved.episode)
    assert meta.extra["forked_from"]["rollout"] == record.id and meta.role == "expert"
    _, _, arrays = hub.store.load_arrays(saved.episode)
    np.testing.assert_allclose(arrays["qpos"][:journaled], draft.arrays["qpos"], atol=1e-6)
    assert saved.steps >= journaled + 30 and np.all(np.diff(arrays["time"]) > 0)


def test_a_rollout_whose_scene_changed_is_refused_with_the_reason(site, tmp_path):
    hub, _, record, out = site
    _start_worker(site, "sim-strict")
    drafts = RecordingDrafts(hub.data_dir)
    path = os.path.join(record.path, STATES_FILE)
    kept = tmp_path / "states.npz"
    os.replace(path, kept)
    try:
        states = np.load(kept)["states"]
        np.savez_compressed(path, states=states[:, :-3])  # as if the scene's model had changed since
        go = fork_rollout(hub.store, drafts, record.id, 10, role="agent")
        with TeleopClient(hub.session, "sim-strict") as client:
            with pytest.raises(bus.RemoteError, match="the scene changed since the episode was recorded"):
                client.open(go.scene, go.robot, go.task, go.seed, fork=go.fork)
            # The session is usable for a fresh start afterwards.
            assert client.open("pick_place", "panda", TASK, 0).task == TASK
    finally:
        os.replace(kept, path)
    assert read_states(record.path).shape == out.states.shape  # the rollout itself is untouched
