"""Jobs on the bus: the hub's queue that assigns them to workers and watches them, and the client API.

Life of a job::

    JobClient.submit ──JobSubmit──▶ JobQueue ──JobAssign──▶ worker (JobRunner) ──▶ handler
          ▲                            │ status: queued          status: running, progress,
          └──── JobWatch ◀─────────────┴──────────────────────── artifacts, result, succeeded|failed|cancelled

* **Queue**: jobs wait (FIFO) until a worker of the right kind that offers the job's kind is idle.
* **Faults**: the queue follows workers through :class:`~studio.backend.presence.Directory`. When a
  worker's liveliness token disappears, each of its running jobs is failed with the reason, or — if it
  was submitted with ``requeue_on_worker_loss`` (training) and has attempts left — queued again and
  handed to the next free worker with ``attempt + 1``.
* **Restarts**: the queue writes every state change to a journal file. A restarted queue reloads it,
  asks every worker which jobs it holds (``…/jobs``), re-attaches to the running ones, and gives workers
  that were running a job when it went down ``reattach_grace_s`` to reconnect before declaring them lost.
* **Listing**: the queue answers ``studio/jobs/*/status`` (and ``…/result``, ``…/progress``), so a
  restarted UI lists jobs with one query and then watches the ones it shows.

Workers report on ``…/report``, which only the queue hears; the queue is the one publisher of
``…/status`` and publishes a state only after recording it, so what a watcher sees is already listed.
Of two statuses of one job, the one with the larger :func:`~studio.backend.messages.status_rank` wins
(attempt, then queued < running < finished), so late or repeated reports do no harm.
"""

from __future__ import annotations

import os
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.job_runner import JOB_KINDS
from studio.backend.presence import Directory, WorkerEntry

JOURNAL_VERSION = 1


def new_job_id(kind: str) -> str:
    return f"{kind}-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}-{secrets.token_hex(3)}"


class _JournalEntry(msgspec.Struct):
    status: msg.JobStatus
    result: msg.JobResult | None = None


class _Journal(msgspec.Struct):
    version: int
    jobs: list[_JournalEntry]


@dataclass
class _Job:
    status: msg.JobStatus
    result: msg.JobResult | None = None
    progress: msg.JobProgress | None = None
    cancel_reason: str | None = None
    #: When set, the job's worker is missing; at this time the worker-loss policy applies.
    lost_deadline: float | None = None


@dataclass
class _Assignment:
    job: str
    kind: str
    worker: str
    attempt: int


@dataclass
class _Pending:
    """Work the dispatcher thread does outside the lock."""

    reattach: set[tuple[str, str]] = field(default_factory=set)
    cancels: list[tuple[str, str, msg.JobCancel]] = field(default_factory=list)


class JobQueue:
    """The hub's job queue (one per studio; it lives in the UI host's process).

    Args:
        session: the hub's Zenoh session.
        directory: the hub's worker directory.
        journal: file the queue persists its jobs to (None: memory only, lost on restart).
        reattach_grace_s: how long, after a restart, a worker that was running a job may take to reconnect.
        assign_timeout_s: how long to wait for a worker to accept an assignment.
    """

    def __init__(
        self,
        session: zenoh.Session,
        directory: Directory,
        *,
        journal: str | os.PathLike | None = None,
        reattach_grace_s: float = 5.0,
        assign_timeout_s: float = 3.0,
    ):
        self.session = session
        self.directory = directory
        self.journal_path = Path(journal) if journal is not None else None
        self.reattach_grace_s = reattach_grace_s
        self.assign_timeout_s = assign_timeout_s
        self._cond = threading.Condition()
        self._jobs: dict[str, _Job] = {}
        self._assigned: dict[str, _Assignment] = {}  # worker id -> what the queue believes it runs
        self._skip_until: dict[str, float] = {}  # worker id -> do not offer it jobs before this time
        self._pending = _Pending()
        self._closed = False
        self._load_journal()
        remote = {"allowed_origin": zenoh.Locality.REMOTE}
        self._entities: list[Any] = [
            bus.declare_queryable(session, keys.all_jobs("submit"), self._on_submit, msg.JobSubmit),
            bus.declare_queryable(session, keys.all_jobs("cancel"), self._on_cancel, msg.JobCancel),
            bus.declare_queryable(session, keys.all_jobs("status"), self._on_list("status")),
            bus.declare_queryable(session, keys.all_jobs("result"), self._on_list("result")),
            bus.declare_queryable(session, keys.all_jobs("progress"), self._on_list("progress")),
            bus.declare_subscriber(session, keys.all_jobs("report"), self._on_worker_status, msg.JobStatus),
            bus.declare_subscriber(
                session, keys.all_jobs("result"), self._on_result, msg.JobResult, **remote
            ),
            bus.declare_subscriber(
                session, keys.all_jobs("progress"), self._on_progress, msg.JobProgress, **remote
            ),
        ]
        directory.add_listener(self._on_directory)
        with self._cond:
            for entry in directory.workers():
                self._pending.reattach.add((entry.kind, entry.worker))
        self._thread = threading.Thread(target=self._loop, name="job-queue", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ public API (in-process)
    def jobs(self) -> list[msg.JobStatus]:
        with self._cond:
            return sorted((j.status for j in self._jobs.values()), key=lambda s: (s.submitted_at, s.job))

    def get(self, job: str) -> msg.JobStatus | None:
        with self._cond:
            j = self._jobs.get(job)
            return None if j is None else j.status

    def close(self) -> None:
        """Stop serving (jobs keep running on their workers; a new queue re-attaches to them)."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        self.directory.remove_listener(self._on_directory)
        self._thread.join(5.0)
        for entity in self._entities:
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass

    # ------------------------------------------------------------------ journal
    def _load_journal(self) -> None:
        if self.journal_path is None or not self.journal_path.exists():
            return
        try:
            data = msgspec.json.decode(self.journal_path.read_bytes(), type=_Journal)
            if data.version != JOURNAL_VERSION:
                raise ValueError(f"journal version {data.version}, expected {JOURNAL_VERSION}")
        except (msgspec.MsgspecError, ValueError) as e:
            keep = self.journal_path.with_name(f"{self.journal_path.name}.unreadable-{int(time.time())}")
            self.journal_path.rename(keep)
            bus.log.error(
                "job journal %s is unreadable (%s); kept it as %s and started empty",
                self.journal_path,
                e,
                keep,
            )
            return
        deadline = time.monotonic() + self.reattach_grace_s
        for entry in data.jobs:
            job = _Job(status=entry.status, result=entry.result)
            if entry.status.state == "running":
                job.lost_deadline = deadline  # until its worker shows up and confirms
                if entry.status.worker:
                    self._assigned[entry.status.worker] = _Assignment(
                        entry.status.job, entry.status.kind, entry.status.worker, entry.status.attempt
                    )
            self._jobs[entry.status.job] = job

    def _save_journal_locked(self) -> None:
        if self.journal_path is None:
            return
        data = _Journal(
            version=JOURNAL_VERSION,
            jobs=[_JournalEntry(j.status, j.result) for j in self._jobs.values()],
        )
        self.journal_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.journal_path.with_name(self.journal_path.name + ".tmp")
        with open(tmp, "wb") as f:
            f.write(msgspec.json.encode(data))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.journal_path)

    # ------------------------------------------------------------------ state changes (lock held)
    def _set_status_locked(self, job: _Job, status: msg.JobStatus, publish: bool = True) -> None:
        job.status = status
        if status.terminal or status.state == "queued":
            owner = status.worker or ""
            a = self._assigned.get(owner)
            if a is not None and a.job == status.job:
                del self._assigned[owner]
        self._save_journal_locked()
        if publish:
            self._publish(keys.job_key(status.job, "status"), status)
        self._cond.notify_all()

    def _publish(self, key: str, message: msg.Message) -> None:
        try:
            self.session.put(key, msg.encode(message))
        except zenoh.ZError:
            bus.log.warning("could not publish on %s", key)

    def _apply_worker_loss_locked(self, job: _Job) -> None:
        s = job.status
        who = s.worker or "its worker"
        now = time.time()
        if job.cancel_reason is not None:
            new = msgspec.structs.replace(
                s, state="cancelled", reason=f"{job.cancel_reason} (worker {who} lost)", updated_at=now
            )
        elif s.requeue_on_worker_loss and s.attempt < s.max_attempts:
            new = msgspec.structs.replace(
                s,
                state="queued",
                attempt=s.attempt + 1,
                worker=None,
                updated_at=now,
                reason=f"worker {who} lost during attempt {s.attempt}; re-queued (attempt {s.attempt + 1} of {s.max_attempts})",
            )
        else:
            tail = "" if not s.requeue_on_worker_loss else f"; no attempts left ({s.max_attempts})"
            new = msgspec.structs.replace(
                s,
                state="failed",
                updated_at=now,
                reason=f"worker {who} lost during attempt {s.attempt} (its liveliness token disappeared){tail}",
            )
        job.lost_deadline = None
        if s.worker:
            self._assigned.pop(s.worker, None)
        self._set_status_locked(job, new)

    # ------------------------------------------------------------------ queryables
    def _on_submit(self, submit: msg.JobSubmit, query: zenoh.Query) -> msg.Message:
        job_id, _ = keys.parse_job_key(str(query.key_expr))
        if job_id != submit.job:
            return msg.ErrorReply(
                code="bad_request", message=f"JobSubmit for {submit.job} sent to job {job_id}"
            )
        with self._cond:
            if self._closed:
                return msg.ErrorReply(code="unavailable", message="the job queue is shutting down")
            existing = self._jobs.get(submit.job)
            if existing is not None:
                same = (existing.status.kind, existing.status.spec) == (submit.kind, submit.spec)
                if same:
                    return existing.status  # a retried submission
                return msg.ErrorReply(code="conflict", message=f"job {submit.job} exists with another spec")
            now = time.time()
            status = msg.JobStatus(
                job=submit.job,
                kind=submit.kind,
                worker_kind=submit.worker_kind,
                state="queued",
                attempt=1,
                worker=None,
                reason="waiting for a worker",
                submitted_at=now,
                updated_at=now,
                queue_position=None,
                spec=submit.spec,
                requeue_on_worker_loss=submit.requeue_on_worker_loss,
                max_attempts=submit.max_attempts,
            )
            job = _Job(status=status)
            self._jobs[submit.job] = job
            status = self._with_queue_info_locked(status)
            self._set_status_locked(job, status)
            return status

    def _on_cancel(self, cancel: msg.JobCancel, query: zenoh.Query) -> msg.Message:
        reason = cancel.reason or "cancelled by the user"
        with self._cond:
            job = self._jobs.get(cancel.job)
            if job is None:
                return msg.ErrorReply(code="not_found", message=f"no job {cancel.job}")
            s = job.status
            if s.terminal:
                return s
            if s.state == "queued":
                self._set_status_locked(
                    job,
                    msgspec.structs.replace(
                        s, state="cancelled", reason=reason, updated_at=time.time(), queue_position=None
                    ),
                )
                return job.status
            job.cancel_reason = reason
            if s.worker:
                self._pending.cancels.append(
                    (s.worker_kind, s.worker, msg.JobCancel(job=s.job, reason=reason))
                )
                self._cond.notify_all()
            return msgspec.structs.replace(s, reason=f"cancel requested: {reason}")

    def _on_list(
        self, leaf: str
    ) -> Callable[[msg.Message | None, zenoh.Query], list[tuple[str, msg.Message]]]:
        def handler(_request: msg.Message | None, query: zenoh.Query) -> list[tuple[str, msg.Message]]:
            asked = zenoh.KeyExpr(str(query.key_expr))
            out: list[tuple[str, msg.Message]] = []
            with self._cond:
                for job_id, job in self._jobs.items():
                    item = {"status": job.status, "result": job.result, "progress": job.progress}[leaf]
                    key = keys.job_key(job_id, leaf)
                    if item is not None and asked.intersects(zenoh.KeyExpr(key)):
                        out.append((key, item))
            return out

        return handler

    # ------------------------------------------------------------------ subscriptions (workers' reports)
    def _on_worker_status(self, status: msg.JobStatus, sample: zenoh.Sample) -> None:
        self._merge_status(status)

    def _merge_status(self, status: msg.JobStatus) -> None:
        """Apply a worker's report of a job. Workers report to the queue alone (``…/report``); the queue
        publishes the merged status on ``…/status`` after recording it, so a watcher never sees a state
        that :meth:`JobClient.list` does not list yet."""
        with self._cond:
            job = self._jobs.get(status.job)
            if job is None:
                # A job the queue never heard of (its journal was lost): adopt it.
                job = _Job(status=status)
                self._jobs[status.job] = job
                if status.state == "running" and status.worker:
                    self._assigned[status.worker] = _Assignment(
                        status.job, status.kind, status.worker, status.attempt
                    )
                self._set_status_locked(job, status)
                return
            cur = job.status
            if status.attempt != cur.attempt:
                if status.state == "running" and status.worker and status.attempt < cur.attempt:
                    self._pending.cancels.append(
                        (
                            status.worker_kind,
                            status.worker,
                            msg.JobCancel(job=status.job, reason=f"attempt {status.attempt} was superseded"),
                        )
                    )
                    self._cond.notify_all()
                return
            if msg.status_rank(status) < msg.status_rank(cur):
                return
            if status.state == "running":
                job.lost_deadline = None
                if status.worker:
                    self._assigned[status.worker] = _Assignment(
                        status.job, status.kind, status.worker, status.attempt
                    )
                if cur.state == "running" and cur.worker == status.worker:
                    job.status = status
                    return
            self._set_status_locked(job, status)

    def _on_result(self, result: msg.JobResult, sample: zenoh.Sample) -> None:
        with self._cond:
            job = self._jobs.get(result.job)
            if job is not None and result.attempt == job.status.attempt:
                job.result = result
                self._save_journal_locked()

    def _on_progress(self, progress: msg.JobProgress, sample: zenoh.Sample) -> None:
        with self._cond:
            job = self._jobs.get(progress.job)
            if job is not None and progress.attempt == job.status.attempt:
                job.progress = progress

    def _on_directory(self, event: str, entry: WorkerEntry) -> None:
        with self._cond:
            if event == "joined":
                self._pending.reattach.add((entry.kind, entry.worker))
            elif event == "left":
                self._skip_until.pop(entry.worker, None)
                for job in self._jobs.values():
                    s = job.status
                    if s.state == "running" and s.worker == entry.worker:
                        job.lost_deadline = time.monotonic()
            self._cond.notify_all()

    # ------------------------------------------------------------------ dispatcher thread
    def _loop(self) -> None:
        while True:
            with self._cond:
                if self._closed:
                    return
                self._cond.wait(0.25)
                if self._closed:
                    return
                reattach, self._pending.reattach = self._pending.reattach, set()
                cancels, self._pending.cancels = self._pending.cancels, []
                now = time.monotonic()
                for job in self._jobs.values():
                    if (
                        job.status.state == "running"
                        and job.lost_deadline is not None
                        and now >= job.lost_deadline
                    ):
                        if job.status.worker and self.directory.is_alive(job.status.worker):
                            job.lost_deadline = None  # it came back; the re-attach query settles the rest
                            continue
                        self._apply_worker_loss_locked(job)
            try:
                for kind, worker in reattach:
                    self._reattach(kind, worker)
                for kind, worker, cancel in cancels:
                    self._forward_cancel(kind, worker, cancel)
                self._dispatch()
            except Exception:
                bus.log.exception("job queue iteration failed")

    def _reattach(self, kind: str, worker: str) -> None:
        """Ask a (re)joined worker which jobs it holds and reconcile them with the queue's view."""
        try:
            replies = bus.request_all(
                self.session, keys.worker_key(kind, worker, "jobs"), msg.Message, timeout=2.0
            )
        except zenoh.ZError:
            replies = []
        if not any(isinstance(m, msg.WorkerStatus) for m in replies):
            # No answer (its queryables may not be declared to us yet): ask again shortly, if it is still here.
            if self.directory.get(kind, worker) is not None:
                threading.Timer(0.5, self._request_reattach, args=(kind, worker)).start()
            return
        held = set()
        for m in replies:
            if isinstance(m, msg.JobStatus):
                if m.state == "running":
                    held.add(m.job)
                self._merge_status(m)
            elif isinstance(m, msg.JobResult):
                self._on_result(m, None)  # type: ignore[arg-type]
        with self._cond:
            # The queue believed this worker runs a job it does not report: treat the attempt as lost.
            for job in self._jobs.values():
                s = job.status
                if s.state == "running" and s.worker == worker and s.job not in held:
                    finished = [m for m in replies if isinstance(m, msg.JobStatus) and m.job == s.job]
                    if not finished:
                        self._apply_worker_loss_locked(job)

    def _request_reattach(self, kind: str, worker: str) -> None:
        with self._cond:
            if not self._closed:
                self._pending.reattach.add((kind, worker))
                self._cond.notify_all()

    def _forward_cancel(self, kind: str, worker: str, cancel: msg.JobCancel) -> None:
        try:
            bus.request(
                self.session, keys.worker_key(kind, worker, "cancel"), cancel, msg.JobStatus, timeout=2.0
            )
        except bus.BusError as e:
            bus.log.warning("could not forward the cancellation of %s to %s: %s", cancel.job, worker, e)

    def _with_queue_info_locked(self, status: msg.JobStatus) -> msg.JobStatus:
        queued = sorted(
            (
                j.status
                for j in self._jobs.values()
                if j.status.state == "queued" and j.status.worker_kind == status.worker_kind
            ),
            key=lambda s: (s.submitted_at, s.job),
        )
        position = next((i for i, s in enumerate(queued) if s.job == status.job), len(queued))
        capable = [
            e
            for e in self.directory.workers(status.worker_kind)
            if e.status is not None and status.kind in e.status.job_kinds
        ]
        if capable:
            reason = f"waiting for a free {status.worker_kind} worker ({position} ahead)"
        else:
            missing = [
                f"{e.worker}: {e.status.unavailable.get(status.kind, 'does not offer it')}"
                for e in self.directory.workers(status.worker_kind)
                if e.status is not None
            ]
            reason = f"no connected {status.worker_kind} worker can run {status.kind!r} jobs"
            if missing:
                reason += " (" + "; ".join(missing) + ")"
        if status.reason.startswith("worker ") and "re-queued" in status.reason:
            reason = status.reason + "; " + reason
        return msgspec.structs.replace(status, queue_position=position, reason=reason[:4000])

    def _dispatch(self) -> None:
        while True:
            with self._cond:
                if self._closed:
                    return
                now = time.monotonic()
                queued = sorted(
                    (j for j in self._jobs.values() if j.status.state == "queued"),
                    key=lambda j: (j.status.submitted_at, j.status.job),
                )
                choice = None
                for job in queued:
                    s = job.status
                    for entry in self.directory.workers(s.worker_kind):
                        st = entry.status
                        if (
                            st is not None
                            and st.state == "idle"
                            and s.kind in st.job_kinds
                            and entry.worker not in self._assigned
                            and self._skip_until.get(entry.worker, 0.0) <= now
                        ):
                            choice = (job, entry)
                            break
                    if choice:
                        break
                # Keep the queued jobs' positions and reasons current.
                for job in queued:
                    if choice is not None and job is choice[0]:
                        continue
                    updated = self._with_queue_info_locked(job.status)
                    if (updated.queue_position, updated.reason) != (
                        job.status.queue_position,
                        job.status.reason,
                    ):
                        self._set_status_locked(job, msgspec.structs.replace(updated, updated_at=time.time()))
                if choice is None:
                    return
                job, entry = choice
                s = job.status
                self._assigned[entry.worker] = _Assignment(s.job, s.kind, entry.worker, s.attempt)
                assign = msg.JobAssign(
                    job=s.job,
                    kind=s.kind,
                    attempt=s.attempt,
                    spec=s.spec,
                    submitted_at=s.submitted_at,
                    requeue_on_worker_loss=s.requeue_on_worker_loss,
                    max_attempts=s.max_attempts,
                )
            try:
                running = bus.request(
                    self.session,
                    keys.worker_key(entry.kind, entry.worker, "assign"),
                    assign,
                    msg.JobStatus,
                    timeout=self.assign_timeout_s,
                )
            except bus.BusError as e:
                bus.log.info("worker %s did not take job %s: %s", entry.worker, assign.job, e)
                with self._cond:
                    a = self._assigned.get(entry.worker)
                    if a is not None and a.job == assign.job:
                        del self._assigned[entry.worker]
                    self._skip_until[entry.worker] = time.monotonic() + 1.0
                continue
            self._merge_status(running)


# ---------------------------------------------------------------------------------------------- client
class JobWatch:
    """Follows one job: its newest status (by rank), progress, artifacts, result and live poses.

    Callbacks run on Zenoh's threads. Use :meth:`wait` to block until the job reaches a state.
    """

    def __init__(
        self,
        session: zenoh.Session,
        job: str,
        *,
        on_status: Callable[[msg.JobStatus], None] | None = None,
        on_progress: Callable[[msg.JobProgress], None] | None = None,
        on_artifact: Callable[[msg.JobArtifact], None] | None = None,
        on_poses: Callable[[msg.PoseFrame], None] | None = None,
    ):
        self.job = keys.check_chunk(job, "job id")
        self._cond = threading.Condition()
        self.status: msg.JobStatus | None = None
        self.progress: msg.JobProgress | None = None
        self.result: msg.JobResult | None = None
        self.artifacts: list[msg.JobArtifact] = []
        self.history: list[msg.JobStatus] = []
        self._on_status, self._on_progress, self._on_artifact = on_status, on_progress, on_artifact
        self._subs = [
            bus.declare_subscriber(session, keys.job_key(job, "status"), self._status, msg.JobStatus),
            bus.declare_subscriber(session, keys.job_key(job, "progress"), self._progress, msg.JobProgress),
            bus.declare_subscriber(session, keys.job_key(job, "artifacts"), self._artifact, msg.JobArtifact),
            bus.declare_subscriber(session, keys.job_key(job, "result"), self._result, msg.JobResult),
        ]
        if on_poses is not None:
            self._subs.append(
                bus.declare_subscriber(
                    session, keys.job_key(job, "poses"), lambda m, _s: on_poses(m), msg.PoseFrame
                )
            )
        for status in bus.request_all(session, keys.job_key(job, "status"), msg.JobStatus):
            self._status(status, None)
        for result in bus.request_all(session, keys.job_key(job, "result"), msg.JobResult):
            self._result(result, None)

    def _status(self, status: msg.JobStatus, _sample: Any) -> None:
        with self._cond:
            if self.status is not None and msg.status_rank(status) < msg.status_rank(self.status):
                return
            self.status = status
            self.history.append(status)
            self._cond.notify_all()
        if self._on_status is not None:
            self._on_status(status)

    def _progress(self, progress: msg.JobProgress, _sample: Any) -> None:
        with self._cond:
            self.progress = progress
            self._cond.notify_all()
        if self._on_progress is not None:
            self._on_progress(progress)

    def _artifact(self, artifact: msg.JobArtifact, _sample: Any) -> None:
        with self._cond:
            self.artifacts.append(artifact)
            self._cond.notify_all()
        if self._on_artifact is not None:
            self._on_artifact(artifact)

    def _result(self, result: msg.JobResult, _sample: Any) -> None:
        with self._cond:
            if self.result is None or result.attempt >= self.result.attempt:
                self.result = result
            self._cond.notify_all()

    def wait(
        self, predicate: Callable[[JobWatch], bool] | None = None, timeout: float = 10.0
    ) -> msg.JobStatus | None:
        """Wait until ``predicate(self)`` (default: the job is finished); returns the latest status.

        Raises TimeoutError if it does not happen within ``timeout`` seconds.
        """
        pred = predicate or (lambda w: w.status is not None and w.status.terminal)
        deadline = time.monotonic() + timeout
        with self._cond:
            while not pred(self):
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(
                        f"job {self.job}: condition not reached within {timeout} s (status {self.status})"
                    )
                self._cond.wait(min(left, 0.1))
            return self.status

    def close(self) -> None:
        for sub in self._subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass

    def __enter__(self) -> JobWatch:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class JobClient:
    """Submit, list, watch and cancel jobs through the hub's queue."""

    def __init__(self, session: zenoh.Session, timeout: float = 5.0):
        self.session = session
        self.timeout = timeout

    def submit(
        self,
        kind: str,
        spec: dict[str, Any],
        *,
        worker_kind: str | None = None,
        requeue_on_worker_loss: bool | None = None,
        max_attempts: int = 3,
        job: str | None = None,
    ) -> msg.JobStatus:
        """Queue a job; the defaults for a known kind come from :data:`JOB_KINDS`."""
        known = JOB_KINDS.get(kind)
        if worker_kind is None:
            if known is None:
                raise ValueError(f"job kind {kind!r} is not in JOB_KINDS; pass worker_kind=")
            worker_kind = known.worker_kind
        if requeue_on_worker_loss is None:
            requeue_on_worker_loss = known.requeue_on_worker_loss if known is not None else False
        job = job or new_job_id(kind)
        submit = msg.JobSubmit(
            job=job,
            kind=kind,
            worker_kind=worker_kind,
            spec=spec,
            requeue_on_worker_loss=requeue_on_worker_loss,
            max_attempts=max_attempts,
        )
        return bus.request(
            self.session, keys.job_key(job, "submit"), submit, msg.JobStatus, timeout=self.timeout
        )

    def cancel(self, job: str, reason: str = "") -> msg.JobStatus:
        return bus.request(
            self.session,
            keys.job_key(job, "cancel"),
            msg.JobCancel(job=job, reason=reason),
            msg.JobStatus,
            timeout=self.timeout,
        )

    def list(self) -> list[msg.JobStatus]:
        """Every job the queue knows, oldest first."""
        statuses = bus.request_all(self.session, keys.all_jobs("status"), msg.JobStatus, timeout=self.timeout)
        return sorted(statuses, key=lambda s: (s.submitted_at, s.job))

    def status(self, job: str) -> msg.JobStatus | None:
        found = bus.request_all(
            self.session, keys.job_key(job, "status"), msg.JobStatus, timeout=self.timeout
        )
        return max(found, key=msg.status_rank) if found else None

    def result(self, job: str) -> msg.JobResult | None:
        found = bus.request_all(
            self.session, keys.job_key(job, "result"), msg.JobResult, timeout=self.timeout
        )
        return max(found, key=lambda r: r.attempt) if found else None

    def watch(self, job: str, **callbacks: Any) -> JobWatch:
        return JobWatch(self.session, job, **callbacks)
