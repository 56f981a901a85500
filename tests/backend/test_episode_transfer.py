"""Episode shipping over the bus: chunked, checksummed, stored by the hub's sink, and kept in the spool (then
retried) when the hub's store cannot be reached — never lost."""

from __future__ import annotations

import hashlib
import time

import numpy as np
import pytest

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.episode_transfer import (
    EpisodeShipper,
    EpisodeSink,
    ShipError,
    payload_recording,
    recording_payload,
)
from studio.data.store import EpisodeStore
from studio.sim.camera import CameraModel
from studio.sim.recording import Recording

pytestmark = pytest.mark.timeout(60)


def make_recording(seed: int = 0, steps: int = 30, frames: int = 20) -> Recording:
    rng = np.random.default_rng(seed)
    camera = CameraModel.from_fovy(45.0, 32, 24, np.eye(4))
    return Recording(
        scene="pick_place",
        robot="panda",
        task="pick_place/cube->red",
        seed=seed,
        success=bool(seed % 2),
        camera=camera,
        frames=rng.integers(0, 255, (frames, 24, 32, 3), dtype=np.uint8),
        frame_steps=np.linspace(0, steps - 1, frames).round().astype(np.int64),
        arrays={
            "time": np.arange(steps) * 0.02,
            "qpos": rng.normal(size=(steps, 9)),
            "ee_pos_world": rng.normal(size=(steps, 3)),
            "ee_pos_cam": rng.normal(size=(steps, 3)),
            "gripper_cmd": rng.uniform(size=steps),
            "gripper_opening": rng.uniform(size=steps),
            "object_poses": rng.normal(size=(steps, 4, 7)),
        },
        object_names=["cube", "cylinder", "prism", "bar"],
    )


@pytest.fixture
def sessions(port):
    hub = bus.open_session(bus.BusConfig.hub([bus.loopback_endpoint(port)]))
    worker = bus.open_session(bus.BusConfig.worker([bus.loopback_endpoint(port)]))
    yield hub, worker
    worker.close()
    hub.close()


def test_payload_round_trip_is_exact():
    rec = make_recording(3)
    back = payload_recording(msg.decode(msg.encode(recording_payload(rec)), msg.RecordingPayload))
    assert back.task == rec.task and back.seed == 3 and back.success is True
    assert np.array_equal(back.frames, rec.frames) and np.array_equal(back.frame_steps, rec.frame_steps)
    for k, v in rec.arrays.items():
        assert np.array_equal(back.arrays[k], v) and back.arrays[k].dtype == v.dtype
    assert np.allclose(back.camera.K, rec.camera.K)


def test_shipped_episode_is_stored_by_the_hub(sessions, tmp_path):
    hub, worker = sessions
    with EpisodeStore(tmp_path / "data") as store:
        sink = EpisodeSink(hub, store)
        shipper = EpisodeShipper(worker, tmp_path / "spool", chunk_bytes=8192)
        rec = make_recording(1)
        episode = shipper.ship(rec, role="agent", source="teleop", extra={"note": "x"})
        loaded = store.load(episode)
        assert (
            loaded.meta.source == "teleop"
            and loaded.meta.role == "agent"
            and loaded.meta.extra["note"] == "x"
        )
        assert np.allclose(loaded.arrays["ee_pos_world"], rec.arrays["ee_pos_world"])
        assert loaded.frames.shape == rec.frames.shape
        assert not shipper.pending() and not list((tmp_path / "spool").glob("*.payload"))
        shipper.close()
        sink.close()


def test_episode_waits_in_the_spool_until_the_hub_store_appears(sessions, tmp_path):
    hub, worker = sessions
    shipper = EpisodeShipper(worker, tmp_path / "spool", timeout_s=0.5, retry_s=0.2)
    try:
        with pytest.raises(ShipError, match="retried automatically") as info:
            shipper.ship(make_recording(2), role="expert", source="teleop")
        assert info.value.kept_at.exists() and len(shipper.pending()) == 1
        with EpisodeStore(tmp_path / "data") as store:
            sink = EpisodeSink(hub, store)
            deadline = time.monotonic() + 10
            while shipper.pending() and time.monotonic() < deadline:
                time.sleep(0.1)
            assert not shipper.pending()
            stored = store.episodes()
            assert len(stored) == 1 and stored[0].role == "expert" and stored[0].seed == 2
            sink.close()
    finally:
        shipper.close()


def test_sink_refuses_incomplete_or_corrupt_transfers(sessions, tmp_path):
    hub, worker = sessions
    with EpisodeStore(tmp_path / "data") as store:
        sink = EpisodeSink(hub, store)
        payload = msg.encode(recording_payload(make_recording(4)))
        half = len(payload) // 2
        key = keys.upload_key("t-1")
        bus.request(
            worker, key, msg.EpisodeChunk(transfer="t-1", index=0, count=2, data=payload[:half]), msg.ChunkAck
        )
        good_sha = hashlib.sha256(payload).hexdigest()
        commit = msg.EpisodeCommit(transfer="t-1", count=2, sha256=good_sha, role="agent", source="teleop")
        with pytest.raises(bus.RemoteError, match="have 1 of 2 chunks"):
            bus.request(worker, key, commit, msg.EpisodeStored)
        corrupt = payload[half:-1] + bytes([payload[-1] ^ 1])
        bus.request(
            worker, key, msg.EpisodeChunk(transfer="t-1", index=1, count=2, data=corrupt), msg.ChunkAck
        )
        with pytest.raises(bus.RemoteError, match="SHA-256 mismatch"):
            bus.request(worker, key, commit, msg.EpisodeStored)
        # A transfer id that differs from its key, and a checksum-valid but meaningless payload.
        with pytest.raises(bus.RemoteError, match="differs from the key"):
            bus.request(
                worker, key, msg.EpisodeChunk(transfer="t-2", index=0, count=1, data=b"x"), msg.ChunkAck
            )
        junk = msg.encode(msg.Ack())
        bus.request(
            worker,
            keys.upload_key("t-3"),
            msg.EpisodeChunk(transfer="t-3", index=0, count=1, data=junk),
            msg.ChunkAck,
        )
        junk_commit = msg.EpisodeCommit(
            transfer="t-3", count=1, sha256=hashlib.sha256(junk).hexdigest(), role="agent", source="teleop"
        )
        with pytest.raises(bus.RemoteError, match="not a valid recording"):
            bus.request(worker, keys.upload_key("t-3"), junk_commit, msg.EpisodeStored)
        assert store.episodes() == []
        sink.close()
