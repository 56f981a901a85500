"""Content-addressed transfer of a job's files over the bus: a round trip by content id, a corrupt piece refused,
an interrupted fetch resumed from where it stopped, the size cap, the cache, an offered output kept by the hub at
its path (and nowhere else), and an episode offered byte for byte into the hub's store."""

from __future__ import annotations

import hashlib
import os

import msgspec
import numpy as np
import pytest

from studio.backend import bus
from studio.backend import messages as msg
from studio.backend.artifact_transfer import (
    BlobCache,
    BlobFetcher,
    BlobServer,
    FileRef,
    HubArtifacts,
    InputManifest,
    TransferError,
    WorkerArtifacts,
)
from studio.data.paths import SHIPPED_POLICY_DIR
from studio.data.store import EpisodeStore

from .test_episode_transfer import make_recording

pytestmark = pytest.mark.timeout(60)

CHUNK = 4096


@pytest.fixture
def sessions(port):
    hub = bus.open_session(bus.BusConfig.hub([bus.loopback_endpoint(port)]))
    worker = bus.open_session(bus.BusConfig.worker([bus.loopback_endpoint(port)]))
    yield hub, worker
    worker.close()
    hub.close()


def _file(path, size: int, seed: int = 0) -> str:
    path.parent.mkdir(parents=True, exist_ok=True)
    data = np.random.default_rng(seed).integers(0, 256, size, dtype=np.uint8).tobytes()
    path.write_bytes(data)
    return hashlib.sha256(data).hexdigest()


class CorruptingServer(BlobServer):
    """Flips a byte of piece ``index`` (keeping the digest of the true piece), ``times`` times."""

    def __init__(self, *args, index: int, times: int, **kwargs):
        super().__init__(*args, **kwargs)
        self.index, self.times = index, times

    def piece(self, blob: str, index: int) -> msg.Message:
        part = super().piece(blob, index)
        if isinstance(part, msg.BlobPart) and index == self.index and self.times > 0:
            self.times -= 1
            data = bytes([part.data[0] ^ 0xFF]) + part.data[1:]
            return msg.BlobPart(
                blob=blob, index=index, count=part.count, size=part.size, digest=part.digest, data=data
            )
        return part


def test_round_trip_by_content_id_and_a_cache_hit_fetches_nothing(sessions, tmp_path):
    hub_s, worker_s = sessions
    src = BlobCache(tmp_path / "hub")
    blob = _file(tmp_path / "hub" / "runs" / "a" / "best.pt", 5 * CHUNK + 123)
    ref = src.publish(tmp_path / "hub" / "runs" / "a" / "best.pt")
    assert (ref.blob, ref.size, ref.path) == (blob, 5 * CHUNK + 123, "runs/a/best.pt")
    server = BlobServer(hub_s, src, "hub", chunk_bytes=CHUNK)
    dest = BlobCache(tmp_path / "worker")
    fetcher = BlobFetcher(worker_s, dest, chunk_bytes=CHUNK)
    got = fetcher.fetch("hub", blob)
    assert got == tmp_path / "worker" / "artifacts" / "blobs" / blob
    assert hashlib.sha256(got.read_bytes()).hexdigest() == blob
    assert [i for _, i in server.served] == list(range(6))
    assert not list(dest.partial_dir.iterdir())
    fetcher.fetch("hub", blob)
    assert len(server.served) == 6  # cached by id: nothing asked again
    assert dest.place(blob, tmp_path / "worker" / "runs" / "a" / "best.pt")
    assert not dest.place(blob, tmp_path / "worker" / "runs" / "a" / "best.pt")  # already there


def test_a_corrupt_piece_is_asked_again_and_one_that_stays_corrupt_fails_the_fetch(sessions, tmp_path):
    hub_s, worker_s = sessions
    src = BlobCache(tmp_path / "hub")
    blob = _file(tmp_path / "hub" / "plans" / "p.npz", 3 * CHUNK)
    src.publish(tmp_path / "hub" / "plans" / "p.npz")
    server = CorruptingServer(hub_s, src, "hub", chunk_bytes=CHUNK, index=1, times=1)
    dest = BlobCache(tmp_path / "worker")
    got = BlobFetcher(worker_s, dest, chunk_bytes=CHUNK).fetch("hub", blob)
    assert hashlib.sha256(got.read_bytes()).hexdigest() == blob
    assert [i for _, i in server.served] == [0, 1, 1, 2]
    server.close()

    other = BlobCache(tmp_path / "worker2")
    CorruptingServer(hub_s, src, "hub2", chunk_bytes=CHUNK, index=2, times=99)
    with pytest.raises(TransferError, match="does not match its digest"):
        BlobFetcher(worker_s, other, chunk_bytes=CHUNK).fetch("hub2", blob)
    assert not other.has(blob)


def test_an_interrupted_fetch_resumes_where_it_stopped_and_a_damaged_partial_is_refused(sessions, tmp_path):
    hub_s, worker_s = sessions
    src = BlobCache(tmp_path / "hub")
    blob = _file(tmp_path / "hub" / "runs" / "r" / "last.pt", 8 * CHUNK + 7)
    src.publish(tmp_path / "hub" / "runs" / "r" / "last.pt")
    server = BlobServer(hub_s, src, "hub", chunk_bytes=CHUNK)
    dest = BlobCache(tmp_path / "worker")
    fetcher = BlobFetcher(worker_s, dest, chunk_bytes=CHUNK)
    with pytest.raises(TransferError, match="stopped after 5 of 9"):
        fetcher.fetch("hub", blob, stop_after=5)
    assert not dest.has(blob) and dest.partial_path(blob).stat().st_size == 5 * CHUNK
    fetcher.fetch("hub", blob)
    assert [i for _, i in server.served] == [
        0,
        1,
        2,
        3,
        4,
        4,
        5,
        6,
        7,
        8,
    ]  # the last piece kept, then the rest
    assert hashlib.sha256(dest.blob_path(blob).read_bytes()).hexdigest() == blob

    again = BlobCache(tmp_path / "worker2")
    fetcher2 = BlobFetcher(worker_s, again, chunk_bytes=CHUNK)
    with pytest.raises(TransferError):
        fetcher2.fetch("hub", blob, stop_after=3)
    with open(again.partial_path(blob), "r+b") as f:  # the disk damages a kept piece
        f.write(b"\x00" * 10)
    with pytest.raises(TransferError, match="fetch it again"):
        fetcher2.fetch("hub", blob)
    assert not again.partial_path(blob).exists() and not again.has(blob)
    assert hashlib.sha256(fetcher2.fetch("hub", blob).read_bytes()).hexdigest() == blob


def test_content_above_the_cap_is_refused_before_anything_is_written(sessions, tmp_path):
    hub_s, worker_s = sessions
    src = BlobCache(tmp_path / "hub")
    blob = _file(tmp_path / "hub" / "runs" / "big.pt", 4 * CHUNK)
    src.publish(tmp_path / "hub" / "runs" / "big.pt")
    BlobServer(hub_s, src, "hub", chunk_bytes=CHUNK)
    dest = BlobCache(tmp_path / "worker")
    with pytest.raises(TransferError, match="more than the 10000 allowed"):
        BlobFetcher(worker_s, dest, chunk_bytes=CHUNK, max_bytes=10_000).fetch("hub", blob)
    assert not dest.has(blob) and dest.partial_path(blob).stat().st_size == 0
    with pytest.raises(TransferError, match="no content"):
        BlobFetcher(worker_s, dest, chunk_bytes=CHUNK).fetch("hub", "0" * 64)


def test_a_published_file_changed_since_is_no_longer_served_as_its_old_content(tmp_path):
    src = BlobCache(tmp_path / "hub")
    path = tmp_path / "hub" / "runs" / "m.jsonl"
    old = _file(path, 100)
    src.publish(path)
    _file(path, 100, seed=1)
    os.utime(path, ns=(1, 1))
    assert src.source(old) is None


def test_an_output_is_kept_by_the_hub_at_its_path_and_an_episode_byte_for_byte(sessions, tmp_path):
    hub_s, worker_s = sessions
    with EpisodeStore(tmp_path / "hub") as hub_store, EpisodeStore(tmp_path / "worker") as worker_store:
        hub = HubArtifacts(hub_s, tmp_path / "hub", hub_store)
        worker = WorkerArtifacts(worker_s, tmp_path / "worker", "sim-1")
        try:
            blob = _file(tmp_path / "worker" / "plans" / "job-1.npz", 3000)
            assert worker.offer(tmp_path / "worker" / "plans" / "job-1.npz") == ["plans/job-1.npz"]
            assert hashlib.sha256((tmp_path / "hub" / "plans" / "job-1.npz").read_bytes()).hexdigest() == blob

            _file(tmp_path / "worker" / "catalog-copy.bin", 10)
            with pytest.raises(TransferError, match="outputs go under"):
                worker.offer(tmp_path / "worker" / "catalog-copy.bin")
            assert not (tmp_path / "hub" / "catalog-copy.bin").exists()

            meta = worker_store.add_episode(make_recording(seed=3), role="agent", source="teleop")
            assert worker.offer_episode(meta.id) == f"episodes/{meta.id}"
            for name in ("meta.json", "frames.mp4", "arrays.npz"):
                mine = (tmp_path / "worker" / "episodes" / meta.id / name).read_bytes()
                assert (tmp_path / "hub" / "episodes" / meta.id / name).read_bytes() == mine
            assert hub_store.get(meta.id).task == meta.task
            assert worker.offer_episode(meta.id) == f"episodes/{meta.id}"  # a retried offer is answered alike
        finally:
            worker.close()
            hub.close()


def test_inputs_of_a_plan_job_are_fetched_into_the_workers_own_data_dir(sessions, tmp_path):
    hub_s, worker_s = sessions
    with EpisodeStore(tmp_path / "hub") as hub_store:
        demo = hub_store.add_episode(make_recording(seed=1), role="expert", source="teleop")
        ck = _file(tmp_path / "hub" / "runs" / "r1" / "best.pt", 2000)
        dec = _file(tmp_path / "hub" / "runs" / "r1" / "best.decoder.pt", 500, seed=2)
        hub = HubArtifacts(hub_s, tmp_path / "hub", hub_store)
        worker = WorkerArtifacts(worker_s, tmp_path / "worker", "sim-1")
        try:
            spec = {
                "checkpoint": str(tmp_path / "hub" / "runs" / "r1" / "best.pt"),
                "expert_episode_id": demo.id,
                "task": demo.task,
                "seed": 3,
            }
            inputs = hub.describe_inputs("plan", spec)
            assert inputs is not None
            manifest = msgspec.json.decode(hub.cache.blob_path(inputs).read_bytes(), type=InputManifest)
            assert sorted(f.path for f in manifest.files) == ["runs/r1/best.decoder.pt", "runs/r1/best.pt"]
            assert [e.id for e in manifest.episodes] == [demo.id]
            local, root = worker.prepare({**spec, "inputs": inputs})
            assert root == str((tmp_path / "hub").resolve())
            assert local["checkpoint"] == str((tmp_path / "worker").resolve() / "runs" / "r1" / "best.pt")
            for name, digest in (("best.pt", ck), ("best.decoder.pt", dec)):
                got = (tmp_path / "worker" / "runs" / "r1" / name).read_bytes()
                assert hashlib.sha256(got).hexdigest() == digest
            assert worker.store().get(demo.id).task == demo.task
            before = len(hub.server.served)
            worker.prepare({**spec, "inputs": inputs})
            assert len(hub.server.served) == before  # everything is cached by id on the worker
        finally:
            worker.close()
            hub.close()


@pytest.mark.parametrize("path", ["../x.npz", "/etc/passwd", "plans/../../x", "plans//x", "plans/./x", "."])
def test_an_offer_naming_a_path_that_leaves_the_data_dir_is_not_a_message(path):
    offer = msg.encode(msg.BlobOffer(holder="sim-1", blob="a" * 64, size=1, path=path))  # not checked here
    with pytest.raises(msg.ProtocolError):
        msg.decode(offer)


def test_a_manifest_naming_a_file_outside_the_input_dirs_is_refused_before_anything_is_fetched(
    sessions, tmp_path
):
    hub_s, worker_s = sessions
    with EpisodeStore(tmp_path / "hub") as hub_store:
        hub = HubArtifacts(hub_s, tmp_path / "hub", hub_store)
        worker = WorkerArtifacts(worker_s, tmp_path / "worker", "sim-1")
        try:
            (tmp_path / "worker" / "catalog.sqlite").write_bytes(b"the worker's own")
            blob = _file(tmp_path / "hub" / "runs" / "evil.bin", 100)
            hub.cache.publish(tmp_path / "hub" / "runs" / "evil.bin")
            manifest = InputManifest(
                root=str(tmp_path / "hub"), files=[FileRef(path="catalog.sqlite", blob=blob, size=100)]
            )
            inputs = hub.cache.keep_bytes(msgspec.json.encode(manifest))
            with pytest.raises(TransferError, match=r"not at catalog\.sqlite"):
                worker.prepare({"checkpoint": "oracle", "inputs": inputs})
            assert (tmp_path / "worker" / "catalog.sqlite").read_bytes() == b"the worker's own"
            assert not worker.cache.has(blob)
        finally:
            worker.close()
            hub.close()


def test_a_shipped_policy_named_by_the_hubs_installation_is_the_workers_own_copy(sessions, tmp_path):
    hub_s, worker_s = sessions
    with EpisodeStore(tmp_path / "hub") as hub_store:
        demo = hub_store.add_episode(make_recording(seed=1), role="expert", source="teleop")
        hub = HubArtifacts(hub_s, tmp_path / "hub", hub_store)
        worker = WorkerArtifacts(worker_s, tmp_path / "worker", "sim-1")
        try:
            policy = SHIPPED_POLICY_DIR.resolve() / "some-policy.pt"
            spec = {"checkpoint": str(policy), "expert_episode_id": demo.id, "task": demo.task, "seed": 3}
            inputs = hub.describe_inputs("plan", spec)
            assert inputs is not None
            manifest = msgspec.json.decode(hub.cache.blob_path(inputs).read_bytes(), type=InputManifest)
            assert manifest.files == [] and manifest.shipped == str(SHIPPED_POLICY_DIR.resolve())
            # as if the hub's installation were elsewhere: its path is read as this worker's installation
            moved = msgspec.structs.replace(manifest, shipped="/opt/hub-install/studio/policies")
            other = hub.cache.keep_bytes(msgspec.json.encode(moved))
            hub_spec = {
                **spec,
                "checkpoint": "/opt/hub-install/studio/policies/some-policy.pt",
                "inputs": other,
            }
            local, _ = worker.prepare(hub_spec)
            assert local["checkpoint"] == str(policy)
        finally:
            worker.close()
            hub.close()
