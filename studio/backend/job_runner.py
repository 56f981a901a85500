"""The worker side of jobs: the registry of job handlers, the context a handler works with, the runner.

A *handler* is a plain function ``handler(ctx: JobContext) -> dict | None`` that reads ``ctx.spec``,
reports through ``ctx.progress`` / ``ctx.artifact`` / ``ctx.poses``, checks ``ctx.cancelled`` (or calls
``ctx.raise_if_cancelled()``) at convenient points, and returns its result. It knows nothing of Zenoh,
so ``studio.model`` can provide one without importing the backend. Handlers are found through
:data:`JOB_KINDS` (``module:function`` strings imported when a worker starts) plus any
``--handler KIND=module:function`` given to ``studio worker``; a kind whose module cannot be imported
is announced as unavailable, with the reason, in the worker's status.

A worker runs one job at a time. If it dies, the job queue notices through its liveliness token and
fails or re-queues the job; a re-queued job is handed out again with the same spec and ``attempt + 1``,
and resuming (e.g. from the last checkpoint in the run directory the spec names) is the handler's job.
"""

from __future__ import annotations

import importlib
import threading
import time
import traceback
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, cast

import msgspec
import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.presence import WorkerPresence


@dataclass(frozen=True)
class JobKind:
    """A kind of job: which workers run it, with which handler, and what happens if its worker dies."""

    name: str
    worker_kind: str
    handler: str
    requeue_on_worker_loss: bool
    description: str
    #: ``module:function`` turning a raw spec into the kind's typed, bounded spec (``ValueError`` if it is not one).
    spec: str | None = None


#: Job kinds the studio knows. Their handlers live with the code they drive and are imported lazily.
JOB_KINDS: dict[str, JobKind] = {
    "train": JobKind(
        name="train",
        worker_kind="train",
        handler="studio.backend.train_job:run_training_job",
        requeue_on_worker_loss=True,
        spec="studio.backend.train_job:parse_spec",
        description="train OSVI-WM; spec: studio.backend.train_job.TrainJobSpec (resumes from run_dir)",
    ),
    "rollout": JobKind(
        name="rollout",
        worker_kind="sim",
        handler="studio.backend.rollout_job:run_rollout_job",
        requeue_on_worker_loss=False,
        spec="studio.backend.rollout_job:parse_spec",
        description="imitate one expert episode; spec: checkpoint, expert episode, task, seed, replans",
    ),
    "plan": JobKind(
        name="plan",
        worker_kind="sim",
        handler="studio.backend.plan_job:run_plan_job",
        requeue_on_worker_loss=False,
        spec="studio.backend.plan_job:parse_spec",
        description="plan (not execute) one imitation; spec as rollout; writes <data>/plans/<job>.npz",
    ),
    "compare": JobKind(
        name="compare",
        worker_kind="sim",
        handler="studio.backend.compare_job:run_compare_job",
        requeue_on_worker_loss=False,
        spec="studio.backend.compare_job:parse_spec",
        description="two checkpoints on the same seeded episodes; spec: a, b, tasks, episodes, seed, replan",
    ),
    "expert": JobKind(
        name="expert",
        worker_kind="sim",
        handler="studio.backend.expert_job:run_expert_job",
        requeue_on_worker_loss=False,
        spec="studio.backend.expert_job:parse_spec",
        description="record and store one scripted expert demonstration; spec: task, seed, robot",
    ),
    "collect": JobKind(
        name="collect",
        worker_kind="sim",
        handler="studio.backend.collect_job:run_collect_job",
        requeue_on_worker_loss=True,
        spec="studio.backend.collect_job:check_spec",
        description="scripted episodes in bulk, as studio collect; spec: studio.backend.collect_job.CollectJobSpec "
        "(re-queued, it makes only the episodes still missing)",
    ),
}

Handler = Callable[["JobContext"], "dict[str, Any] | None"]

_SPEC_PARSERS: dict[str, Callable[[Any], Any]] = {}


def check_spec(kind: str, spec: dict[str, Any]) -> Any:
    """The typed spec of a job of a :data:`JOB_KINDS` kind (None for another kind, whose handler checks it).

    Raises ``ValueError`` with one line naming what is wrong. The queue checks every submitted spec with it;
    the handlers check again on the worker (a worker cannot know who sent an assignment), and also that every
    path the spec names lies in the worker's data directory.
    """
    known = JOB_KINDS.get(kind)
    if known is None or known.spec is None:
        return None
    parse = _SPEC_PARSERS.get(kind)
    if parse is None:
        try:
            parse = cast(Callable[[Any], Any], load_handler(known.spec))
        except HandlerUnavailable as e:
            bus.log.debug("cannot check %s job specs here: %s", kind, e)
            return None
        _SPEC_PARSERS[kind] = parse
    return parse(spec)


class HandlerUnavailable(RuntimeError):
    """A handler reference cannot be imported or does not name a function."""


def load_handler(ref: str) -> Handler:
    """Import ``module:function``; raises :class:`HandlerUnavailable` with the reason."""
    module_name, sep, attr = ref.partition(":")
    if not sep or not module_name or not attr:
        raise HandlerUnavailable(f"handler reference {ref!r} must look like 'package.module:function'")
    try:
        module = importlib.import_module(module_name)
    except Exception as e:  # a broken module must not take the worker down with it
        raise HandlerUnavailable(f"cannot import {module_name}: {type(e).__name__}: {e}") from None
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise HandlerUnavailable(f"{module_name} has no function {attr!r}")
    return fn


def parse_handler_option(text: str) -> tuple[str, str]:
    """``KIND=module:function`` -> (kind, reference)."""
    kind, sep, ref = text.partition("=")
    if not sep:
        raise ValueError(f"--handler takes KIND=module:function, got {text!r}")
    return keys.check_chunk(kind.strip(), "job kind"), ref.strip()


def resolve_handlers(
    worker_kind: str, extra: Iterable[str] = (), *, defaults: bool = True
) -> tuple[dict[str, Handler], dict[str, str]]:
    """The handlers a worker of ``worker_kind`` offers, and the kinds it cannot offer with the reason.

    ``extra`` holds ``KIND=module:function`` texts; ``defaults=False`` leaves out :data:`JOB_KINDS`.
    """
    refs = {k.name: k.handler for k in JOB_KINDS.values() if defaults and k.worker_kind == worker_kind}
    for text in extra:
        kind, ref = parse_handler_option(text)
        refs[kind] = ref
    handlers: dict[str, Handler] = {}
    unavailable: dict[str, str] = {}
    for kind, ref in refs.items():
        try:
            handlers[kind] = load_handler(ref)
        except HandlerUnavailable as e:
            unavailable[kind] = str(e)
    return handlers, unavailable


class JobFiles(Protocol):
    """How a worker whose data dir is its own gets a job's inputs and hands over its outputs
    (:class:`studio.backend.artifact_transfer.WorkerArtifacts`)."""

    def prepare(self, spec: dict[str, Any]) -> tuple[dict[str, Any], str | None]:
        """Fetch the spec's inputs; the spec as this data dir's, and the hub's data dir (None: no inputs)."""
        ...

    def offer(self, path: str | Path) -> list[str]:
        """Hand a file (or a directory's files) to the hub's data dir."""
        ...

    def offer_episode(self, episode_id: str, rollout: Any = None) -> str:
        """Hand a stored episode (and the rollout it records) to the hub's store."""
        ...

    def as_hub_path(self, value: Any, hub_data_dir: str) -> Any:
        """``value`` with this data dir's paths (strings, also inside dicts and lists) as the hub's."""
        ...


class JobCancelled(Exception):
    """Raised by :meth:`JobContext.raise_if_cancelled` once the job has been cancelled."""


class JobContext:
    """What a handler sees of its job and of the bus.

    Attributes:
        job, kind, attempt: the job's id, kind and attempt number (1 for the first run).
        spec: the submitted specification (handler-defined, JSON-like).
        worker: id of the worker running it.
        data_dir: the worker's dataset root, if it was given one.
        session: the worker's Zenoh session (for handlers that publish more than progress).
        hub_data_dir: the hub's data dir the spec's paths were written for, when this worker's data dir is its
            own (the spec then names this worker's copies, fetched before the handler runs); else None.
    """

    def __init__(self, runner: JobRunner, assign: msg.JobAssign):
        self._runner = runner
        self.job = assign.job
        self.kind = assign.kind
        self.attempt = assign.attempt
        self.spec: dict[str, Any] = dict(assign.spec)
        self.worker = runner.presence.worker
        self.data_dir: Path | None = runner.data_dir
        self.session: zenoh.Session = runner.session
        self.hub_data_dir: str | None = None
        self._cancel = threading.Event()
        self.cancel_reason = ""
        self._started = time.monotonic()
        self._first_step: tuple[int, float] | None = None
        self._activity_at = -1.0

    @property
    def cancelled(self) -> bool:
        return self._cancel.is_set()

    def _request_cancel(self, reason: str) -> None:
        self.cancel_reason = reason or "cancelled"
        self._cancel.set()

    def raise_if_cancelled(self) -> None:
        if self._cancel.is_set():
            raise JobCancelled(self.cancel_reason or "cancelled")

    def wait_cancelled(self, timeout: float) -> bool:
        """Sleep up to ``timeout`` seconds, waking early (and returning True) when cancelled."""
        return self._cancel.wait(timeout)

    def progress(
        self,
        step: int,
        total: int | None = None,
        *,
        message: str = "",
        eta_s: float | None = None,
        **metrics: float,
    ) -> None:
        """Publish progress. Without ``eta_s`` the ETA is estimated from this attempt's step rate."""
        now = time.monotonic()
        if self._first_step is None:
            self._first_step = (step, now)
        if eta_s is None and total is not None:
            s0, t0 = self._first_step
            if step > s0 and now > t0:
                eta_s = max(0.0, (total - step) * (now - t0) / (step - s0))
        self._runner.publish(
            keys.job_key(self.job, "progress"),
            msg.JobProgress(
                job=self.job,
                attempt=self.attempt,
                step=max(0, int(step)),
                total=None if total is None else max(0, int(total)),
                metrics={k: float(v) for k, v in metrics.items()},
                message=message[:4000],
                eta_s=eta_s,
            ),
            must_arrive=False,
        )
        if total and now - self._activity_at >= 0.5:  # the worker's status says how far it is, at ≤ 2 Hz
            self._activity_at = now
            self._runner.presence.update(activity=f"{self.kind} job {self.job}: step {step}/{total}")

    def artifact(self, name: str, path: str | Path, step: int | None = None) -> None:
        """Announce a file the job has finished writing (a checkpoint, a stored rollout, ...); a worker whose data
        dir is its own first hands it to the hub (:meth:`output`) and announces it at its place there."""
        self.output(path)
        self._runner.publish(
            keys.job_key(self.job, "artifacts"),
            msg.JobArtifact(
                job=self.job, attempt=self.attempt, name=name, path=self.hub_path(path), step=step
            ),
        )

    def output(self, path: str | Path) -> None:
        """A file (or every file of a directory) the job wrote in the data dir for the studio to read: on a worker
        whose data dir is its own it is sent to the hub, which keeps it at the same place in its data dir (raises
        :class:`~studio.backend.artifact_transfer.TransferError` if the hub does not take it); else nothing to do."""
        if self._runner.artifacts is not None:
            self._runner.artifacts.offer(path)

    def output_episode(self, episode_id: str, rollout: Any = None) -> None:
        """An episode the job stored (with ``rollout``, the row of the rollout it records): on a worker whose data
        dir is its own it is added to the hub's store as it is; else nothing to do."""
        if self._runner.artifacts is not None:
            self._runner.artifacts.offer_episode(episode_id, rollout)

    def hub_path(self, path: str | Path) -> str:
        """``path`` of this worker's data dir as the same place in the hub's (unchanged when they are one)."""
        if self.hub_data_dir is None or self._runner.artifacts is None:
            return str(path)
        return str(self._runner.artifacts.as_hub_path(str(path), self.hub_data_dir))

    def poses(self, frame: msg.PoseFrame) -> None:
        """Stream the poses of a running simulation (latest wins) for live display."""
        self._runner.publish(keys.job_key(self.job, "poses"), frame, must_arrive=False)


@dataclass
class _Running:
    assign: msg.JobAssign
    ctx: JobContext
    status: msg.JobStatus
    thread: threading.Thread


class JobRunner:
    """Runs the jobs the queue assigns to this worker, one at a time, and reports on them.

    Declares ``…/assign``, ``…/cancel`` and ``…/jobs`` under the worker's key. Finished jobs are kept
    (the last ``keep_finished``) so that a restarted queue can learn how they ended.
    """

    def __init__(
        self,
        session: zenoh.Session,
        presence: WorkerPresence,
        handlers: dict[str, Handler],
        *,
        data_dir: Path | None = None,
        artifacts: JobFiles | None = None,
        keep_finished: int = 64,
    ):
        self.session = session
        self.presence = presence
        self.handlers = dict(handlers)
        self.data_dir = data_dir
        self.artifacts = artifacts
        self._lock = threading.Lock()
        self._current: _Running | None = None
        self._finished: deque[tuple[msg.JobStatus, msg.JobResult | None]] = deque(maxlen=keep_finished)
        self._shutting_down = False
        kind, worker = presence.kind, presence.worker
        self._queryables = [
            bus.declare_queryable(
                session, keys.worker_key(kind, worker, "assign"), self._on_assign, msg.JobAssign
            ),
            bus.declare_queryable(
                session, keys.worker_key(kind, worker, "cancel"), self._on_cancel, msg.JobCancel
            ),
            bus.declare_queryable(session, keys.worker_key(kind, worker, "jobs"), self._on_jobs),
        ]

    # ------------------------------------------------------------------ bus
    def publish(self, key: str, message: msg.Message, *, must_arrive: bool = True) -> None:
        """Publish a job's message; ``must_arrive=False`` for a stream whose newest sample supersedes the rest."""
        congestion = bus.MUST_ARRIVE if must_arrive else zenoh.CongestionControl.DROP
        try:
            self.session.put(key, msg.encode(message), congestion_control=congestion)
        except zenoh.ZError:
            bus.log.warning("could not publish on %s (session closed?)", key)

    def _status(self, assign: msg.JobAssign, state: msg.JobState, reason: str = "") -> msg.JobStatus:
        return msg.JobStatus(
            job=assign.job,
            kind=assign.kind,
            worker_kind=self.presence.kind,
            state=state,
            attempt=assign.attempt,
            worker=self.presence.worker,
            reason=reason[:4000],
            submitted_at=assign.submitted_at,
            updated_at=time.time(),
            spec=assign.spec,
            requeue_on_worker_loss=assign.requeue_on_worker_loss,
            max_attempts=assign.max_attempts,
        )

    def _on_assign(self, assign: msg.JobAssign, _query: zenoh.Query) -> msg.Message:
        with self._lock:
            cur = self._current
            if cur is not None:
                if (cur.assign.job, cur.assign.attempt) == (assign.job, assign.attempt):
                    return cur.status  # a retried assignment of the job we already run
                return msg.ErrorReply(code="busy", message=f"worker runs job {cur.assign.job}")
            if self._shutting_down:
                return msg.ErrorReply(code="unavailable", message="worker is shutting down")
            handler = self.handlers.get(assign.kind)
            if handler is None:
                return msg.ErrorReply(
                    code="unavailable", message=f"this worker has no handler for {assign.kind!r}"
                )
            ctx = JobContext(self, assign)
            status = self._status(assign, "running")
            thread = threading.Thread(
                target=self._run, args=(handler, ctx, assign), name=f"job-{assign.job}", daemon=True
            )
            self._current = _Running(assign, ctx, status, thread)
        self.presence.update(state="busy", job=assign.job, activity=f"{assign.kind} job {assign.job}")
        self.publish(keys.job_key(assign.job, "report"), status)
        thread.start()
        return status

    def _on_cancel(self, cancel: msg.JobCancel, _query: zenoh.Query) -> msg.Message:
        with self._lock:
            cur = self._current
            if cur is not None and cur.assign.job == cancel.job:
                cur.ctx._request_cancel(cancel.reason)
                return cur.status
            for status, _ in self._finished:
                if status.job == cancel.job:
                    return status
        return msg.ErrorReply(code="not_found", message=f"this worker does not hold job {cancel.job}")

    def _on_jobs(self, _request: msg.Message | None, query: zenoh.Query) -> list[tuple[str, msg.Message]]:
        """The worker's status first (so an empty listing is told apart from no answer), then one
        JobStatus (and JobResult) per job it runs or recently finished, all on the query's key."""
        key = str(query.key_expr)
        out: list[tuple[str, msg.Message]] = [(key, self.presence.status)]
        with self._lock:
            for status, result in self._finished:
                out.append((key, status))
                if result is not None:
                    out.append((key, result))
            if self._current is not None:
                out.append((key, self._current.status))
        return out

    # ------------------------------------------------------------------ running
    def _run(self, handler: Handler, ctx: JobContext, assign: msg.JobAssign) -> None:
        result: dict[str, Any] | None = None
        state: msg.JobState
        try:
            if self.artifacts is not None:
                ctx.progress(0, message="fetching the job's inputs from the hub")
                ctx.spec, ctx.hub_data_dir = self.artifacts.prepare(ctx.spec)
            result = handler(ctx)
            if result is not None and not isinstance(result, dict):
                raise TypeError(f"handler returned {type(result).__name__}, expected a dict or None")
            if result is not None and ctx.hub_data_dir is not None and self.artifacts is not None:
                result = self.artifacts.as_hub_path(result, ctx.hub_data_dir)
            state, reason = ("cancelled", ctx.cancel_reason) if ctx.cancelled else ("succeeded", "")
        except JobCancelled as e:
            state, reason = "cancelled", str(e)
        except Exception as e:
            reason = f"{type(e).__name__}: {e}"
            bus.log.error("job %s failed: %s", assign.job, reason.splitlines()[0][:500] if reason else "")
            bus.log.debug("job %s failed:\n%s", assign.job, traceback.format_exc())
            state = "failed"
        result_msg = None
        if result is not None:
            try:
                result_msg = msg.JobResult(job=assign.job, attempt=assign.attempt, result=result)
                msg.encode(result_msg)
            except (TypeError, ValueError) as e:
                result_msg, state, reason = None, "failed", f"result is not serialisable: {e}"
        status = msgspec.structs.replace(
            self._status(assign, state, reason), has_result=result_msg is not None
        )
        with self._lock:
            self._current = None
            shutting_down = self._shutting_down
            if not shutting_down:
                self._finished.append((status, result_msg))
        if shutting_down:
            # Say nothing: the queue sees this worker leave and applies the job's worker-loss policy
            # (a training job is re-queued and resumes elsewhere).
            return
        if result_msg is not None:
            self.publish(keys.job_key(assign.job, "result"), result_msg)
        self.publish(keys.job_key(assign.job, "report"), status)
        self.presence.update(state="idle", job=None, activity="idle")

    @property
    def current_job(self) -> str | None:
        with self._lock:
            return None if self._current is None else self._current.assign.job

    def shutdown(self, timeout: float = 5.0) -> None:
        """Stop accepting jobs, ask the running one to stop, and wait up to ``timeout`` for it."""
        with self._lock:
            self._shutting_down = True
            cur = self._current
        self.presence.update(state="stopping", activity="shutting down")
        if cur is not None:
            cur.ctx._request_cancel("worker shutting down")
            cur.thread.join(timeout)
        for q in self._queryables:
            try:
                q.undeclare()
            except zenoh.ZError:
                pass
