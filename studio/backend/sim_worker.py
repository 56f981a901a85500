"""The teleop service of ``studio worker sim``: one :class:`~studio.backend.teleop_session.TeleopSession` per client.

A client picks a session id, declares a liveliness token on ``studio/sim/<worker>/<session>/client``
and sends :class:`~studio.backend.messages.OpenSession` to ``…/<session>/ctl``; every later request
goes to the same key. The session ends on :class:`~studio.backend.messages.CloseSession` or when the
client's token disappears (its process died or lost the link), so an abandoned session never keeps a
simulator running.

Session ids are visible to anyone on the bus (they are in every key of the session), so they grant nothing: the
worker mints an unguessable *owner token* when it creates a session and returns it only in the answer to that
OpenSession (:attr:`~studio.backend.messages.SessionInfo.owner`). Every later request to ``…/ctl`` — a re-open
included — and every :class:`~studio.backend.messages.EeTarget` on ``…/cmd`` must carry it as its Zenoh
attachment; the session answers anything else with ``conflict`` and drops such commands (one rate-limited line).
The token is never published. Without an authenticated bus, a peer that can read the opener's traffic can still
read the token. Rollout jobs run on the same worker through its
:class:`~studio.backend.job_runner.JobRunner`.
"""

from __future__ import annotations

import contextlib
import hmac
import secrets
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.episode_transfer import EpisodeDestination
from studio.backend.presence import WorkerPresence
from studio.backend.teleop_session import SessionError, TeleopConfig, TeleopSession


class SimWorker:
    """Hosts teleop sessions on a sim worker.

    Args:
        zsession: the worker's Zenoh session.
        presence: the worker's presence (its status shows the number of sessions).
        destination: where recorded episodes go.
        spool_dir: where recordings the store refused are kept (when they cannot be kept as drafts).
        drafts_dir: the data dir's drafts (:class:`studio.data.drafts.RecordingDrafts`), where a recording the
            store refused is kept so the studio offers it back (None: the spool directory only).
        max_sessions: sessions beyond this are refused with ``busy``.
        config: timing of every session.
    """

    def __init__(
        self,
        zsession: zenoh.Session,
        presence: WorkerPresence,
        destination: EpisodeDestination,
        spool_dir: Path,
        *,
        max_sessions: int = 4,
        config: TeleopConfig | None = None,
        drafts_dir: Path | None = None,
    ):
        self.zsession = zsession
        self.presence = presence
        self.worker = presence.worker
        self.destination = destination
        self.spool_dir = spool_dir
        self.max_sessions = max_sessions
        self.drafts_dir = drafts_dir
        self.config = config or TeleopConfig()
        self._lock = threading.Lock()
        self._sessions: dict[str, TeleopSession] = {}
        self._owners: dict[str, str] = {}  # session id -> owner token
        self._opening: set[str] = set()
        self._closing: list[threading.Thread] = []
        self._closed = False
        self._ctl = bus.declare_queryable(zsession, keys.all_sessions(self.worker, "ctl"), self._on_ctl)
        self._clients = zsession.liveliness().declare_subscriber(
            keys.all_sessions(self.worker, "client"), self._on_client
        )

    @property
    def sessions(self) -> list[str]:
        with self._lock:
            return sorted(self._sessions)

    def _announce(self) -> None:
        n = len(self.sessions)
        self.presence.update(
            sessions=n, activity=f"{n} teleop session{'s' if n != 1 else ''}" if n else "idle"
        )

    # ------------------------------------------------------------------ requests
    def _not_owner(self, session_id: str, query: zenoh.Query) -> msg.ErrorReply | None:
        """An error unless the query carries the owner token of ``session_id`` (None: it does, or no such session)."""
        with self._lock:
            owner = self._owners.get(session_id)
        if owner is None or hmac.compare_digest(bus.attachment_bytes(query), owner.encode()):
            return None
        bus.bad_input_log.warning(
            f"ctl-owner:{self.worker}",
            "refused a request to session %s without its owner's token",
            session_id,
        )
        return msg.ErrorReply(
            code="conflict",
            message=f"session {session_id} belongs to another client (owner token missing or wrong)",
        )

    def _on_ctl(self, request: msg.Message | None, query: zenoh.Query) -> Any:
        _, session_id, _ = keys.parse_session_key(str(query.key_expr))
        if request is None:
            return msg.ErrorReply(code="bad_request", message="a teleop request needs a payload")
        refused = self._not_owner(session_id, query)
        if refused is not None:
            return refused
        if isinstance(request, msg.OpenSession):
            with self._lock:
                if self._closed:
                    return msg.ErrorReply(code="unavailable", message="worker is shutting down")
                if session_id in self._opening:
                    return msg.ErrorReply(code="conflict", message=f"session {session_id} is being opened")
                if (
                    session_id not in self._sessions
                    and len(self._sessions) + len(self._opening) >= self.max_sessions
                ):
                    return msg.ErrorReply(
                        code="busy", message=f"worker hosts its maximum of {self.max_sessions} sessions"
                    )
                self._opening.add(session_id)
            threading.Thread(target=self._open, args=(session_id, request, query), daemon=True).start()
            return bus.DEFERRED
        if isinstance(request, msg.CloseSession):
            found = self._close_session(session_id, "its client closed it", wait=False)
            return msg.Ack(message="closed" if found else "no such session")
        with self._lock:
            session = self._sessions.get(session_id)
        if session is None:
            return msg.ErrorReply(
                code="not_found", message=f"no teleop session {session_id} on {self.worker}"
            )
        try:
            return session.handle(request, query)
        except SessionError as e:
            return msg.ErrorReply(code=e.code, message=str(e))

    def _open(self, session_id: str, request: msg.OpenSession, query: zenoh.Query) -> None:
        started = time.monotonic()
        try:
            with self._lock:
                owner = self._owners.get(session_id) or secrets.token_urlsafe(24)
            # Re-opening (by its owner) replaces the old session.
            replaced = self._close_session(session_id, "re-opened")
            try:
                session = TeleopSession(
                    self.zsession,
                    self.worker,
                    session_id,
                    request,
                    self.destination,
                    self.spool_dir,
                    self.config,
                    owner=owner,
                    drafts_dir=self.drafts_dir,
                )
            except SessionError as e:
                bus.reply(query, msg.ErrorReply(code=e.code, message=str(e)))
                return
            except Exception as e:
                bus.log.exception("opening session %s failed", session_id)
                bus.reply(query, msg.ErrorReply(code="internal", message=f"{type(e).__name__}: {e}"))
                return
            with self._lock:
                closed = self._closed
                if not closed:
                    self._sessions[session_id] = session
                    self._owners[session_id] = owner
            if closed:
                session.close()
                bus.reply(query, msg.ErrorReply(code="unavailable", message="worker is shutting down"))
                return
            bus.reply(query, session.info())
            bus.log.info(
                "%s session %s: %s / %s / %s seed %d in %.1f s (%d sessions)",
                "re-opened" if replaced else "opened",
                session_id,
                request.scene,
                request.robot,
                request.task,
                request.seed,
                time.monotonic() - started,
                len(self.sessions),
            )
            self._announce()
        finally:
            with self._lock:
                self._opening.discard(session_id)
            query.drop()

    def _on_client(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.DELETE:
            return
        try:
            _, session_id, _ = keys.parse_session_key(str(sample.key_expr))
        except keys.KeyExprError:
            return
        threading.Thread(
            target=self._close_if_abandoned, args=(session_id, str(sample.key_expr)), daemon=True
        ).start()

    def _close_if_abandoned(self, session_id: str, key: str) -> None:
        """Close the session unless a client token is still alive on its key (another peer's token that came and
        went on the same key does not end the owner's session)."""
        try:
            alive = any(r.ok is not None for r in self.zsession.liveliness().get(key, timeout=1.0))
        except zenoh.ZError:
            alive = False
        if not alive:
            self._close_session(session_id, "its client left the bus", wait=False)

    def _close_session(self, session_id: str, why: str, wait: bool = True) -> bool:
        """Remove a session; its pending saves finish (in the background unless ``wait``)."""
        with self._lock:
            session = self._sessions.pop(session_id, None)
            self._owners.pop(session_id, None)
        if session is None:
            return False
        bus.log.info("closing session %s: %s", session_id, why)
        if wait:
            session.close()
        else:
            t = threading.Thread(target=session.close, name=f"close-{session_id}", daemon=True)
            with self._lock:
                self._closing = [c for c in self._closing if c.is_alive()] + [t]
            t.start()
        self._announce()
        return True

    def close(self) -> None:
        """Close every session, waiting for recordings still being stored."""
        with self._lock:
            self._closed = True
            sessions = list(self._sessions.values())
            self._sessions.clear()
            closing = list(self._closing)
        for entity in (self._ctl, self._clients):
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        for s in sessions:
            s.close()
        for t in closing:
            t.join(60.0)
