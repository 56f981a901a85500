"""How a job's files move between data directories over the bus, so that workers need no shared disk.

Files travel by *content id* (the hex SHA-256 of their bytes):

* every holder of files — the hub, and a worker that keeps its own data directory — serves them on
  ``studio/blobs/<holder>/<content id>`` (:class:`BlobServer`): a :class:`~studio.backend.messages.BlobGet` for
  piece ``index`` is answered with a :class:`~studio.backend.messages.BlobPart` carrying that piece (1 MiB, as
  episode shipping's chunks) and the piece's own SHA-256;
* a fetcher (:class:`BlobFetcher`) asks for the pieces in order, checks each piece's digest (a corrupt piece is
  asked again), appends it to ``<data-dir>/artifacts/partial/<id>`` (so an interrupted fetch resumes where it
  stopped), refuses content larger than its cap before writing anything, checks the SHA-256 of the whole and only
  then moves it, atomically, into the content-addressed cache ``<data-dir>/artifacts/blobs/<id>`` — content already
  there is never fetched again;
* a file is *placed* at a path of the data directory by copying it from the cache through a temporary file renamed
  over the path.

A job submitted through the hub's :class:`ArtifactJobClient` carries ``inputs``: the content id of a
:class:`InputManifest` listing the files (checkpoints and their decoders, a run directory, a split file) and the
stored episodes it reads, with their content ids. A worker started with ``--own-data-dir``
(:class:`WorkerArtifacts`) fetches what it lacks into its own data directory before the job runs, reads the spec's
paths in the hub's data directory as the same paths in its own, and afterwards offers what the job wrote to the hub
(:class:`~studio.backend.messages.BlobOffer`, :class:`~studio.backend.messages.EpisodeOffer`): the hub
(:class:`HubArtifacts`) fetches it from the worker by content id and keeps it at the same path of its data directory,
or adds the episode to its store byte for byte, so the UI reads plans, checkpoints and rollouts where it always did.
Received bytes are only ever checked, copied and renamed here; checkpoints are loaded weights-only by the model.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import threading
from pathlib import Path
from typing import Annotated, Any

import msgspec
import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.episode_transfer import CHUNK_BYTES
from studio.backend.job_client import JobClient
from studio.data.atomic_files import atomic_write, fsync_path
from studio.data.paths import SHIPPED_POLICY_DIR

#: The holder name of the hub's data directory.
HUB_HOLDER = "hub"
#: The hub's queryables for offers of a job's outputs and for descriptions of a job's inputs.
OFFER_KEY = f"{keys.ROOT}/store/artifacts"
INPUTS_KEY = f"{keys.ROOT}/store/inputs"
ARTIFACTS_DIR = "artifacts"
#: Largest file fetched by default (a checkpoint of the paper's model is far below it).
MAX_BLOB_BYTES = 4 << 30
#: Largest input manifest, and the most files and episodes one lists.
MAX_MANIFEST_BYTES = 16 << 20
MAX_INPUT_FILES = 4096
MAX_INPUT_EPISODES = 100_000
#: Where offered outputs may land in the hub's data directory.
OUTPUT_DIRS = ("runs", "plans", "rollouts")
#: Where the files a job reads (checkpoints, run directories, split files) may be, besides stored episodes.
INPUT_DIRS = ("runs",)
#: Offers the hub works on at once (beyond: ``busy``).
MAX_OFFERS = 4
_READ_BYTES = 1 << 20
_PIECE_TRIES = 3


class TransferError(RuntimeError):
    """Content could not be fetched, checked or placed; the message says which and why in one line."""


class FileRef(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A file by content: its path relative to a data directory, content id and size."""

    path: msg.DataPath
    blob: msg.ContentId
    size: Annotated[int, msgspec.Meta(ge=0)]


class EpisodeFiles(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A stored episode by content: its id and its files (paths are the file names in its directory)."""

    id: Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")]
    files: Annotated[list[FileRef], msgspec.Meta(max_length=8)]


class InputManifest(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """What a job reads, by content. ``root`` is the data directory of the hub that described it: a spec path
    inside it means the same path inside a worker's own data directory. ``shipped`` is where the hub's installation
    keeps the policies shipped with the studio: a path there means the worker's own copy of that policy."""

    root: Annotated[str, msgspec.Meta(min_length=1, max_length=4096)]
    files: Annotated[list[FileRef], msgspec.Meta(max_length=MAX_INPUT_FILES)] = []
    episodes: Annotated[list[EpisodeFiles], msgspec.Meta(max_length=MAX_INPUT_EPISODES)] = []
    shipped: Annotated[str, msgspec.Meta(max_length=4096)] = ""


def blob_key(holder: str, blob: str) -> str:
    return f"{keys.ROOT}/blobs/{keys.check_chunk(holder, 'holder')}/{keys.check_chunk(blob, 'content id')}"


def file_digest(path: Path) -> tuple[str, int]:
    """(content id, size) of the file at ``path``."""
    h = hashlib.sha256()
    size = 0
    with open(path, "rb") as f:
        while block := f.read(_READ_BYTES):
            h.update(block)
            size += len(block)
    return h.hexdigest(), size


def _copy_atomically(src: Path, dest: Path) -> None:
    """``dest`` becomes a durable copy of ``src`` in one rename (a reader never sees half of it)."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    with open(src, "rb") as fin:
        atomic_write(dest, lambda fout: shutil.copyfileobj(fin, fout, _READ_BYTES))


def data_path(data_dir: Path, rel: str) -> Path:
    """``rel`` (a :data:`~studio.backend.messages.DataPath`) inside ``data_dir``; ``TransferError`` if it resolves
    outside (a symbolic link on the way included)."""
    root = data_dir.resolve()
    path = (root / rel).resolve()
    if path == root or root not in path.parents:
        raise TransferError(f"the path {rel} resolves to {path}, outside the data dir {root}")
    return path


class BlobCache:
    """The content-addressed files of one data directory, and the files it *publishes* in place.

    Fetched content is kept in ``<data-dir>/artifacts/blobs/<id>`` (written once, never changed). A published file
    stays where it is; it is served while its size and modification time are those it had when published (changed
    since, it is hashed again and served only if its content is still the same).
    """

    def __init__(self, data_dir: str | os.PathLike):
        self.data_dir = Path(data_dir).resolve()
        self.blobs_dir = self.data_dir / ARTIFACTS_DIR / "blobs"
        self.partial_dir = self.data_dir / ARTIFACTS_DIR / "partial"
        for d in (self.blobs_dir, self.partial_dir):
            d.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._published: dict[str, tuple[Path, int, int]] = {}  # id -> (path, size, mtime_ns)
        self._digests: dict[tuple[str, int, int], str] = {}  # (path, size, mtime_ns) -> id

    def blob_path(self, blob: str) -> Path:
        return self.blobs_dir / keys.check_chunk(blob, "content id")

    def partial_path(self, blob: str) -> Path:
        return self.partial_dir / keys.check_chunk(blob, "content id")

    def publish(self, path: Path) -> FileRef:
        """Serve the file at ``path`` (inside the data dir) by its content id; returns its reference."""
        path = Path(path).resolve()
        rel = path.relative_to(self.data_dir).as_posix()
        st = path.stat()
        stamp = (str(path), st.st_size, st.st_mtime_ns)
        with self._lock:
            blob = self._digests.get(stamp)
        if blob is None:
            blob, size = file_digest(path)
            if size != st.st_size:
                raise TransferError(f"{path} changed while it was read")
        with self._lock:
            self._digests[stamp] = blob
            self._published[blob] = (path, st.st_size, st.st_mtime_ns)
        return FileRef(path=rel, blob=blob, size=st.st_size)

    def source(self, blob: str) -> tuple[Path, int] | None:
        """Where content ``blob`` can be read now and its size, or None if this data dir does not hold it."""
        cached = self.blob_path(blob)
        with contextlib.suppress(FileNotFoundError):
            return cached, cached.stat().st_size
        with self._lock:
            entry = self._published.get(blob)
        if entry is None:
            return None
        path, size, mtime = entry
        try:
            st = path.stat()
        except FileNotFoundError:
            return None
        if (st.st_size, st.st_mtime_ns) != (size, mtime):
            if file_digest(path)[0] != blob:
                with self._lock:
                    self._published.pop(blob, None)
                return None
            with self._lock:
                self._published[blob] = (path, st.st_size, st.st_mtime_ns)
        return path, st.st_size

    def has(self, blob: str) -> bool:
        return self.blob_path(blob).is_file()

    def keep(self, path: Path) -> str:
        """Copy the file at ``path`` into the cache; returns its content id."""
        blob, _ = file_digest(path)
        if not self.has(blob):
            _copy_atomically(path, self.blob_path(blob))
        return blob

    def keep_bytes(self, data: bytes) -> str:
        """Keep ``data`` in the cache; returns its content id."""
        blob = hashlib.sha256(data).hexdigest()
        if not self.has(blob):
            atomic_write(self.blob_path(blob), data)
        return blob

    def place(self, blob: str, dest: Path) -> bool:
        """Make ``dest`` hold content ``blob`` (from the cache); False when it already did."""
        if dest.is_file():
            st = dest.stat()
            if st.st_size == self.blob_path(blob).stat().st_size and file_digest(dest)[0] == blob:
                return False
        _copy_atomically(self.blob_path(blob), dest)
        return True


class BlobServer:
    """Answers :class:`~studio.backend.messages.BlobGet` for the content of ``cache`` as holder ``holder``."""

    def __init__(
        self, session: zenoh.Session, cache: BlobCache, holder: str, *, chunk_bytes: int = CHUNK_BYTES
    ):
        self.cache = cache
        self.holder = holder
        self.chunk_bytes = chunk_bytes
        self.served: list[tuple[str, int]] = []  # (content id, piece) answered, newest last (bounded)
        self._queryable = bus.declare_queryable(
            session, f"{keys.ROOT}/blobs/{keys.check_chunk(holder, 'holder')}/*", self._on_get, msg.BlobGet
        )

    def close(self) -> None:
        with contextlib.suppress(zenoh.ZError):
            self._queryable.undeclare()

    def piece(self, blob: str, index: int) -> msg.Message:
        found = self.cache.source(blob)
        if found is None:
            return msg.ErrorReply(code="not_found", message=f"{self.holder} holds no content {blob}")
        path, size = found
        count = max(1, -(-size // self.chunk_bytes))
        if index >= count:
            return msg.ErrorReply(
                code="bad_request", message=f"content {blob} has {count} pieces, not {index + 1}"
            )
        with open(path, "rb") as f:
            f.seek(index * self.chunk_bytes)
            data = f.read(self.chunk_bytes)
        self.served.append((blob, index))
        del self.served[:-1000]
        digest = hashlib.sha256(data).hexdigest()
        return msg.BlobPart(blob=blob, index=index, count=count, size=size, digest=digest, data=data)

    def _on_get(self, request: msg.BlobGet, query: zenoh.Query) -> msg.Message:
        if str(query.key_expr).rsplit("/", 1)[-1] != request.blob:
            return msg.ErrorReply(code="bad_request", message="content id differs from the key")
        return self.piece(request.blob, request.index)


class BlobFetcher:
    """Fetches content by id from a holder into ``cache`` (see the module docstring for the checks)."""

    def __init__(
        self,
        session: zenoh.Session,
        cache: BlobCache,
        *,
        chunk_bytes: int = CHUNK_BYTES,
        max_bytes: int = MAX_BLOB_BYTES,
        timeout_s: float = 10.0,
    ):
        self.session = session
        self.cache = cache
        self.chunk_bytes = chunk_bytes
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s
        self._locks: dict[str, threading.Lock] = {}
        self._locks_lock = threading.Lock()

    def fetch(
        self, holder: str, blob: str, *, max_bytes: int | None = None, stop_after: int | None = None
    ) -> Path:
        """The cached file of content ``blob``, fetched from ``holder`` if the cache lacks it.

        ``max_bytes`` caps the size (default: the fetcher's); ``stop_after`` stops after that many pieces were
        received in this call, leaving the fetch to be resumed (for tests of interruption). Raises
        :class:`TransferError`.
        """
        keys.check_chunk(blob, "content id")
        with self._locks_lock:
            lock = self._locks.setdefault(blob, threading.Lock())
        with lock:
            if self.cache.has(blob):
                return self.cache.blob_path(blob)
            return self._fetch_locked(holder, blob, max_bytes or self.max_bytes, stop_after)

    def _get(self, holder: str, blob: str, index: int) -> msg.BlobPart:
        problem = ""
        for _ in range(_PIECE_TRIES):
            try:
                part = bus.request(
                    self.session,
                    blob_key(holder, blob),
                    msg.BlobGet(blob=blob, index=index),
                    msg.BlobPart,
                    timeout=self.timeout_s,
                )
            except bus.BusError as e:
                problem = bus.one_line(e)
                if isinstance(e, bus.RemoteError):
                    break
                continue
            if part.blob != blob or part.index != index:
                problem = f"{holder} answered piece {part.index} of {part.blob} for piece {index} of {blob}"
            elif hashlib.sha256(part.data).hexdigest() != part.digest:
                problem = f"piece {index} of {blob} from {holder} does not match its digest"
            else:
                return part
        raise TransferError(f"cannot fetch content {blob} from {holder}: {problem}")

    def _fetch_locked(self, holder: str, blob: str, max_bytes: int, stop_after: int | None) -> Path:
        partial = self.cache.partial_path(blob)
        have = partial.stat().st_size if partial.exists() else 0
        start = max(
            0, (have - 1) // self.chunk_bytes
        )  # the last piece kept is asked again: it may be the end
        received = 0
        with open(partial, "ab") as out:
            out.truncate(start * self.chunk_bytes)  # a piece written only in part is asked again
            index, count, size = start, -1, -1  # known from the first piece
            while count < 0 or index < count:
                part = self._get(holder, blob, index)
                if part.size > max_bytes:
                    raise TransferError(
                        f"content {blob} has {part.size} bytes, more than the {max_bytes} allowed"
                    )
                if count < 0:
                    count, size = part.count, part.size
                    if count != max(1, -(-size // self.chunk_bytes)):
                        raise TransferError(f"{holder} cuts content {blob} into pieces of another size")
                if (part.count, part.size) != (count, size):
                    raise TransferError(f"content {blob} changed size on {holder} during the fetch")
                expected = min(self.chunk_bytes, size - index * self.chunk_bytes)
                if len(part.data) != expected:
                    raise TransferError(f"piece {index} of {blob} has {len(part.data)} bytes, not {expected}")
                out.write(part.data)
                index += 1
                received += 1
                if stop_after is not None and received >= stop_after and index < count:
                    out.flush()
                    raise TransferError(f"fetch of {blob} stopped after {index} of {count} pieces")
            out.flush()
            os.fsync(out.fileno())
        got, got_size = file_digest(partial)
        if got != blob:
            partial.unlink(missing_ok=True)
            raise TransferError(
                f"content {blob} from {holder} arrived as {got} ({got_size} bytes); fetch it again"
            )
        os.chmod(partial, 0o444)
        os.replace(partial, self.cache.blob_path(blob))
        fsync_path(self.cache.blobs_dir, directory=True)
        return self.cache.blob_path(blob)


# ---------------------------------------------------------------------------------------------- job inputs
def _path_values(kind: str, spec: dict[str, Any]) -> tuple[list[str], list[str], list[str] | None]:
    """(directories, checkpoints and plain files, episode ids or None for every stored one) a spec of ``kind``
    reads; values that are not paths (``"oracle"``, a scene name) are left for the worker to resolve."""

    def text(key: str) -> list[str]:
        value = spec.get(key)
        return [value] if isinstance(value, str) and value else []

    if kind == "train":
        scene = [s for s in text("scene") if "/" in s or s.endswith(".json")]
        return text("run_dir"), scene + text("init"), None
    if kind in ("plan", "rollout"):
        return [], text("checkpoint"), text("expert_episode_id")
    if kind == "compare":
        return [], text("a") + text("b"), None
    return [], [], []


def _checkpoint_companions(path: Path) -> list[Path]:
    """Files read with a checkpoint: its latent decoder (:func:`studio.eval.latents.find_decoder`'s places) and
    its demonstration-score calibration."""
    names = [
        path.parent / "decoder" / "best.pt",
        path.parent / "decoder" / "last.pt",
        path.parent / "decoder.pt",
        path.with_name(f"{path.stem}.decoder.pt"),
        path.with_name(f"{path.stem}.demo-score.npz"),
    ]
    return [p for p in names if p.is_file()]


def _files_under(directory: Path, limit: int) -> list[Path]:
    found: list[Path] = []
    for path in sorted(directory.rglob("*")):
        if path.is_file() and not path.is_symlink() and not path.name.startswith("."):
            found.append(path)
            if len(found) > limit:
                raise TransferError(f"{directory} holds more than {limit} files")
    return found


class HubArtifacts:
    """The hub's side: serves the content of its data directory that job specs name, describes a job's inputs,
    and takes the outputs workers offer (fetching them from the worker and keeping them in its data directory or
    its store). At most ``max_offers`` offers are worked on at once; an output is at most ``max_bytes``."""

    def __init__(
        self,
        session: zenoh.Session,
        data_dir: str | os.PathLike,
        store: Any,
        *,
        max_bytes: int = MAX_BLOB_BYTES,
        max_offers: int = MAX_OFFERS,
    ):
        self.cache = BlobCache(data_dir)
        self.data_dir = self.cache.data_dir
        self.store = store
        self.server = BlobServer(session, self.cache, HUB_HOLDER)
        self.fetcher = BlobFetcher(session, self.cache, max_bytes=max_bytes)
        self.max_offers = max_offers
        self._working = 0
        self._lock = threading.Lock()
        self._queryables = [
            bus.declare_queryable(session, OFFER_KEY, self._on_offer, (msg.BlobOffer, msg.EpisodeOffer)),
            bus.declare_queryable(session, INPUTS_KEY, self._on_describe, msg.DescribeInputs),
        ]

    def close(self) -> None:
        for q in self._queryables:
            with contextlib.suppress(zenoh.ZError):
                q.undeclare()
        self.server.close()

    # ------------------------------------------------------------------ inputs
    def describe_inputs(self, kind: str, spec: dict[str, Any]) -> str | None:
        """The content id of the :class:`InputManifest` of a ``kind`` job with ``spec`` (now served by the hub),
        or None for a kind that reads nothing from the data dir."""
        directories, files, episode_ids = _path_values(kind, spec)
        if not directories and not files and episode_ids == []:
            return None
        refs: dict[str, FileRef] = {}
        for value in directories + files:
            path = self._inside(value)
            if path is None:
                continue
            if path.is_dir():
                found = _files_under(path, MAX_INPUT_FILES)
            elif path.is_file():
                found = [path] + (
                    _checkpoint_companions(path) if value in files and path.suffix == ".pt" else []
                )
            else:
                continue
            for f in found:
                ref = self.cache.publish(f)
                refs[ref.path] = ref
        if episode_ids is None:
            metas = self.store.episodes()
        else:
            metas = [self.store.get(e) for e in episode_ids]
        episodes = []
        for meta in metas[:MAX_INPUT_EPISODES]:
            folder = self.store.episode_dir(meta.id)
            parts = [self.cache.publish(folder / name) for name in _episode_file_names()]
            episodes.append(
                EpisodeFiles(
                    id=meta.id,
                    files=[FileRef(path=Path(p.path).name, blob=p.blob, size=p.size) for p in parts],
                )
            )
        manifest = InputManifest(
            root=str(self.data_dir),
            files=list(refs.values())[:MAX_INPUT_FILES],
            episodes=episodes,
            shipped=str(SHIPPED_POLICY_DIR.resolve()),
        )
        return self.cache.keep_bytes(msgspec.json.encode(manifest))

    def _inside(self, value: str) -> Path | None:
        """The path ``value`` names if it lies in one of :data:`INPUT_DIRS` of the data dir (else the worker resolves
        it itself: ``"oracle"``, a shipped policy — or refuses it)."""
        if "\x00" in value:
            return None
        path = (self.data_dir / value).resolve()
        return path if any(self.data_dir / d in path.parents for d in INPUT_DIRS) else None

    def _on_describe(self, request: msg.DescribeInputs, _query: zenoh.Query) -> msg.Message:
        from studio.backend.job_runner import check_spec

        check_spec(request.kind, request.spec)  # a ValueError is answered bad_request
        try:
            return msg.InputsDescribed(inputs=self.describe_inputs(request.kind, request.spec))
        except (KeyError, TransferError) as e:
            return msg.ErrorReply(code="not_found", message=bus.one_line(e))

    # ------------------------------------------------------------------ outputs
    def _on_offer(self, offer: msg.Message, query: zenoh.Query) -> Any:
        with self._lock:
            if self._working >= self.max_offers:
                return msg.ErrorReply(
                    code="busy", message=f"the hub takes {self.max_offers} outputs at once already"
                )
            self._working += 1
        threading.Thread(target=self._answer, args=(offer, query), name="artifact-offer", daemon=True).start()
        return bus.DEFERRED

    def _answer(self, offer: msg.Message, query: zenoh.Query) -> None:
        try:
            answer: msg.Message
            try:
                answer = self.take(offer)
            except (TransferError, ValueError, OSError) as e:
                answer = msg.ErrorReply(code="bad_request", message=bus.one_line(e))
            with contextlib.suppress(zenoh.ZError):
                bus.reply(query, answer)
        finally:
            with contextlib.suppress(zenoh.ZError):
                query.drop()
            with self._lock:
                self._working -= 1

    def take(self, offer: msg.Message) -> msg.BlobStored:
        """Fetch an offered output from its holder and keep it; raises TransferError (or ValueError) saying why not."""
        if isinstance(offer, msg.BlobOffer):
            if offer.path.split("/", 1)[0] not in OUTPUT_DIRS or "/" not in offer.path:
                raise TransferError(f"outputs go under {', '.join(OUTPUT_DIRS)}/, not to {offer.path}")
            dest = data_path(self.data_dir, offer.path)
            self.fetcher.fetch(offer.holder, offer.blob, max_bytes=min(self.fetcher.max_bytes, offer.size))
            self.cache.place(offer.blob, dest)
            return msg.BlobStored(blob=offer.blob, path=offer.path)
        assert isinstance(offer, msg.EpisodeOffer)  # the queryable decodes only these two types
        return self._take_episode(offer)

    def _take_episode(self, offer: msg.EpisodeOffer) -> msg.BlobStored:
        from studio.data.catalog import RolloutRecord

        names = _episode_file_names()
        if set(offer.files) != set(names) or set(offer.sizes) != set(names):
            raise TransferError(
                f"an episode is the files {', '.join(names)}, not {', '.join(sorted(offer.files))}"
            )
        first = offer.files[names[0]]
        rel = f"episodes/{offer.episode}"
        if self.store.catalog.get_episode(offer.episode) is not None:
            return msg.BlobStored(blob=first, path=rel)  # a retried offer
        rollout = None
        if offer.rollout is not None:
            row = dict(offer.rollout)
            try:
                rollout = msgspec.convert(row, RolloutRecord)
            except msgspec.ValidationError as e:
                raise TransferError(f"not a rollout row: {e}") from None
            if rollout.path is not None:
                rollout.path = str(data_path(self.data_dir, rollout.path))
            if rollout.checkpoint_id is not None and not self.store.catalog.has_checkpoint(
                rollout.checkpoint_id
            ):
                rollout.checkpoint_id = None
        work = self.data_dir / ARTIFACTS_DIR / "import" / offer.episode
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        try:
            for name in names:
                blob = offer.files[name]
                self.fetcher.fetch(
                    offer.holder, blob, max_bytes=min(self.fetcher.max_bytes, offer.sizes[name])
                )
                shutil.copyfile(self.cache.blob_path(blob), work / name)
            from studio.data.episode import read_meta

            if read_meta(work)[0].id != offer.episode:
                raise TransferError(f"the offered episode's files are not those of episode {offer.episode}")
            self.store.add_episode_files(work, rollout=rollout)
        finally:
            shutil.rmtree(work, ignore_errors=True)
        return msg.BlobStored(blob=first, path=rel)


def _episode_file_names() -> tuple[str, ...]:
    from studio.data.episode import EPISODE_FILES

    return tuple(EPISODE_FILES)


class ArtifactJobClient(JobClient):
    """A job client whose jobs carry the content id of their inputs (``spec["inputs"]``), so that a worker with its
    own data directory can fetch them: described by ``artifacts`` in the hub's process, else asked of the hub."""

    def __init__(self, session: zenoh.Session, artifacts: HubArtifacts | None = None, timeout: float = 5.0):
        super().__init__(session, timeout)
        self.artifacts = artifacts

    def describe_inputs(self, kind: str, spec: dict[str, Any]) -> str | None:
        if self.artifacts is not None:
            return self.artifacts.describe_inputs(kind, spec)
        request = msg.DescribeInputs(kind=kind, spec=spec)
        return bus.request(
            self.session, INPUTS_KEY, request, msg.InputsDescribed, timeout=self.timeout * 6
        ).inputs

    def submit(self, kind: str, spec: dict[str, Any], **kwargs: Any) -> msg.JobStatus:
        if "inputs" not in spec:
            try:
                inputs = self.describe_inputs(kind, spec)
            except (OSError, KeyError, TransferError, bus.BusError) as e:
                bus.log.warning(
                    "%s job: its inputs cannot be described for remote workers: %s", kind, bus.one_line(e)
                )
                inputs = None
            if inputs is not None:
                spec = {**spec, "inputs": inputs}
        return super().submit(kind, spec, **kwargs)


# ---------------------------------------------------------------------------------------------- worker side
def translate_paths(value: Any, old: str, new: str) -> Any:
    """``value`` with every string that is ``old`` or a path under it rewritten to lie under ``new``."""
    if isinstance(value, str):
        if value == old:
            return new
        if value.startswith(old.rstrip("/") + "/"):
            return new.rstrip("/") + "/" + value[len(old.rstrip("/")) + 1 :]
        return value
    if isinstance(value, dict):
        return {k: translate_paths(v, old, new) for k, v in value.items()}
    if isinstance(value, list):
        return [translate_paths(v, old, new) for v in value]
    return value


class WorkerArtifacts:
    """A worker's side when its data directory is its own: fetches a job's inputs before it runs and offers the job's
    outputs to the hub, serving them meanwhile as holder ``holder`` (the worker's id)."""

    def __init__(
        self,
        session: zenoh.Session,
        data_dir: str | os.PathLike,
        holder: str,
        *,
        max_bytes: int = MAX_BLOB_BYTES,
        timeout_s: float = 10.0,
    ):
        self.session = session
        self.cache = BlobCache(data_dir)
        self.data_dir = self.cache.data_dir
        self.holder = holder
        self.timeout_s = timeout_s
        self.server = BlobServer(session, self.cache, holder)
        self.fetcher = BlobFetcher(session, self.cache, max_bytes=max_bytes, timeout_s=timeout_s)
        self._store: Any = None

    def close(self) -> None:
        self.server.close()
        if self._store is not None:
            self._store.close()

    def store(self) -> Any:
        if self._store is None:
            from studio.data.store import EpisodeStore

            self._store = EpisodeStore(self.data_dir)
        return self._store

    def prepare(self, spec: dict[str, Any]) -> tuple[dict[str, Any], str | None]:
        """Fetch what ``spec["inputs"]`` lists and lacks here; returns the spec with the hub's paths as this data
        dir's, and the hub's data dir (None when the spec names no inputs)."""
        inputs = spec.get("inputs")
        if not isinstance(inputs, str):
            return spec, None
        manifest_path = self.fetcher.fetch(HUB_HOLDER, inputs, max_bytes=MAX_MANIFEST_BYTES)
        try:
            manifest = msgspec.json.decode(manifest_path.read_bytes(), type=InputManifest)
        except msgspec.DecodeError as e:
            raise TransferError(f"the inputs {inputs} are not a manifest: {e}") from None
        for ref in manifest.files:
            if ref.path.split("/", 1)[0] not in INPUT_DIRS:
                raise TransferError(
                    f"a job's input files lie under {', '.join(INPUT_DIRS)}/, not at {ref.path}"
                )
        for ref in manifest.files:
            self._fetch_to(ref, data_path(self.data_dir, ref.path))
        for episode in manifest.episodes:
            store = self.store()
            if store.catalog.get_episode(episode.id) is not None:
                continue
            work = self.data_dir / ARTIFACTS_DIR / "import" / episode.id
            shutil.rmtree(work, ignore_errors=True)
            try:
                for ref in episode.files:
                    if ref.path not in _episode_file_names():
                        raise TransferError(f"episode {episode.id} lists a file {ref.path}")
                    self._fetch_to(ref, work / ref.path)
                from studio.data.episode import read_meta

                if read_meta(work)[0].id != episode.id:
                    raise TransferError(f"the files listed for episode {episode.id} are another episode's")
                store.add_episode_files(work)
            finally:
                shutil.rmtree(work, ignore_errors=True)
        local = translate_paths(spec, manifest.root, str(self.data_dir))
        if manifest.shipped:
            local = translate_paths(local, manifest.shipped, str(SHIPPED_POLICY_DIR.resolve()))
        return local, manifest.root

    def as_hub_path(self, value: Any, hub_data_dir: str) -> Any:
        """``value`` with this data dir's paths (strings, also inside dicts and lists) as the same in the hub's."""
        return translate_paths(value, str(self.data_dir), hub_data_dir)

    def _fetch_to(self, ref: FileRef, dest: Path) -> None:
        self.fetcher.fetch(HUB_HOLDER, ref.blob, max_bytes=min(self.fetcher.max_bytes, ref.size))
        self.cache.place(ref.blob, dest)

    def _offer(self, offer: msg.Message, size: int) -> msg.BlobStored:
        timeout = self.timeout_s * 3 + size / (
            1 << 20
        )  # the hub fetches it meanwhile: a second per MiB at least
        try:
            return bus.request(self.session, OFFER_KEY, offer, msg.BlobStored, timeout=timeout)
        except bus.BusError as e:
            raise TransferError(f"the hub did not take {type(offer).__name__}: {bus.one_line(e)}") from None

    def offer(self, path: str | os.PathLike) -> list[str]:
        """Offer the file at ``path`` (or every file under the directory ``path``) to the hub, which keeps it at the
        same place in its data dir; returns the paths (relative to the data dirs) it took."""
        path = Path(path).resolve()
        found = _files_under(path, MAX_INPUT_FILES) if path.is_dir() else [path]
        taken = []
        for f in found:
            ref = self.cache.publish(f)
            self._offer(
                msg.BlobOffer(holder=self.holder, blob=ref.blob, size=ref.size, path=ref.path), ref.size
            )
            taken.append(ref.path)
        return taken

    def offer_episode(self, episode_id: str, rollout: Any = None) -> str:
        """Offer stored episode ``episode_id`` (with ``rollout``, the row of the rollout it records, whose folder is
        offered first) to the hub's store; returns the episode's path there."""
        store = self.store()
        row = None
        if rollout is not None:
            row = msgspec.to_builtins(rollout)
            if rollout.path:
                self.offer(rollout.path)
                row["path"] = Path(rollout.path).resolve().relative_to(self.data_dir).as_posix()
            row["episode_id"] = None
        folder = store.episode_dir(episode_id)
        refs = {name: self.cache.publish(folder / name) for name in _episode_file_names()}
        offer = msg.EpisodeOffer(
            holder=self.holder,
            episode=episode_id,
            files={n: r.blob for n, r in refs.items()},
            sizes={n: r.size for n, r in refs.items()},
            rollout=row,
        )
        return self._offer(offer, sum(r.size for r in refs.values())).path
