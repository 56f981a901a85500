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


def test_uncommitted_chunks_are_bounded_and_expire(sessions, tmp_path):
    """A peer that sends chunks and never commits holds a bounded amount of the hub's memory, briefly."""
    from studio.backend import episode_transfer as et

    assert et.MAX_UNCOMMITTED_BYTES <= 256 << 20 and et.STALE_S <= 60 and et.MAX_TRANSFER_CHUNKS <= 256
    hub, worker = sessions
    with EpisodeStore(tmp_path / "data") as store:
        sink = EpisodeSink(hub, store)
        chunk = lambda t, i, n, size=1000: msg.EpisodeChunk(transfer=t, index=i, count=n, data=b"x" * size)  # noqa: E731
        with pytest.raises(bus.RemoteError, match="bad_request: a transfer has at most 256 chunks"):
            bus.request(worker, keys.upload_key("u-0"), chunk("u-0", 0, 400_000), msg.ChunkAck)
        for t in range(et.MAX_TRANSFERS):
            bus.request(worker, keys.upload_key(f"u-{t}"), chunk(f"u-{t}", 0, 2), msg.ChunkAck)
        with pytest.raises(bus.RemoteError, match=r"busy: .*transfers already"):
            bus.request(worker, keys.upload_key("u-x"), chunk("u-x", 0, 2), msg.ChunkAck)
        with pytest.raises(bus.RemoteError, match="bad_request: request larger than"):
            bus.request(worker, keys.upload_key("u-0"), chunk("u-0", 1, 2, size=3 << 20), msg.ChunkAck)
        assert sink.held_bytes == 1000 * et.MAX_TRANSFERS
        sink.close()

        small = EpisodeSink(hub, store, max_bytes=5000, max_transfer_bytes=3000, stale_s=0.6)
        for i in range(3):
            bus.request(worker, keys.upload_key("v-1"), chunk("v-1", i, 10), msg.ChunkAck)
        with pytest.raises(bus.RemoteError, match="bad_request: a transfer holds at most 3000 bytes"):
            bus.request(worker, keys.upload_key("v-1"), chunk("v-1", 3, 10), msg.ChunkAck)
        bus.request(worker, keys.upload_key("v-2"), chunk("v-2", 0, 10, size=2000), msg.ChunkAck)
        with pytest.raises(bus.RemoteError, match="busy: the store host holds too many"):
            bus.request(worker, keys.upload_key("v-3"), chunk("v-3", 0, 10), msg.ChunkAck)
        deadline = time.monotonic() + 5
        while small.held_bytes and time.monotonic() < deadline:
            time.sleep(0.1)
        assert small.held_bytes == 0  # expired without another request arriving
        small.close()


def test_an_episode_the_store_refuses_is_one_bad_request_and_one_log_line(sessions, tmp_path, caplog):
    hub, worker = sessions
    with EpisodeStore(tmp_path / "data") as store:
        sink = EpisodeSink(hub, store)
        payload = msg.encode(recording_payload(make_recording(5)))
        sha = hashlib.sha256(payload).hexdigest()
        for i in range(3):
            t = f"e-{i}"
            bus.request(
                worker,
                keys.upload_key(t),
                msg.EpisodeChunk(transfer=t, index=0, count=1, data=payload),
                msg.ChunkAck,
            )
            commit = msg.EpisodeCommit(
                transfer=t, count=1, sha256=sha, role="agent", source="teleop", embodiment="martian"
            )
            with pytest.raises(
                bus.RemoteError, match=r"bad_request: the store refused the episode: .*embodiment"
            ):
                bus.request(worker, keys.upload_key(t), commit, msg.EpisodeStored)
        assert not store.episodes()
        sink.close()
    text = caplog.text
    assert "Traceback" not in text and len([r for r in caplog.records if r.levelname != "DEBUG"]) <= 1, text
