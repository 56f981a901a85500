"""The client side of the job queue: submit, list, watch and cancel jobs over the bus.

:class:`JobClient` talks to the hub's :class:`~studio.backend.job_queue.JobQueue` (``JobSubmit``, ``JobCancel``,
listing by ``studio/jobs/*/status``); :class:`JobWatch` follows one job — its newest status (by
:func:`~studio.backend.messages.status_rank`), progress, artifacts, result and live poses. :func:`new_job_id`
names a job (kind, UTC time, random suffix), for callers that need the id before submitting.
"""

from __future__ import annotations

import secrets
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.job_runner import JOB_KINDS


def new_job_id(kind: str) -> str:
    """A new job's id: its kind, the UTC time to the second and 48 random bits (3,000 jobs submitted in one second
    share an id with odds below one in a million; with 24 bits, about one such burst in four did)."""
    return f"{kind}-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}-{secrets.token_hex(6)}"


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


#: How long :meth:`JobClient.submit` keeps asking a hub whose queue does not answer in time (a loaded machine). The
#: queue takes a repeated submission of a job id it holds, with the same spec, as that job, so asking again never
#: queues a job twice; giving up early could leave a queued job that nobody follows.
SUBMIT_PATIENCE_S = 30.0


class JobClient:
    """Submit, list, watch and cancel jobs through the hub's queue."""

    def __init__(self, session: zenoh.Session, timeout: float = 5.0, patience: float = SUBMIT_PATIENCE_S):
        self.session = session
        self.timeout = timeout
        self.patience = patience

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
        """Queue a job; the defaults for a known kind come from :data:`JOB_KINDS`. A submission the queue does not
        answer within ``timeout`` is sent again under the same job id for up to ``patience`` seconds
        (:data:`SUBMIT_PATIENCE_S`); then :class:`~studio.backend.bus.RequestTimeout` is raised."""
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
        deadline, tries = time.monotonic() + max(self.patience, self.timeout), 0
        while True:
            tries += 1
            try:
                return bus.request(
                    self.session, keys.job_key(job, "submit"), submit, msg.JobStatus, timeout=self.timeout
                )
            except bus.RequestTimeout as e:
                if time.monotonic() + self.timeout > deadline:
                    raise bus.RequestTimeout(f"{e} (asked {tries} times)") from e
                bus.log.info(
                    "job %s: the queue did not answer in %.1f s, asking again (same job)", job, self.timeout
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
