"""The jobs the browser studio follows, shared by every tab: status, progress history, plans, live poses.

A job is followed once (one :class:`~studio.backend.job_client.JobWatch` per job for the whole app), however
many tabs show it, so that every viewer of a running rollout sees the same stream. Tabs read the state
of a :class:`TrackedJob` when they refresh and subscribe to its poses while they display it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from studio.backend import messages as msg
from studio.backend.job_client import JobClient, JobWatch

#: Progress records kept per job (training curves come from the run's metrics file when it is readable).
MAX_HISTORY = 5000


class TrackedJob:
    """One followed job. Attributes are replaced atomically; read them without locking."""

    def __init__(self, job: str, kind: str, spec: dict, started_by: int | None):
        self.job, self.kind, self.spec, self.started_by = job, kind, dict(spec), started_by
        self.status: msg.JobStatus | None = None
        self.progress: msg.JobProgress | None = None
        self.result: dict | None = None
        self.history: list[msg.JobProgress] = []
        self.messages: list[str] = []
        self.plans: list[np.ndarray] = []
        self.artifacts: list[msg.JobArtifact] = []
        self.poses_seen = 0
        self._pose_listeners: list[Callable[[msg.PoseFrame], None]] = []
        self._lock = threading.Lock()
        self.watch: JobWatch | None = None
        self.created = time.time()

    @property
    def state(self) -> str:
        return self.status.state if self.status is not None else "submitting"

    @property
    def terminal(self) -> bool:
        return self.status is not None and self.status.terminal

    def add_pose_listener(self, fn: Callable[[msg.PoseFrame], None]) -> None:
        with self._lock:
            self._pose_listeners.append(fn)

    def remove_pose_listener(self, fn: Callable[[msg.PoseFrame], None]) -> None:
        with self._lock:
            if fn in self._pose_listeners:
                self._pose_listeners.remove(fn)

    # callbacks (Zenoh threads)
    def _on_status(self, status: msg.JobStatus) -> None:
        if not self.spec and status.spec:  # followed before its spec was known (see JobBoard.follow)
            self.spec = dict(status.spec)
        self.status = status

    def _on_progress(self, p: msg.JobProgress) -> None:
        self.progress = p
        if len(self.history) < MAX_HISTORY:
            self.history.append(p)
        if p.message and (not self.messages or self.messages[-1] != p.message):
            self.messages.append(p.message)
        if "wp0_x" in p.metrics:
            rows = [[p.metrics.get(f"wp{i}_{c}", np.nan) for c in "xyzg"] for i in range(5)]
            self.plans.append(np.asarray(rows, dtype=np.float64))

    def _on_artifact(self, a: msg.JobArtifact) -> None:
        self.artifacts.append(a)

    def _on_poses(self, frame: msg.PoseFrame) -> None:
        self.poses_seen += 1
        with self._lock:
            listeners = list(self._pose_listeners)
        for fn in listeners:
            fn(frame)


class JobBoard:
    """Submits jobs and follows them; :meth:`poll` fetches results of jobs that finished."""

    def __init__(self, client: JobClient):
        self.client = client
        self._jobs: dict[str, TrackedJob] = {}
        self._lock = threading.Lock()

    def submit(self, kind: str, spec: dict, started_by: int | None = None, **kwargs) -> TrackedJob:
        status = self.client.submit(kind, spec, **kwargs)
        tracked = self.follow(status.job, kind, spec, started_by)
        if tracked.status is None:
            tracked.status = status
        return tracked

    def follow(
        self, job: str, kind: str, spec: dict | None = None, started_by: int | None = None
    ) -> TrackedJob:
        with self._lock:
            tracked = self._jobs.get(job)
            if tracked is not None:
                # A tab refreshing between choosing a job id and submitting it follows the job with no spec
                # yet; the spec (where its run writes its curves) and who started it are filled in when known.
                if not tracked.spec and spec:
                    tracked.spec = dict(spec)
                if tracked.started_by is None:
                    tracked.started_by = started_by
                return tracked
            tracked = TrackedJob(job, kind, spec or {}, started_by)
            self._jobs[job] = tracked
        watch = self.client.watch(
            job,
            on_status=tracked._on_status,
            on_progress=tracked._on_progress,
            on_artifact=tracked._on_artifact,
            on_poses=tracked._on_poses if kind == "rollout" else None,
        )
        tracked.watch = watch
        if watch.status is not None:
            tracked.status = watch.status
        return tracked

    def get(self, job: str) -> TrackedJob | None:
        with self._lock:
            return self._jobs.get(job)

    def jobs(self, kind: str | None = None) -> list[TrackedJob]:
        with self._lock:
            return sorted(
                (j for j in self._jobs.values() if kind is None or j.kind == kind), key=lambda j: j.created
            )

    def cancel(self, job: str, reason: str = "cancelled from the browser") -> msg.JobStatus:
        return self.client.cancel(job, reason)

    def poll(self) -> None:
        """Pick up results (and close the watches) of jobs that have finished."""
        for tracked in self.jobs():
            w = tracked.watch
            if w is None:
                continue
            if tracked.result is None and w.result is not None:
                tracked.result = dict(w.result.result)
            if tracked.terminal and (tracked.result is not None or tracked.state != "succeeded"):
                if time.time() - (tracked.status.updated_at if tracked.status else 0) > 2.0:
                    w.close()
                    tracked.watch = None

    def close(self) -> None:
        for tracked in self.jobs():
            if tracked.watch is not None:
                tracked.watch.close()
