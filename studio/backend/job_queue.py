"""The hub's job queue: it assigns jobs to workers, watches them and journals every change.

The client side (submit, watch, cancel) is :mod:`studio.backend.job_client`; the journal file is
:mod:`studio.backend.job_journal`.

Life of a job::

    JobClient.submit ──JobSubmit──▶ JobQueue ──JobAssign──▶ worker (JobRunner) ──▶ handler
          ▲                            │ status: queued          status: running, progress,
          └──── JobWatch ◀─────────────┴──────────────────────── artifacts, result, succeeded|failed|cancelled

* **Queue**: jobs wait (FIFO) until a worker of the right kind that offers the job's kind is idle. A submitted
  spec is capped in size (:data:`MAX_SPEC_BYTES`) and, for a kind of :data:`~studio.backend.job_runner.JOB_KINDS`,
  checked against the kind's typed spec before it is queued (:func:`~studio.backend.job_runner.check_spec`).
* **Scale**: submit, cancel and a job's status cost O(log n) in the number of jobs: queued jobs are kept
  in sorted lists per (worker kind, job kind), so "N ahead" is a binary search, and the dispatcher looks
  only at the heads of those lists. An idle queue does no work. Positions are exact whenever a status is
  asked for; pushed updates of them go, at most once a second, to the first :data:`PUSHED_POSITIONS` jobs of a
  queue (a job further back learns its new place when it moves up or is asked for).
* **Faults**: the queue follows workers through :class:`~studio.backend.presence.Directory`. When a
  worker's liveliness token disappears, each of its running jobs is failed with the reason, or — if it
  was submitted with ``requeue_on_worker_loss`` (training) and has attempts left — queued again and
  handed to the next free worker with ``attempt + 1``.
* **Journal**: every state change is appended to a journal file (one JSON line per change, flushed at
  once and synced to disk at most once a second); the file is rewritten whole only to compact it, when it
  has grown to twice the live jobs. Finished jobs beyond the newest :data:`KEEP_FINISHED` are pruned (never an
  unfinished one). A journal write that fails (disk full, read-only) is logged once and retried; the status
  is published regardless, the queue goes on from memory, and the journal is rewritten as soon as writing
  works again.
* **Restarts**: a restarted queue reloads the journal, asks every worker which jobs it holds (``…/jobs``),
  re-attaches to the running ones, and gives workers that were running a job when it went down
  ``reattach_grace_s`` to reconnect before declaring them lost. Jobs the journal has as queued are held
  back for that long too, so that a job that ran (and ended) while the journal could not be written is
  learnt from its worker instead of being run again.
* **Listing**: the queue answers ``studio/jobs/*/status`` (and ``…/result``, ``…/progress``), so a
  restarted UI lists jobs with one query and then watches the ones it shows.

Workers report on ``…/report``, which only the queue hears; the queue is the one publisher of
``…/status`` and publishes a state only after recording it, so what a watcher sees is already listed.
A report counts only for a job the queue holds, from the worker it assigned that attempt to (anything else
is logged, rate-limited, and dropped: a forged report can neither block the queue nor end another
worker's job). Of two statuses of one job, the one with the larger
:func:`~studio.backend.messages.status_rank` wins (attempt, then queued < running < finished), so late or
repeated reports do no harm.
"""

from __future__ import annotations

import bisect
import heapq
import itertools
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.job_journal import JournalEntry, JournalError, JournalFile
from studio.backend.job_runner import JOB_KINDS, check_spec
from studio.backend.presence import Directory, WorkerEntry

#: Largest job spec the queue accepts, as JSON bytes (a spec names files and options, never data).
MAX_SPEC_BYTES = 64 << 10
#: Largest JobSubmit request payload the queue decodes.
MAX_SUBMIT_BYTES = 2 * MAX_SPEC_BYTES
#: Most unfinished (queued or running) jobs the queue holds at once.
MAX_UNFINISHED = 100_000
#: Finished jobs the queue (and its journal) keeps, newest first; older ones are pruned.
KEEP_FINISHED = 500
#: Queued jobs per queue whose changed position is pushed on ``…/status``.
PUSHED_POSITIONS = 100
#: How long a worker's report that its job ended waits for the result it published just before.
RESULT_WAIT_S = 5.0


@dataclass
class _Job:
    status: msg.JobStatus
    result: msg.JobResult | None = None
    progress: msg.JobProgress | None = None
    cancel_reason: str | None = None
    #: When set, the job's worker is missing; at this time the worker-loss policy applies.
    lost_deadline: float | None = None

    @property
    def key(self) -> tuple[float, str]:
        """Its place in the queue: submission time, then id."""
        return (self.status.submitted_at, self.status.job)


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
        reattach_grace_s: how long, after a restart, a worker that was running a job may take to reconnect
            (and how long jobs the journal has as queued wait for their workers' word before they run).
        assign_timeout_s: how long to wait for a worker to accept an assignment.
        keep_finished: finished jobs kept (newest first); older ones are pruned from memory and journal.
    """

    def __init__(
        self,
        session: zenoh.Session,
        directory: Directory,
        *,
        journal: str | os.PathLike | None = None,
        reattach_grace_s: float = 5.0,
        assign_timeout_s: float = 3.0,
        keep_finished: int = KEEP_FINISHED,
    ):
        self.session = session
        self.directory = directory
        self.journal_path = Path(journal) if journal is not None else None
        self.reattach_grace_s = reattach_grace_s
        self.assign_timeout_s = assign_timeout_s
        self.keep_finished = keep_finished
        self._cond = threading.Condition()
        self._jobs: dict[str, _Job] = {}
        #: (worker kind, job kind) -> sorted queue keys of its queued jobs
        self._queues: dict[tuple[str, str], list[tuple[float, str]]] = {}
        self._running_on: dict[str, set[str]] = {}  # worker id -> ids of its running jobs
        self._lost: set[str] = set()  # ids of running jobs whose worker is missing (lost_deadline set)
        self._finished: OrderedDict[str, None] = OrderedDict()  # ids of finished jobs, oldest first
        self._unfinished = 0
        self._assigned: dict[str, _Assignment] = {}  # worker id -> what the queue believes it runs
        self._skip_until: dict[str, float] = {}  # worker id -> do not offer it jobs before this time
        self._held: list[str] = []  # jobs loaded as queued, not offered before _held_until
        self._held_until = 0.0
        self._positions_dirty: set[str] = set()  # worker kinds whose pushed positions may be stale
        self._positions_at = 0.0
        self._pending = _Pending()
        self._closed = False
        self._journal = JournalFile(self.journal_path) if self.journal_path is not None else None
        self._journal_failed_at: float | None = None  # when set, the journal lags memory; rewrite it
        self._journal_synced_at = 0.0
        self._load_journal()
        remote = {"allowed_origin": zenoh.Locality.REMOTE}
        self._entities: list[Any] = [
            bus.declare_queryable(
                session, keys.all_jobs("submit"), self._on_submit, msg.JobSubmit, max_bytes=MAX_SUBMIT_BYTES
            ),
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
        with self._cond:
            if self._journal is not None:
                if self._journal_failed_at is not None:
                    self._rewrite_journal_locked()
                self._journal.close()

    # ------------------------------------------------------------------ journal
    def _load_journal(self) -> None:
        if self._journal is None or self.journal_path is None or not self.journal_path.exists():
            return
        try:
            entries, compact = self._journal.load()
        except (JournalError, OSError) as e:
            keep = self.journal_path.with_name(f"{self.journal_path.name}.unreadable-{int(time.time())}")
            try:
                self.journal_path.rename(keep)
            except OSError:
                keep = self.journal_path
            bus.log.error(
                "job journal %s is unreadable (%s); kept it as %s and started empty",
                self.journal_path,
                e,
                keep,
            )
            return
        deadline = time.monotonic() + self.reattach_grace_s
        for entry in entries:
            job = _Job(status=entry.status, result=entry.result)
            self._jobs[entry.status.job] = job
            s = entry.status
            if s.state == "running":
                job.lost_deadline = deadline  # until its worker shows up and confirms
                self._lost.add(s.job)
                if s.worker:
                    self._assigned[s.worker] = _Assignment(s.job, s.kind, s.worker, s.attempt)
            if s.state == "queued":
                self._held.append(s.job)
            self._index_locked(None, s)
            if s.state == "queued":
                self._unindex_queued_locked(job.key, s)  # held back until the workers had their say
        if self._held:
            self._held_until = deadline
        pruned = self._prune_locked()
        if compact or pruned or self._journal.lines > 2 * len(self._jobs) + 100:
            self._rewrite_journal_locked()

    def _record_locked(self, job: _Job) -> None:
        """Append the job's state to the journal; a failure is logged (once until it works again) and the
        journal is rewritten from memory later."""
        if self._journal is None:
            return
        if self._journal_failed_at is not None:
            return  # the rewrite that follows the failure will hold this change
        try:
            self._journal.append([JournalEntry(job.status, job.result)])
        except OSError as e:
            self._journal_failed(e)

    def _journal_failed(self, e: OSError) -> None:
        self._journal_failed_at = time.monotonic()
        bus.bad_input_log.warning(
            "journal",
            "could not write the job journal %s: %s; jobs go on from memory and the journal is rewritten "
            "once writing works again",
            self.journal_path,
            e.strerror or e,
        )

    def _rewrite_journal_locked(self) -> bool:
        if self._journal is None:
            return True
        try:
            self._journal.compact([JournalEntry(j.status, j.result) for j in self._jobs.values()])
        except OSError as e:
            self._journal_failed(e)
            return False
        if self._journal_failed_at is not None:
            bus.log.warning("the job journal %s is written again", self.journal_path)
        self._journal_failed_at = None
        return True

    def _journal_upkeep_locked(self, now: float) -> None:
        """Rewrite a journal that lagged or grew long; sync appended entries at most once a second."""
        j = self._journal
        if j is None:
            return
        if self._journal_failed_at is not None:
            if now - self._journal_failed_at >= 1.0:
                self._rewrite_journal_locked()
            return
        if j.lines > 2 * len(self._jobs) + 1000:
            self._rewrite_journal_locked()
        elif now - self._journal_synced_at >= 1.0:
            self._journal_synced_at = now
            try:
                j.sync()
            except OSError as e:
                self._journal_failed(e)

    # ------------------------------------------------------------------ indexes (lock held)
    def _index_locked(self, old: msg.JobStatus | None, new: msg.JobStatus) -> None:
        """Move a job between the indexes as its status goes from ``old`` to ``new``."""
        key = (new.submitted_at, new.job)
        if old is not None:
            if old.state == "queued":
                self._unindex_queued_locked(key, old)
            elif old.state == "running" and old.worker:
                running = self._running_on.get(old.worker)
                if running is not None:
                    running.discard(old.job)
                    if not running:
                        del self._running_on[old.worker]
            if not old.terminal:
                self._unfinished -= 1
        if new.state == "queued":
            bisect.insort(self._queues.setdefault((new.worker_kind, new.kind), []), key)
            self._positions_dirty.add(new.worker_kind)
        elif new.state == "running" and new.worker:
            self._running_on.setdefault(new.worker, set()).add(new.job)
        if new.terminal:
            self._finished.pop(new.job, None)
            self._finished[new.job] = None
        else:
            self._unfinished += 1

    def _unindex_queued_locked(self, key: tuple[float, str], status: msg.JobStatus) -> None:
        qkey = (status.worker_kind, status.kind)
        q = self._queues.get(qkey)
        if q is None:
            return
        i = bisect.bisect_left(q, key)
        if i < len(q) and q[i] == key:
            del q[i]
            self._positions_dirty.add(status.worker_kind)
        if not q:
            del self._queues[qkey]

    def _prune_locked(self) -> int:
        """Forget the oldest finished jobs beyond ``keep_finished``; returns how many."""
        n = 0
        while len(self._finished) > self.keep_finished:
            job_id, _ = self._finished.popitem(last=False)
            self._jobs.pop(job_id, None)
            n += 1
        return n

    def _position_locked(self, status: msg.JobStatus) -> int:
        """Queued jobs of the same worker kind ahead of this one (O(job kinds · log n))."""
        key = (status.submitted_at, status.job)
        return sum(
            bisect.bisect_left(q, key) for (wk, _k), q in self._queues.items() if wk == status.worker_kind
        )

    # ------------------------------------------------------------------ state changes (lock held)
    def _set_status_locked(self, job: _Job, status: msg.JobStatus, publish: bool = True) -> None:
        """Record a status change: indexes, journal (a failing write is logged, never raised), publication."""
        old = job.status if self._jobs.get(status.job) is job and job.status is not status else None
        if old is not None:
            self._index_locked(old, status)
        job.status = status
        if status.terminal or status.state == "queued":
            owner = status.worker or ""
            a = self._assigned.get(owner)
            if a is not None and a.job == status.job:
                del self._assigned[owner]
        if job.lost_deadline is not None and status.state != "running":
            job.lost_deadline = None
            self._lost.discard(status.job)
        self._record_locked(job)
        if publish:
            self._publish(keys.job_key(status.job, "status"), status)
        if status.terminal:
            self._prune_locked()
        self._cond.notify_all()

    def _add_job_locked(self, status: msg.JobStatus) -> _Job:
        job = _Job(status=status)
        self._jobs[status.job] = job
        self._index_locked(None, status)
        return job

    def _publish(self, key: str, message: msg.Message) -> None:
        try:
            self.session.put(key, msg.encode(message), congestion_control=bus.MUST_ARRIVE)
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
        self._lost.discard(s.job)
        if s.worker:
            self._assigned.pop(s.worker, None)
        if new.state == "queued":
            new = self._with_queue_info_locked(new)
        self._set_status_locked(job, new)

    # ------------------------------------------------------------------ queryables
    def _on_submit(self, submit: msg.JobSubmit, query: zenoh.Query) -> msg.Message:
        job_id, _ = keys.parse_job_key(str(query.key_expr))
        if job_id != submit.job:
            return msg.ErrorReply(
                code="bad_request", message=f"JobSubmit for {submit.job} sent to job {job_id}"
            )
        size = len(msgspec.json.encode(submit.spec))
        if size > MAX_SPEC_BYTES:
            return msg.ErrorReply(
                code="bad_request",
                message=f"job spec of {size} bytes exceeds the {MAX_SPEC_BYTES} bytes a spec may have",
            )
        known = JOB_KINDS.get(submit.kind)
        if known is not None and submit.worker_kind != known.worker_kind:
            return msg.ErrorReply(
                code="bad_request",
                message=f"{submit.kind} jobs run on {known.worker_kind} workers, not {submit.worker_kind}",
            )
        try:
            check_spec(submit.kind, submit.spec)
        except ValueError as e:
            return msg.ErrorReply(code="bad_request", message=str(e).splitlines()[0][:4000])
        with self._cond:
            if self._closed:
                return msg.ErrorReply(code="unavailable", message="the job queue is shutting down")
            existing = self._jobs.get(submit.job)
            if existing is not None:
                same = (existing.status.kind, existing.status.spec) == (submit.kind, submit.spec)
                if same:
                    return self._fresh_locked(existing.status)  # a retried submission
                return msg.ErrorReply(code="conflict", message=f"job {submit.job} exists with another spec")
            if self._unfinished >= MAX_UNFINISHED:
                return msg.ErrorReply(
                    code="busy", message=f"the queue holds its maximum of {MAX_UNFINISHED} unfinished jobs"
                )
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
            job = self._add_job_locked(status)
            status = self._with_queue_info_locked(status)
            job.status = status
            self._record_locked(job)
            self._publish(keys.job_key(status.job, "status"), status)
            self._cond.notify_all()
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

    def _fresh_locked(self, status: msg.JobStatus) -> msg.JobStatus:
        """A queued job's status with its position as of now; any other status as it is."""
        return self._with_queue_info_locked(status) if status.state == "queued" else status

    def _on_list(
        self, leaf: str
    ) -> Callable[[msg.Message | None, zenoh.Query], list[tuple[str, msg.Message]]]:
        def item_of(job: _Job) -> msg.Message | None:
            if leaf == "status":
                return self._fresh_locked(job.status)
            return job.result if leaf == "result" else job.progress

        def handler(_request: msg.Message | None, query: zenoh.Query) -> list[tuple[str, msg.Message]]:
            selector = str(query.key_expr)
            out: list[tuple[str, msg.Message]] = []
            try:
                one, _ = keys.parse_job_key(selector)  # one job's key: a lookup
            except keys.KeyExprError:
                one = None
            with self._cond:
                if one is not None:
                    job = self._jobs.get(one)
                    item = None if job is None else item_of(job)
                    return [] if item is None else [(keys.job_key(one, leaf), item)]
                asked = zenoh.KeyExpr(selector)
                for job_id, job in self._jobs.items():
                    key = keys.job_key(job_id, leaf)
                    if asked.intersects(zenoh.KeyExpr(key)):
                        item = item_of(job)
                        if item is not None:
                            out.append((key, item))
            return out

        return handler

    # ------------------------------------------------------------------ subscriptions (workers' reports)
    def _on_worker_status(self, status: msg.JobStatus, sample: zenoh.Sample) -> None:
        self._merge_status(status, None)

    def _ignore(self, status: msg.JobStatus, why: str) -> None:
        bus.bad_input_log.warning(
            "job-report",
            "ignored a %s report of job %s from %s: %s",
            status.state,
            status.job,
            status.worker,
            why,
        )

    def _merge_status(self, status: msg.JobStatus, source: str | None) -> None:
        """Apply a worker's account of a job. ``source`` is the worker whose own queryable gave it (its answer
        to an assignment or to ``…/jobs``); None for a report on ``…/report``, which anyone could have sent and
        which counts only from the worker the queue assigned that attempt to.

        The queue publishes the merged status on ``…/status`` after recording it, so a watcher never sees a
        state that :meth:`JobClient.list` does not list yet."""
        with self._cond:
            if not status.worker:
                return self._ignore(status, "it names no worker")
            if source is not None and status.worker != source:
                return self._ignore(status, f"worker {source} answered for another worker")
            job = self._jobs.get(status.job)
            if job is None:
                if source is None:
                    return self._ignore(status, "the queue holds no such job")
                if status.state != "running":
                    return  # a job the queue finished and pruned (or never had): nothing to do
                # A job its worker runs that the queue never heard of (its journal was lost): adopt it.
                job = self._add_job_locked(status)
                self._assigned[status.worker] = _Assignment(
                    status.job, status.kind, status.worker, status.attempt
                )
                self._record_locked(job)
                self._publish(keys.job_key(status.job, "status"), status)
                return
            cur = job.status
            a = self._assigned.get(status.worker)
            assigned = a is not None and (a.job, a.attempt) == (status.job, status.attempt)
            if (
                source is None
                and not assigned
                and not (
                    cur.state == "running" and cur.worker == status.worker and cur.attempt == status.attempt
                )
            ):
                return self._ignore(
                    status, f"attempt {status.attempt} of the job is not assigned to that worker"
                )
            if status.attempt != cur.attempt:
                if status.state == "running" and status.attempt < cur.attempt:
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
            if (status.worker_kind, status.kind, status.submitted_at) != (
                cur.worker_kind,
                cur.kind,
                cur.submitted_at,
            ):
                return self._ignore(status, "it does not match the job the queue holds")
            if status.state == "running":
                job.lost_deadline = None
                self._lost.discard(status.job)
                self._assigned[status.worker] = _Assignment(
                    status.job, status.kind, status.worker, status.attempt
                )
                if cur.state == "running" and cur.worker == status.worker:
                    job.status = status
                    return
            if (
                source is None
                and status.terminal
                and status.has_result
                and not self._wait_result_locked(job, status)
            ):
                return  # the job moved on while the result was awaited
            self._set_status_locked(job, status)

    def _wait_result_locked(self, job: _Job, status: msg.JobStatus) -> bool:
        """Wait (on a report's thread, the lock released meanwhile) until the result the worker published before
        ``status`` is in: results and reports arrive on different subscribers' threads, and a watcher that sees
        the job end reads its result next. False if the job got as far as ``status`` or further meanwhile (another
        end, a later attempt); a repeated ``running`` of the same attempt (the worker's answer to its assignment
        can arrive after its end) does not count."""
        deadline = time.monotonic() + RESULT_WAIT_S
        while job.result is None or job.result.attempt != status.attempt:
            left = deadline - time.monotonic()
            if left <= 0:
                bus.log.warning(
                    "job %s ended without its result arriving within %.0f s", status.job, RESULT_WAIT_S
                )
                break
            self._cond.wait(left)
        return msg.status_rank(job.status) < msg.status_rank(status)

    def _on_result(self, result: msg.JobResult, sample: zenoh.Sample | None) -> None:
        with self._cond:
            job = self._jobs.get(result.job)
            if job is None or result.attempt != job.status.attempt:
                return
            if job.status.state != "running" and job.result is not None:
                return  # the attempt's result is in; a later copy does not replace it
            job.result = result
            self._record_locked(job)
            self._cond.notify_all()  # a report that ended the attempt may be waiting for it

    def _on_progress(self, progress: msg.JobProgress, sample: zenoh.Sample) -> None:
        with self._cond:
            job = self._jobs.get(progress.job)
            if job is not None and progress.attempt == job.status.attempt and job.status.state == "running":
                job.progress = progress

    def _on_directory(self, event: str, entry: WorkerEntry) -> None:
        with self._cond:
            if event == "joined":
                self._pending.reattach.add((entry.kind, entry.worker))
            elif event == "left":
                self._skip_until.pop(entry.worker, None)
                for job_id in self._running_on.get(entry.worker, ()):
                    job = self._jobs[job_id]
                    job.lost_deadline = time.monotonic()
                    self._lost.add(job_id)
            self._positions_dirty.add(entry.kind)  # the reasons of its queued jobs may change
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
                for job_id in list(self._lost):
                    job = self._jobs.get(job_id)
                    if job is None or job.status.state != "running" or job.lost_deadline is None:
                        self._lost.discard(job_id)
                        continue
                    if now >= job.lost_deadline:
                        if job.status.worker and self.directory.is_alive(job.status.worker):
                            job.lost_deadline = None  # it came back; the re-attach query settles the rest
                            self._lost.discard(job_id)
                            continue
                        self._apply_worker_loss_locked(job)
                if self._held and now >= self._held_until:
                    for job_id in self._held:
                        held = self._jobs.get(job_id)
                        if held is not None and held.status.state == "queued":
                            bisect.insort(
                                self._queues.setdefault((held.status.worker_kind, held.status.kind), []),
                                held.key,
                            )
                            self._positions_dirty.add(held.status.worker_kind)
                    self._held = []
                self._journal_upkeep_locked(now)
            try:
                for kind, worker in reattach:
                    self._reattach(kind, worker)
                for kind, worker, cancel in cancels:
                    self._forward_cancel(kind, worker, cancel)
                self._dispatch()
                self._push_positions()
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
        finished = set()
        for m in replies:
            if isinstance(m, msg.JobStatus):
                if m.state == "running":
                    held.add(m.job)
                else:
                    finished.add(m.job)
                self._merge_status(m, worker)
            elif isinstance(m, msg.JobResult):
                self._on_result(m, None)
        with self._cond:
            # The queue believed this worker runs a job it does not report: treat the attempt as lost.
            for job_id in list(self._running_on.get(worker, ())):
                if job_id not in held and job_id not in finished:
                    self._apply_worker_loss_locked(self._jobs[job_id])

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
        position = self._position_locked(status)
        entries = self.directory.workers(status.worker_kind)
        capable = [e for e in entries if e.status is not None and status.kind in e.status.job_kinds]
        if capable:
            reason = f"waiting for a free {status.worker_kind} worker ({position} ahead)"
        else:
            missing = [
                f"{e.worker}: {e.status.unavailable.get(status.kind, 'does not offer it')}"
                for e in entries
                if e.status is not None
            ]
            reason = f"no connected {status.worker_kind} worker can run {status.kind!r} jobs"
            if missing:
                reason += " (" + "; ".join(missing) + ")"
        if status.reason.startswith("worker ") and "re-queued" in status.reason:
            reason = status.reason.split("; waiting for", 1)[0].split("; no connected", 1)[0] + "; " + reason
        return msgspec.structs.replace(status, queue_position=position, reason=reason[:4000])

    def _push_positions(self) -> None:
        """Publish the changed positions and reasons of the first queued jobs of each queue that changed
        (at most once a second); a queued job's place is not journaled, it is worked out when asked for."""
        with self._cond:
            now = time.monotonic()
            if not self._positions_dirty or now - self._positions_at < 1.0:
                return
            self._positions_at = now
            dirty, self._positions_dirty = self._positions_dirty, set()
            for worker_kind in dirty:
                queues = [q for (wk, _k), q in self._queues.items() if wk == worker_kind]
                for _, job_id in itertools.islice(heapq.merge(*queues), PUSHED_POSITIONS):
                    job = self._jobs[job_id]
                    updated = self._with_queue_info_locked(job.status)
                    if (updated.queue_position, updated.reason) != (
                        job.status.queue_position,
                        job.status.reason,
                    ):
                        job.status = msgspec.structs.replace(updated, updated_at=time.time())
                        self._publish(keys.job_key(job_id, "status"), job.status)

    def _choose_locked(self, now: float) -> tuple[_Job, WorkerEntry] | None:
        """The oldest queued job some idle worker offers, and that worker (O(workers · job kinds · 1))."""
        worker_kinds = {wk for wk, _k in self._queues}
        best: tuple[tuple[float, str], WorkerEntry] | None = None
        for worker_kind in worker_kinds:
            for entry in self.directory.workers(worker_kind):
                st = entry.status
                if (
                    st is None
                    or st.state != "idle"
                    or entry.worker in self._assigned
                    or self._skip_until.get(entry.worker, 0.0) > now
                ):
                    continue
                for kind in st.job_kinds:
                    q = self._queues.get((worker_kind, kind))
                    if q and (best is None or q[0] < best[0]):
                        best = (q[0], entry)
        if best is None:
            return None
        return self._jobs[best[0][1]], best[1]

    def _dispatch(self) -> None:
        while True:
            with self._cond:
                if self._closed:
                    return
                choice = self._choose_locked(time.monotonic())
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
            self._merge_status(running, entry.worker)
            with self._cond:
                if job.status.state == "queued" and job.status.attempt == assign.attempt:
                    # The worker answered with something else than this attempt running: offer it elsewhere.
                    a = self._assigned.get(entry.worker)
                    if a is not None and a.job == assign.job:
                        del self._assigned[entry.worker]
                    self._skip_until[entry.worker] = time.monotonic() + 1.0
