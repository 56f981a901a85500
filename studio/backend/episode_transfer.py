"""How an episode recorded on a worker reaches the store: a shared data directory, or chunks over the bus.

* A worker started with ``--data-dir`` (the embedded default: same machine, same directory) stores
  episodes itself with :class:`studio.data.store.EpisodeStore`, which is safe for concurrent writers.
* A worker without one ships each episode to the hub: the recording is encoded as a
  :class:`~studio.backend.messages.RecordingPayload`, written to a local *spool* file first, then sent as
  :class:`~studio.backend.messages.EpisodeChunk` queries (each acknowledged, so a slow link just slows
  the transfer) and an :class:`~studio.backend.messages.EpisodeCommit` carrying the SHA-256 of the whole.
  The hub's :class:`EpisodeSink` verifies it and adds it to its store. The spool file is deleted only
  after the hub confirmed the episode; if the hub is unreachable it stays and is retried, so a recording
  is never lost to a network problem.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import secrets
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.data.atomic_files import atomic_write
from studio.sim.camera import CameraModel
from studio.sim.recording import Recording

if TYPE_CHECKING:
    from studio.data.store import EpisodeStore

CHUNK_BYTES = 1 << 20
#: Bounds of what the hub holds of transfers not yet committed (see :class:`EpisodeSink`).
MAX_UNCOMMITTED_BYTES = 256 << 20
MAX_TRANSFER_BYTES = 160 << 20
MAX_TRANSFER_CHUNKS = 256
MAX_TRANSFERS = 8
STALE_S = 30.0
#: Where an episode came from: the values :class:`~studio.backend.messages.EpisodeCommit` accepts.
EpisodeSource = Literal["scripted", "teleop", "rollout"]


def recording_payload(rec: Recording) -> msg.RecordingPayload:
    return msg.RecordingPayload(
        scene=rec.scene,
        robot=rec.robot,
        task=rec.task,
        seed=int(rec.seed),
        success=bool(rec.success),
        camera=rec.camera.to_dict(),
        control_dt=float(rec.control_dt),
        object_names=tuple(rec.object_names),
        frames=msg.ArrayData.of(rec.frames),
        frame_steps=msg.ArrayData.of(np.asarray(rec.frame_steps, np.int64)),
        arrays={k: msg.ArrayData.of(np.asarray(v)) for k, v in rec.arrays.items()},
    )


def payload_recording(p: msg.RecordingPayload) -> Recording:
    """Back to a :class:`Recording`; raises ValueError if the payload is inconsistent."""
    try:
        camera = CameraModel.from_dict(p.camera)
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"RecordingPayload.camera is not a camera model: {e}") from None
    return Recording(
        scene=p.scene,
        robot=p.robot,
        task=p.task,
        seed=p.seed,
        success=p.success,
        camera=camera,
        frames=p.frames.to_array(),
        frame_steps=p.frame_steps.to_array(),
        arrays={k: v.to_array() for k, v in p.arrays.items()},
        object_names=list(p.object_names),
        control_dt=p.control_dt,
    )


# ---------------------------------------------------------------------------------------------- hub side
@dataclass
class _Incoming:
    count: int
    chunks: dict[int, bytes] = field(default_factory=dict)
    size: int = 0
    touched: float = field(default_factory=time.monotonic)


class EpisodeSink:
    """The hub's end of episode shipping: reassembles transfers and adds them to ``store``.

    ``store`` is a :class:`studio.data.store.EpisodeStore` (anything with its ``add_episode``). Uncommitted
    chunks are held in memory within bounds: ``max_bytes`` in all, ``max_transfer_bytes`` and
    ``max_chunks`` per transfer, ``max_transfers`` transfers at once (beyond them a chunk is answered
    ``busy`` or ``bad_request``); a partial transfer idle for ``stale_s`` is dropped (the worker still holds
    its spool file and sends it again).
    """

    def __init__(
        self,
        session: zenoh.Session,
        store: Any,
        *,
        max_bytes: int = MAX_UNCOMMITTED_BYTES,
        max_transfer_bytes: int = MAX_TRANSFER_BYTES,
        max_chunks: int = MAX_TRANSFER_CHUNKS,
        max_transfers: int = MAX_TRANSFERS,
        stale_s: float = STALE_S,
    ):
        self.store = store
        self.max_bytes = max_bytes
        self.max_transfer_bytes = max_transfer_bytes
        self.max_chunks = max_chunks
        self.max_transfers = max_transfers
        self.stale_s = stale_s
        self._lock = threading.Lock()
        self._incoming: dict[str, _Incoming] = {}
        self._held = 0  # bytes of uncommitted chunks
        self._done: OrderedDict[str, str] = OrderedDict()  # transfer -> episode id (answers a retried commit)
        self._stop = threading.Event()
        self._queryable = bus.declare_queryable(
            session,
            keys.ALL_UPLOADS,
            self._on_request,
            (msg.EpisodeChunk, msg.EpisodeCommit),
            max_bytes=CHUNK_BYTES + (64 << 10),
        )
        self._sweeper = threading.Thread(target=self._sweep_loop, name="episode-sink-expiry", daemon=True)
        self._sweeper.start()

    def close(self) -> None:
        self._stop.set()
        with contextlib.suppress(zenoh.ZError):
            self._queryable.undeclare()
        with self._lock:
            self._incoming.clear()
            self._held = 0

    @property
    def held_bytes(self) -> int:
        """Bytes of uncommitted chunks held now."""
        with self._lock:
            return self._held

    def _sweep_loop(self) -> None:
        while not self._stop.wait(min(5.0, self.stale_s / 2)):
            with self._lock:
                self._expire_locked(time.monotonic())

    def _expire_locked(self, now: float) -> None:
        for t in [t for t, inc in self._incoming.items() if now - inc.touched > self.stale_s]:
            self._held -= self._incoming.pop(t).size

    def _on_request(self, request: msg.Message, query: zenoh.Query) -> msg.Message:
        transfer = keys.parse_upload_key(str(query.key_expr))
        if getattr(request, "transfer", None) != transfer:
            return msg.ErrorReply(code="bad_request", message="transfer id differs from the key")
        if isinstance(request, msg.EpisodeChunk):
            return self._chunk(request)
        assert isinstance(request, msg.EpisodeCommit)  # the queryable decodes only these two types
        return self._commit(request)

    def _chunk(self, chunk: msg.EpisodeChunk) -> msg.Message:
        if chunk.count > self.max_chunks:
            return msg.ErrorReply(
                code="bad_request",
                message=f"a transfer has at most {self.max_chunks} chunks, not {chunk.count}",
            )
        if len(chunk.data) > CHUNK_BYTES:
            return msg.ErrorReply(code="bad_request", message=f"a chunk holds at most {CHUNK_BYTES} bytes")
        now = time.monotonic()
        with self._lock:
            self._expire_locked(now)
            inc = self._incoming.get(chunk.transfer)
            if inc is None:
                if len(self._incoming) >= self.max_transfers:
                    return msg.ErrorReply(
                        code="busy", message=f"the store host receives {self.max_transfers} transfers already"
                    )
                inc = self._incoming[chunk.transfer] = _Incoming(count=chunk.count)
            if inc.count != chunk.count:
                return msg.ErrorReply(
                    code="bad_request", message=f"chunk count changed from {inc.count} to {chunk.count}"
                )
            if chunk.index not in inc.chunks:
                if inc.size + len(chunk.data) > self.max_transfer_bytes:
                    return msg.ErrorReply(
                        code="bad_request",
                        message=f"a transfer holds at most {self.max_transfer_bytes} bytes",
                    )
                if self._held + len(chunk.data) > self.max_bytes:
                    return msg.ErrorReply(
                        code="busy", message="the store host holds too many unfinished transfers"
                    )
                inc.chunks[chunk.index] = chunk.data
                inc.size += len(chunk.data)
                self._held += len(chunk.data)
            inc.touched = now
        return msg.ChunkAck(transfer=chunk.transfer, index=chunk.index)

    def _commit(self, commit: msg.EpisodeCommit) -> msg.Message:
        from studio.data.store import StoreError

        with self._lock:
            if commit.transfer in self._done:
                return msg.EpisodeStored(transfer=commit.transfer, episode=self._done[commit.transfer])
            inc = self._incoming.get(commit.transfer)
            if inc is None or len(inc.chunks) != commit.count or inc.count != commit.count:
                have = 0 if inc is None else len(inc.chunks)
                return msg.ErrorReply(
                    code="conflict", message=f"have {have} of {commit.count} chunks; resend them"
                )
            data = b"".join(inc.chunks[i] for i in range(commit.count))
            del self._incoming[commit.transfer]
            self._held -= inc.size
        if hashlib.sha256(data).hexdigest() != commit.sha256:
            return msg.ErrorReply(code="bad_request", message="SHA-256 mismatch; resend the episode")
        try:
            payload = msg.decode(data, msg.RecordingPayload)
            recording = payload_recording(payload)
        except (msg.ProtocolError, ValueError) as e:
            return msg.ErrorReply(code="bad_request", message=f"not a valid recording: {e}")
        extra = dict(commit.extra)
        extra.setdefault("transfer", commit.transfer)
        try:
            meta = self.store.add_episode(
                recording, role=commit.role, source=commit.source, embodiment=commit.embodiment, extra=extra
            )
        except (ValueError, StoreError) as e:  # the store refuses it (an unknown embodiment, a filled slot)
            return msg.ErrorReply(
                code="bad_request", message=f"the store refused the episode: {bus.one_line(e)}"
            )
        with self._lock:
            self._done[commit.transfer] = meta.id
            while len(self._done) > 1000:
                self._done.popitem(last=False)
        return msg.EpisodeStored(transfer=commit.transfer, episode=meta.id)


# ---------------------------------------------------------------------------------------------- worker side
class ShipError(RuntimeError):
    """An episode could not be delivered yet; it waits in the spool (``kept_at``)."""

    def __init__(self, text: str, kept_at: Path):
        super().__init__(f"{text} (kept at {kept_at}; retried automatically)")
        self.kept_at = kept_at


class EpisodeShipper:
    """Sends recordings to the hub's :class:`EpisodeSink`, through a spool directory that survives failures.

    A spooled transfer is two files: ``<transfer>.payload`` (the encoded RecordingPayload) and
    ``<transfer>.commit`` (the encoded EpisodeCommit), the latter written last, atomically. Every
    ``retry_s`` seconds (and at start) spooled transfers are sent again; a file lock keeps two workers
    sharing a spool directory from sending the same one twice.
    """

    def __init__(
        self,
        session: zenoh.Session,
        spool_dir: str | os.PathLike,
        *,
        chunk_bytes: int = CHUNK_BYTES,
        timeout_s: float = 10.0,
        retry_s: float = 10.0,
    ):
        self.session = session
        self.spool_dir = Path(spool_dir)
        self.spool_dir.mkdir(parents=True, exist_ok=True)
        self.chunk_bytes = chunk_bytes
        self.timeout_s = timeout_s
        self.retry_s = retry_s
        self._stop = threading.Event()
        self._send_lock = threading.Lock()
        self._active: set[str] = set()
        self._active_lock = threading.Lock()
        self._thread = threading.Thread(target=self._retry_loop, name="episode-shipper", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(self.timeout_s + 1.0)

    def ship(
        self,
        recording: Recording,
        *,
        role: msg.Role,
        source: EpisodeSource,
        embodiment: str | None = None,
        extra: dict[str, Any] | None = None,
    ) -> str:
        """Deliver ``recording`` and return its episode id; raises :class:`ShipError` if it stays spooled."""
        transfer = f"{int(time.time())}-{secrets.token_hex(6)}"
        payload = msg.encode(recording_payload(recording))
        count = max(1, -(-len(payload) // self.chunk_bytes))
        commit = msg.EpisodeCommit(
            transfer=transfer,
            count=count,
            sha256=hashlib.sha256(payload).hexdigest(),
            role=role,
            source=source,
            embodiment=embodiment,
            extra=dict(extra or {}),
        )
        base = self.spool_dir / transfer
        with self._active_lock:
            self._active.add(transfer)
        try:
            atomic_write(base.with_suffix(".payload"), payload)
            atomic_write(base.with_suffix(".commit"), msg.encode(commit))
            return self._send_spooled(base)
        finally:
            with self._active_lock:
                self._active.discard(transfer)

    def pending(self) -> list[Path]:
        return sorted(self.spool_dir.glob("*.commit"))

    def _send_spooled(self, base: Path) -> str:
        lock_path = base.with_suffix(".lock")
        fd = os.open(lock_path, os.O_CREAT | os.O_RDWR, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise ShipError(
                    "another process is sending this episode", base.with_suffix(".payload")
                ) from None
            if not base.with_suffix(".commit").exists():
                raise ShipError("already delivered by another process", base.with_suffix(".payload"))
            try:
                commit = msg.decode(base.with_suffix(".commit").read_bytes(), msg.EpisodeCommit)
                payload = base.with_suffix(".payload").read_bytes()
            except (OSError, msg.ProtocolError) as e:
                raise ShipError(f"spooled episode is unreadable: {e}", base.with_suffix(".payload")) from None
            key = keys.upload_key(commit.transfer)
            try:
                with self._send_lock:
                    for i in range(commit.count):
                        part = payload[i * self.chunk_bytes : (i + 1) * self.chunk_bytes]
                        chunk = msg.EpisodeChunk(
                            transfer=commit.transfer, index=i, count=commit.count, data=part
                        )
                        bus.request(self.session, key, chunk, msg.ChunkAck, timeout=self.timeout_s)
                    stored = bus.request(
                        self.session, key, commit, msg.EpisodeStored, timeout=self.timeout_s * 3
                    )
            except bus.BusError as e:
                raise ShipError(
                    f"could not ship the episode to the hub's store: {e}", base.with_suffix(".payload")
                ) from None
            base.with_suffix(".commit").unlink(missing_ok=True)
            base.with_suffix(".payload").unlink(missing_ok=True)
            return stored.episode
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(lock_path)
            os.close(fd)

    def _retry_loop(self) -> None:
        delay = 0.0  # first pass at start-up, then every retry_s
        while not self._stop.wait(delay):
            delay = self.retry_s
            for commit_path in self.pending():
                if self._stop.is_set():
                    return
                with self._active_lock:
                    if commit_path.stem in self._active:
                        continue  # ship() is sending it right now
                try:
                    episode = self._send_spooled(commit_path.with_suffix(""))
                    bus.log.info("delivered spooled episode %s as %s", commit_path.stem, episode)
                except ShipError as e:
                    bus.log.debug("spooled episode %s still pending: %s", commit_path.stem, e)


class EpisodeDestination:
    """Where a worker's recordings go: its own store (``data_dir``) or the hub over the bus (``shipper``)."""

    def __init__(self, *, data_dir: str | os.PathLike | None = None, shipper: EpisodeShipper | None = None):
        if (data_dir is None) == (shipper is None):
            raise ValueError("EpisodeDestination needs exactly one of data_dir or shipper")
        self.data_dir = None if data_dir is None else Path(data_dir)
        self.shipper = shipper
        self._store: EpisodeStore | None = None
        self._lock = threading.Lock()

    @property
    def via(self) -> Literal["data-dir", "bus"]:
        return "data-dir" if self.data_dir is not None else "bus"

    def save(
        self,
        recording: Recording,
        *,
        role: msg.Role,
        source: EpisodeSource,
        extra: dict[str, Any] | None = None,
    ) -> str:
        """Store the recording; returns the episode id. Raises ShipError (bus) or StoreError (local)."""
        if self.shipper is not None:
            return self.shipper.ship(recording, role=role, source=source, extra=extra)
        with self._lock:
            if self._store is None:
                from studio.data.store import EpisodeStore

                self._store = EpisodeStore(self.data_dir)
            meta = self._store.add_episode(recording, role=role, source=source, extra=dict(extra or {}))
        return meta.id

    def close(self) -> None:
        if self._store is not None:
            self._store.close()
        if self.shipper is not None:
            self.shipper.close()
