"""Who is on the bus: workers announce themselves, the UI host keeps a live directory of them.

A worker holds a Zenoh *liveliness token* on ``studio/workers/<kind>/<id>`` for as long as its
session lives: a crash, a kill or a lost link removes it (at once for a closed connection, within the
link lease otherwise). What the worker is doing is a :class:`~studio.backend.messages.WorkerStatus`,
published on ``…/status`` whenever it changes and answered on the same key for late joiners.

:class:`Directory` is the other side: a liveliness subscriber with history plus a status subscriber,
giving the current set of workers and ``joined`` / ``left`` / ``status`` events.
"""

from __future__ import annotations

import os
import re
import secrets
import socket
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import msgspec
import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg


def new_worker_id(kind: str) -> str:
    """A readable, unique worker id: ``<kind>-<host>-<6 hex>``."""
    host = re.sub(r"[^A-Za-z0-9_.-]", "-", socket.gethostname())[:24].strip("-.") or "host"
    return f"{kind}-{host}-{secrets.token_hex(3)}"


class WorkerPresence:
    """A worker's announcement on the bus: status publisher, status queryable, liveliness token.

    The status is published and answerable before the token appears, so whoever sees the token can
    always ask what the worker is. With ``announce=False`` the token waits for :meth:`announce`, so a
    worker can declare everything it serves before anyone sees it.
    """

    def __init__(
        self,
        session: zenoh.Session,
        kind: str,
        worker: str,
        *,
        job_kinds: Iterable[str] = (),
        unavailable: dict[str, str] | None = None,
        activity: str = "idle",
        announce: bool = True,
    ):
        self.session = session
        self.kind, self.worker = keys.check_chunk(kind, "worker kind"), keys.check_chunk(worker, "worker id")
        now = time.time()
        self._lock = threading.Lock()
        self._status = msg.WorkerStatus(
            worker=worker,
            kind=kind,
            host=socket.gethostname()[:200] or "host",
            pid=os.getpid(),
            state="idle",
            activity=activity,
            job_kinds=tuple(job_kinds),
            unavailable=dict(unavailable or {}),
            job=None,
            sessions=0,
            started_at=now,
            updated_at=now,
        )
        status_key = keys.worker_key(kind, worker, "status")
        self._publisher = session.declare_publisher(status_key, congestion_control=bus.MUST_ARRIVE)
        self._queryable = bus.declare_queryable(session, status_key, lambda _m, _q: self.status)
        self._publisher.put(msg.encode(self._status))
        self._token: zenoh.LivelinessToken | None = None
        self._closed = False
        if announce:
            self.announce()

    def announce(self) -> None:
        """Declare the liveliness token: from now on the worker is visible (call once it can serve)."""
        with self._lock:
            if self._token is None and not self._closed:
                self._token = self.session.liveliness().declare_token(
                    keys.worker_token(self.kind, self.worker)
                )

    @property
    def status(self) -> msg.WorkerStatus:
        with self._lock:
            return self._status

    def update(self, **changes) -> msg.WorkerStatus:
        """Change fields of the status (e.g. ``state="busy", activity="training job x"``) and publish it."""
        with self._lock:
            if self._closed:
                return self._status
            self._status = msgspec.structs.replace(self._status, updated_at=time.time(), **changes)
            status = self._status
            self._publisher.put(msg.encode(status))
        return status

    def close(self) -> None:
        """Withdraw the token (the directory sees the worker leave), then the status endpoints."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for entity in (self._token, self._queryable, self._publisher):
            if entity is None:
                continue
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass  # the session is already closed


@dataclass(frozen=True)
class WorkerEntry:
    """A worker the directory currently sees (``status`` is None until it has been received)."""

    kind: str
    worker: str
    status: msg.WorkerStatus | None
    joined_at: float


Listener = Callable[[str, WorkerEntry], None]


class Directory:
    """The live set of workers, with ``joined`` / ``left`` / ``status`` events for listeners.

    Listeners run on Zenoh's callback threads, outside the directory's lock; they must not block long.
    """

    def __init__(self, session: zenoh.Session):
        self.session = session
        self._cond = threading.Condition()
        self._workers: dict[tuple[str, str], WorkerEntry] = {}
        self._early_status: dict[tuple[str, str], msg.WorkerStatus] = {}
        self._listeners: list[Listener] = []
        self._closed = False
        self._status_sub = bus.declare_subscriber(
            session, keys.ALL_WORKER_STATUS, self._on_status, expect=msg.WorkerStatus
        )
        self._token_sub = session.liveliness().declare_subscriber(
            keys.ALL_WORKER_TOKENS, self._on_token, history=True
        )

    # ------------------------------------------------------------------ queries
    def workers(self, kind: str | None = None) -> list[WorkerEntry]:
        with self._cond:
            return sorted(
                (e for e in self._workers.values() if kind is None or e.kind == kind),
                key=lambda e: (e.kind, e.joined_at, e.worker),
            )

    def get(self, kind: str, worker: str) -> WorkerEntry | None:
        with self._cond:
            return self._workers.get((kind, worker))

    def is_alive(self, worker: str) -> bool:
        with self._cond:
            return any(w == worker for _, w in self._workers)

    def wait_for(self, predicate: Callable[[list[WorkerEntry]], bool], timeout: float) -> bool:
        """Block until ``predicate(workers())`` holds (re-checked on every change) or the timeout passes."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while not predicate(list(self._workers.values())):
                left = deadline - time.monotonic()
                if left <= 0 or self._closed:
                    return False
                self._cond.wait(left)
            return True

    def add_listener(self, listener: Listener) -> None:
        with self._cond:
            self._listeners.append(listener)

    def remove_listener(self, listener: Listener) -> None:
        with self._cond:
            if listener in self._listeners:
                self._listeners.remove(listener)

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        for sub in (self._token_sub, self._status_sub):
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass

    # ------------------------------------------------------------------ events
    def _emit(self, event: str, entry: WorkerEntry) -> None:
        with self._cond:
            listeners = list(self._listeners)
        for listener in listeners:
            try:
                listener(event, entry)
            except Exception:
                bus.log.exception("directory listener failed on %s of %s", event, entry.worker)

    def _on_token(self, sample: zenoh.Sample) -> None:
        try:
            kind, worker, leaf = keys.parse_worker_key(str(sample.key_expr))
        except keys.KeyExprError:
            return
        if leaf is not None:
            return
        ident = (kind, worker)
        if sample.kind == zenoh.SampleKind.PUT:
            with self._cond:
                if self._closed or ident in self._workers:
                    return
                entry = WorkerEntry(kind, worker, self._early_status.pop(ident, None), time.time())
                self._workers[ident] = entry
                self._cond.notify_all()
            self._emit("joined", entry)
            if entry.status is None:
                threading.Thread(target=self._fetch_status, args=(kind, worker), daemon=True).start()
        else:
            with self._cond:
                gone = self._workers.pop(ident, None)
                self._early_status.pop(ident, None)
                self._cond.notify_all()
            if gone is not None:
                self._emit("left", gone)

    def _on_status(self, status: msg.WorkerStatus, sample: zenoh.Sample) -> None:
        try:
            kind, worker, _ = keys.parse_worker_key(str(sample.key_expr))
        except keys.KeyExprError:
            return
        if (status.kind, status.worker) != (kind, worker):
            bus.bad_input_log.warning(
                f"status:{kind}/{worker}", "status on %s names another worker", sample.key_expr
            )
            return
        self._apply_status(status)

    def _apply_status(self, status: msg.WorkerStatus) -> None:
        ident = (status.kind, status.worker)
        with self._cond:
            entry = self._workers.get(ident)
            if entry is None:
                if not self._closed:
                    self._early_status[ident] = status  # the token will follow
                return
            if entry.status is not None and entry.status.updated_at > status.updated_at:
                return  # an older status arrived late
            entry = WorkerEntry(entry.kind, entry.worker, status, entry.joined_at)
            self._workers[ident] = entry
            self._cond.notify_all()
        self._emit("status", entry)

    def _fetch_status(self, kind: str, worker: str) -> None:
        try:
            replies = bus.request_all(self.session, keys.worker_key(kind, worker, "status"), msg.WorkerStatus)
        except zenoh.ZError:
            return
        for status in replies:
            self._apply_status(status)
