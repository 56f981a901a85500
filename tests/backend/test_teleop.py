"""Teleop sessions through a real sim worker process: driving the arm, recording into the store (shared data
directory and shipped over the bus), independent sessions, bad requests, clients that vanish, slow consumers."""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.episode_transfer import EpisodeDestination
from studio.backend.hub import Hub
from studio.backend.presence import WorkerPresence
from studio.backend.sim_worker import SimWorker
from studio.backend.teleop_client import TeleopClient, choose_sim_worker
from studio.backend.teleop_session import TeleopSession

from .conftest import Workers, wait_worker

pytestmark = pytest.mark.timeout(180)

TASK = "pick_place/cube->red"


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A hub with its store, a sim worker sharing the hub's data directory and one shipping over the bus."""
    tmp = tmp_path_factory.mktemp("teleop")
    port = bus.free_loopback_port()
    hub = Hub(bus.BusConfig.hub([bus.loopback_endpoint(port)]), data_dir=tmp / "data")
    workers = Workers(bus.loopback_endpoint(port), tmp)
    try:
        workers.start("sim", "sim-local", "--data-dir", str(hub.data_dir), handlers=())
        workers.start("sim", "sim-remote", handlers=())
        wait_worker(hub.directory, "sim-local")
        wait_worker(hub.directory, "sim-remote")
        yield hub, workers
    finally:
        workers.close()
        hub.close()


def drive(client: TeleopClient, target: np.ndarray, gripper: float, ticks: int) -> msg.PoseFrame:
    """Send ``target`` repeatedly for ``ticks`` acknowledged commands; returns the last pose."""
    frame = None
    for _ in range(ticks):
        frame = client.wait_ack(client.set_target(target, gripper), timeout=2.0)
        assert frame is not None, "command not acknowledged"
    return frame


def test_session_moves_the_arm_streams_poses_and_renders(site):
    hub, _ = site
    with TeleopClient(hub.session, "sim-local") as client:
        info = client.open("pick_place", "panda", TASK, seed=3)
        assert info.task == TASK and info.seed == 3 and info.worker == "sim-local"
        assert "external" in info.cameras and info.body_names[0] == "world"
        assert info.camera["width"] == 320 and info.control_dt == pytest.approx(0.01)
        first = client.poses.wait_until(lambda f: True, 5.0)
        assert first.body_count == len(info.body_names)
        start = np.asarray(first.ee_pos)
        target = start + np.array([0.06, 0.0, 0.08])
        last = drive(client, target, gripper=1.0, ticks=60)
        assert np.linalg.norm(np.asarray(last.ee_pos) - target) < 0.02, (last.ee_pos, target)
        assert last.gripper == 1.0 and last.step > first.step
        # The pose rows are MuJoCo bodies: the hand moved with the grasp point.
        moved = np.linalg.norm(last.poses_array()[:, :3] - first.poses_array()[:, :3], axis=1)
        assert moved.max() > 0.05
        # Without commands the simulation keeps running at its own pace.
        s0 = client.latest_pose().step
        time.sleep(0.5)
        assert client.latest_pose().step - s0 >= 10
        image = client.request_frame(encoding="raw")
        assert (image.height, image.width) == (240, 320) and image.to_array().std() > 5
        jpeg = client.request_frame(camera="wrist", encoding="jpeg", quality=70)
        assert jpeg.to_array().ndim == 3
        geometry = client.geometry()
        assert geometry.body_names == info.body_names and geometry.meshes
        assert all(g.group <= 2 for g in geometry.geoms)
        client.stream_frames(hz=10.0)
        streamed = client.frames.wait_until(lambda f: f.camera == "external" and f.step > image.step, 5.0)
        assert streamed is not None
        client.stream_frames(hz=0.0)
        info2 = client.reset(task="pick_place/prism->blue", seed=4)
        assert info2.task == "pick_place/prism->blue"


@pytest.mark.parametrize("worker, via", [("sim-local", "data-dir"), ("sim-remote", "bus")])
def test_recorded_episode_lands_in_the_hub_store(site, worker, via):
    hub, _ = site
    before = {m.id for m in hub.store.episodes()}
    with TeleopClient(hub.session, worker) as client:
        client.open("pick_place", "panda", TASK, seed=5)
        state = client.start_recording()
        assert state.state == "recording" and state.recorded_steps == 1
        start = np.asarray(client.poses.wait_until(lambda f: True, 5.0).ee_pos)
        drive(client, start + np.array([0.0, 0.05, -0.05]), gripper=0.0, ticks=30)
        saved = client.stop_recording(timeout=120)
        assert isinstance(saved, msg.EpisodeSaved), saved
        assert saved.via == via and saved.role == "agent" and saved.steps >= 30 and saved.frames >= 20
    episodes = [m for m in hub.store.episodes() if m.id not in before]
    assert [m.id for m in episodes] == [saved.episode]
    meta = episodes[0]
    assert meta.source == "teleop" and meta.embodiment == "panda" and meta.task == TASK and meta.seed == 5
    assert meta.num_steps == saved.steps and meta.extra["worker"] == worker
    episode = hub.store.load(saved.episode)
    assert episode.frames.shape[0] == saved.frames
    ee = episode.arrays["ee_pos_world"]
    assert ee[-1][1] - ee[0][1] > 0.02  # the recorded arm followed the commands


class _FullQueue:
    """A command publisher whose link drops every command the first time it is sent (as a full queue does)."""

    def __init__(self, publisher):
        self.publisher, self.seen, self.dropped = publisher, set(), 0

    def put(self, payload: bytes, **kwargs) -> None:
        if payload not in self.seen:
            self.seen.add(payload)
            self.dropped += 1
            return
        self.publisher.put(payload, **kwargs)

    def __getattr__(self, name: str):
        return getattr(self.publisher, name)


def _open_behind_a_full_queue(client: TeleopClient) -> np.ndarray:
    """Open a Sawyer session, then put the client's commands behind :class:`_FullQueue`; returns the start pose."""
    client.open("pick_place", "sawyer", TASK, seed=1)
    start = np.asarray(client.poses.wait_until(lambda f: True, 5.0).ee_pos)
    client._cmd_pub = _FullQueue(client._cmd_pub)
    return start


def test_a_command_the_bus_dropped_is_sent_again_until_the_worker_applied_it(site):
    hub, _ = site
    with TeleopClient(hub.session, "sim-local") as client:
        start = _open_behind_a_full_queue(client)
        # A motion's last target with a gripper change, lost on its first send: the arm still gets there.
        target = start + np.array([0.0, 0.0, 0.06])
        seq = client.set_target(target, 1.0)
        frame = client.wait_ack(seq, timeout=3.0)
        assert frame is not None, "a dropped command was never sent again"
        assert client._cmd_pub.dropped == 1 and client.resent >= 1
        frame = client.poses.wait_until(lambda f: np.linalg.norm(np.asarray(f.ee_pos) - target) < 0.01, 5.0)
        assert frame is not None and frame.gripper == 1.0
        # Applied once, it is not sent again.
        resent = client.resent
        time.sleep(0.6)
        assert client.resent == resent


def test_a_reset_forgets_a_command_the_worker_never_applied(site):
    hub, _ = site
    with TeleopClient(hub.session, "sim-local") as client:
        start = _open_behind_a_full_queue(client)
        client.set_target(start + np.array([0.0, 0.0, 0.06]), 0.0)
        client.reset()  # before the first pose frame could send it again
        s0 = client.latest_pose().step
        time.sleep(0.6)
        frame = client.poses.wait_until(lambda f: f.step >= s0 + 20, 5.0)
        assert frame is not None and frame.ack_seq == -1 and client.resent == 0
        assert np.linalg.norm(np.asarray(frame.ee_pos) - start) < 0.01


def test_a_sessions_events_and_journal_must_arrive_its_streams_may_drop(site, tmp_path):
    """An episode's stored / not stored event and the draft chunks a fork journals block on a full queue (a lost
    one strands the page at "Saving…" or breaks the draft); poses, frames and periodic states drop."""
    hub, _ = site
    request = msg.OpenSession(scene="pick_place", robot="sawyer", task=TASK, seed=0)
    session = TeleopSession(
        hub.session,
        "sim-inproc",
        "s-inproc",
        request,
        EpisodeDestination(data_dir=tmp_path),
        tmp_path / "spool",
    )
    try:
        must, drop = zenoh.CongestionControl.BLOCK, zenoh.CongestionControl.DROP
        assert bus.MUST_ARRIVE == must
        assert (
            session._event_pub.congestion_control == must
            and session.sink._draft_pub.congestion_control == must
        )
        assert session._state_pub.congestion_control == drop
        assert session._pose_pub.congestion_control == drop and session._frame_pub.congestion_control == drop
    finally:
        session.close()


def test_two_clients_get_independent_sessions(site):
    hub, _ = site
    with TeleopClient(hub.session, "sim-local") as a, TeleopClient(hub.session, "sim-local") as b:
        assert a.session_id != b.session_id
        a.open("pick_place", "panda", TASK, seed=1)
        b.open("push", "panda", "push/red-forward", seed=2)
        b0 = np.asarray(b.poses.wait_until(lambda f: True, 5.0).ee_pos)
        a0 = np.asarray(a.poses.wait_until(lambda f: True, 5.0).ee_pos)
        drive(a, a0 + np.array([0.0, 0.0, 0.1]), gripper=1.0, ticks=40)
        b_now = b.latest_pose()
        assert np.linalg.norm(np.asarray(b_now.ee_pos) - b0) < 0.01 and b_now.ack_seq == -1
        assert a.latest_pose().ee_pos[2] > a0[2] + 0.07
        status = hub.directory.get("sim", "sim-local").status
        assert status.sessions == 2
        a.close()
        assert b.wait_ack(b.set_target(b0 + np.array([0.03, 0.0, 0.0]), 0.0)) is not None  # b is unaffected
    assert hub.directory.wait_for(lambda ws: hub.directory.get("sim", "sim-local").status.sessions == 0, 10)


def test_the_worker_logs_each_session_it_opens_replaces_and_closes(site, tmp_path, caplog):
    """What an operator reads in a sim worker's log: each session opened (scene, robot, task, seed, how long it
    took, how many the worker hosts), replaced by a re-open, and closed."""
    hub, _ = site
    presence = WorkerPresence(hub.session, "sim", "sim-logs", announce=False)
    host = SimWorker(hub.session, presence, EpisodeDestination(data_dir=tmp_path), tmp_path / "spool")
    caplog.set_level("INFO", logger=bus.log.name)
    try:
        with TeleopClient(hub.session, "sim-logs") as client:
            client.open("pick_place", "sawyer", TASK, seed=3)
            client.open("push", "panda", "push/red-forward", seed=4)
            sid = client.session_id
        deadline = time.monotonic() + 10
        while host.sessions and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not host.sessions
    finally:
        host.close()
        presence.close()
    lines = [r.getMessage() for r in caplog.records if sid in r.getMessage()]
    assert len(lines) == 4, lines
    assert re.fullmatch(
        rf"opened session {sid}: pick_place / sawyer / {re.escape(TASK)} seed 3 in \d+\.\d s \(1 sessions\)",
        lines[0],
    )
    assert lines[1] == f"closing session {sid}: re-opened"
    assert re.fullmatch(
        rf"re-opened session {sid}: push / panda / push/red-forward seed 4 in \d+\.\d s \(1 sessions\)",
        lines[2],
    )
    assert lines[3] in (
        f"closing session {sid}: its client closed it",
        f"closing session {sid}: its client left the bus",
    )


def test_bad_requests_get_clear_errors_and_the_session_survives(site):
    hub, _ = site
    with TeleopClient(hub.session, "sim-local") as client:
        with pytest.raises(bus.RemoteError, match="bad_request: unknown task"):
            client.open("pick_place", "panda", "pick_place/nothing->nowhere", seed=0)
        with pytest.raises(bus.RemoteError, match="not_found"):
            client.start_recording()
        with pytest.raises(bus.RemoteError, match="exceeds the scene's render buffer"):
            client.open("pick_place", "panda", TASK, seed=0, image_size=(2000, 3000))
        client.open("pick_place", "panda", TASK, seed=0)
        with pytest.raises(bus.RemoteError, match="belongs to scene"):
            client.reset(task="push/red-forward")
        with pytest.raises(bus.RemoteError, match="unknown camera"):
            client.request_frame(camera="nope")
        with pytest.raises(bus.RemoteError, match="conflict: not recording"):
            client.stop_recording()
        client.start_recording()
        with pytest.raises(bus.RemoteError, match="recording too short"):
            client.stop_recording()
        assert client.discard_recording().state == "idle"
        # Garbage on the control key and on the command stream.
        replies = list(
            hub.session.get(
                keys.session_key("sim-local", client.session_id, "ctl"), payload=b"\x01\x92\xa3bad", timeout=3
            )
        )
        assert msg.decode(replies[0].ok.payload.to_bytes(), msg.ErrorReply).code == "bad_request"
        hub.session.put(keys.session_key("sim-local", client.session_id, "cmd"), b"\x01\xff\x00")
        assert client.wait_ack(client.set_target([0.0, 0.4, 0.2], 0.0)) is not None


def test_session_closes_when_its_client_vanishes(site, port):
    hub, _ = site
    other = bus.open_session(bus.BusConfig.worker([hub.endpoint]))
    client = TeleopClient(other, choose_sim_worker(hub.directory))
    client.open("pick_place", "sawyer", TASK, seed=0)
    worker = client.worker
    assert hub.directory.wait_for(lambda ws: hub.directory.get("sim", worker).status.sessions >= 1, 5)
    other.close()  # the client process "dies": its liveliness token disappears
    assert hub.directory.wait_for(lambda ws: hub.directory.get("sim", worker).status.sessions == 0, 10)


def test_slow_consumer_never_stalls_the_simulation(site):
    """A subscriber that takes 0.5 s per pose, through a one-slot blocking channel (so its Zenoh session stops
    reading and back-pressure reaches the network): the worker drops stale poses and keeps simulating."""
    hub, _ = site
    slow = bus.open_session(bus.BusConfig.worker([hub.endpoint]))
    try:
        with TeleopClient(hub.session, "sim-remote") as client:
            client.open("pick_place", "panda", TASK, seed=0)
            sub = slow.declare_subscriber(
                keys.session_key("sim-remote", client.session_id, "poses"), zenoh.handlers.FifoChannel(1)
            )
            consumed = []
            stop = threading.Event()

            def consume() -> None:
                while not stop.is_set():
                    if sub.try_recv() is not None:
                        consumed.append(1)
                    stop.wait(0.5)

            reader = threading.Thread(target=consume, daemon=True)
            reader.start()
            first = client.poses.wait_until(lambda f: True, 5.0)
            time.sleep(2.0)
            last = client.latest_pose()
            stop.set()
            reader.join(2)
            sub.undeclare()
        # About 125 ticks in 2 s; the slow subscriber took a handful of them.
        assert last.step - first.step > 60
        assert 0 < len(consumed) < 10
    finally:
        slow.close()


def test_metaworld_session_follows_the_task_model(site):
    hub, _ = site
    with TeleopClient(hub.session, "sim-remote") as client:
        info = client.open(
            "metaworld", "sawyer", "metaworld/button-press-topdown-v3", seed=0, image_size=(224, 224)
        )
        assert info.task == "metaworld/button-press-topdown-v3" and info.control_dt > 0
        start = np.asarray(client.poses.wait_until(lambda f: True, 10.0).ee_pos)
        last = drive(client, start + np.array([0.0, 0.0, -0.03]), gripper=0.0, ticks=20)
        assert last.body_count == len(info.body_names) and last.ee_pos[2] < start[2] - 0.01
        assert client.request_frame().width == 224
        # Every camera the session offers renders; Meta-World's re-mounted ones go by the studio's names.
        assert info.cameras[:2] == ("external", "wrist") and "behindGripper" not in info.cameras
        for camera in info.cameras:
            assert client.request_frame(camera=camera, encoding="raw").to_array().std() > 1, camera
        other = client.reset(task="metaworld/drawer-open-v3", seed=1)
        assert other.task == "metaworld/drawer-open-v3"
        frame = client.poses.wait_until(lambda f: f.body_count == len(other.body_names), 5.0)
        assert frame is not None
        assert client.geometry().body_names == other.body_names


def test_hand_recordings_are_human_demonstrations(site):
    hub, _ = site
    before = {m.id for m in hub.store.episodes()}
    with TeleopClient(hub.session, "sim-local") as client:
        client.open("pick_place", "hand", TASK, seed=6)
        client.start_recording()
        start = np.asarray(client.poses.wait_until(lambda f: True, 5.0).ee_pos)
        drive(client, start + np.array([0.0, 0.05, -0.05]), gripper=1.0, ticks=30)
        saved = client.stop_recording(timeout=120)
        assert isinstance(saved, msg.EpisodeSaved), saved
        assert saved.role == "expert"
    (meta,) = [m for m in hub.store.episodes() if m.id not in before]
    assert (meta.embodiment, meta.role, meta.source, meta.seed) == ("human", "expert", "teleop", 6)
    assert meta.has_arrays


def test_only_the_opener_controls_its_session(site):
    """Session ids are public (they are in every key); the owner token is not. Another peer's DiscardRecording,
    reset, re-open or close is refused, its commands are dropped, and a command far ahead in seq freezes nothing."""
    hub, _ = site
    other = bus.open_session(bus.BusConfig.worker([hub.endpoint]))
    try:
        with TeleopClient(hub.session, "sim-local") as client:
            info = client.open("pick_place", "panda", TASK, seed=4)
            assert info.owner is not None and len(info.owner) >= 16
            start = np.asarray(client.poses.wait_until(lambda f: True, 5.0).ee_pos)
            client.start_recording()
            ctl = keys.session_key("sim-local", client.session_id, "ctl")
            cmd = keys.session_key("sim-local", client.session_id, "cmd")
            for request in (
                msg.DiscardRecording(),
                msg.StopRecording(),
                msg.ResetSession(seed=9),
                msg.OpenSession(scene="pick_place", robot="panda", task=TASK, seed=0),
                msg.CloseSession(),
            ):
                with pytest.raises(bus.RemoteError, match=r"conflict: .*belongs to another client"):
                    bus.request(other, ctl, request, msg.Message, timeout=5)
            with pytest.raises(bus.RemoteError, match="belongs to another client"):
                bus.request(other, ctl, msg.DiscardRecording(), msg.Message, timeout=5, attachment=b"x" * 32)
            # A forged command, and a far-ahead one: neither is applied nor holds back the owner's commands.
            other.put(cmd, msg.encode(msg.EeTarget(seq=2**62, pos=(0.0, 0.6, 0.6), gripper=1.0)))
            drive(client, start + np.array([0.0, 0.04, 0.0]), gripper=0.0, ticks=10)
            client._cmd_pub.put(
                msg.encode(msg.EeTarget(seq=2**62, pos=(0.0, 0.6, 0.6), gripper=1.0)),
                attachment=client._owner,
            )
            frame = drive(client, start + np.array([0.0, 0.05, 0.0]), gripper=0.0, ticks=15)
            assert (
                frame.ack_seq < 2**62 and abs(frame.ee_pos[2] - start[2]) < 0.05
            )  # not sent to the forged z
            # A token of another peer that comes and goes on the client key does not end the owner's session.
            other.liveliness().declare_token(
                keys.session_key("sim-local", client.session_id, "client")
            ).undeclare()
            time.sleep(2.0)
            state = client.state.wait_until(lambda s: s.recorded_steps >= 20, 5.0)
            assert state is not None and state.state == "recording", state
            assert client.request_frame().camera == "external"  # the session is still open
            saved = client.stop_recording(timeout=120)  # the owner's recording survived the attempts
            assert isinstance(saved, msg.EpisodeSaved), saved
    finally:
        other.close()


def test_a_recording_the_store_refuses_is_kept_as_a_draft_of_the_data_dir(tmp_path, port, workers):
    """A full or broken store: the recording becomes a draft in the worker's data dir, which the Teleop panel's
    Interrupted recordings lists (RecordingDrafts), with every recorded tick — not a file outside the data dir."""
    from studio.data.drafts import RecordingDrafts

    hub = Hub(bus.BusConfig.hub([bus.loopback_endpoint(port)]), data_dir=tmp_path / "hub-data")
    try:
        data = tmp_path / "worker-data"
        data.mkdir()
        (data / "episodes").write_text("not a directory: the store cannot open")
        workers.start("sim", "sim-broken", "--data-dir", str(data), handlers=())
        wait_worker(hub.directory, "sim-broken")
        with TeleopClient(hub.session, "sim-broken") as client:
            client.open("pick_place", "panda", TASK, seed=2)
            client.start_recording()
            start = np.asarray(client.poses.wait_until(lambda f: True, 5.0).ee_pos)
            drive(client, start + np.array([0.0, 0.05, -0.03]), gripper=0.0, ticks=30)
            outcome = client.stop_recording(timeout=120)
        assert isinstance(outcome, msg.EpisodeNotSaved), outcome
        assert outcome.kept_at.startswith("draft "), outcome.kept_at
        drafts = RecordingDrafts(data).drafts()
        assert len(drafts) == 1 and outcome.kept_at.split()[1] == drafts[0].id
        draft = RecordingDrafts(data).load(drafts[0].id)
        assert draft.header["task"] == TASK and draft.header["role"] == "agent" and draft.num_steps >= 30
        assert not list((tmp_path / "spool-sim-broken").glob("unsaved-*"))
        log = workers.log("sim-broken")
        assert "storing a recording failed: FileExistsError" in log and "Traceback" not in log, log
    finally:
        hub.close()
