"""The studio's Zenoh key expressions: one function per key, so that no other module spells a key by hand.

Layout (``<…>`` is one chunk, an :data:`studio.backend.messages.Id`)::

    studio/workers/<kind>/<worker>                 liveliness token: the worker is alive
    studio/workers/<kind>/<worker>/status          pub + queryable: WorkerStatus
    studio/workers/<kind>/<worker>/assign          queryable: JobAssign -> JobStatus | ErrorReply
    studio/workers/<kind>/<worker>/cancel          queryable: JobCancel -> JobStatus | ErrorReply
    studio/workers/<kind>/<worker>/jobs            queryable: one JobStatus per job the worker holds
    studio/sim/<worker>/<session>/ctl              queryable: teleop requests (OpenSession, ...)
    studio/sim/<worker>/<session>/cmd              sub: EeTarget (latest wins)
    studio/sim/<worker>/<session>/poses            pub: PoseFrame at the control rate
    studio/sim/<worker>/<session>/frames           pub: ImageFrame (on request / stream)
    studio/sim/<worker>/<session>/status           pub: SessionState, EpisodeSaved, EpisodeNotSaved
    studio/sim/<worker>/<session>/client           liveliness token of the session's client
    studio/jobs/<job>/submit | cancel              queryables of the job queue
    studio/jobs/<job>/status                       pub + queryable (list with ``studio/jobs/*/status``)
    studio/jobs/<job>/progress | artifacts | poses pub (progress also queryable: latest)
    studio/jobs/<job>/result                       pub + queryable: JobResult
    studio/store/upload/<transfer>                 queryable of the store host: EpisodeChunk, EpisodeCommit

Liveliness tokens live in their own space, so a token and a data key may share a prefix.
"""

from __future__ import annotations

import re

ROOT = "studio"

_CHUNK = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$")

SESSION_LEAVES = ("ctl", "cmd", "poses", "frames", "status", "client", "draft")
JOB_LEAVES = ("submit", "cancel", "status", "report", "progress", "artifacts", "poses", "result")
WORKER_LEAVES = ("status", "assign", "cancel", "jobs")


class KeyExprError(ValueError):
    """A name cannot be used as a key-expression chunk, or a key does not have the expected shape."""


def check_chunk(value: str, what: str = "identifier") -> str:
    """``value`` if it is a valid single chunk (letters, digits, ``_ . -``; at most 64), else raise."""
    if not isinstance(value, str) or not _CHUNK.match(value):
        raise KeyExprError(
            f"{what} {value!r} is not usable in a key: use 1-64 letters, digits, '_', '.' or '-', "
            "starting with a letter or digit"
        )
    return value


def _leaf(leaf: str, allowed: tuple[str, ...]) -> str:
    if leaf not in allowed:
        raise KeyExprError(f"unknown key leaf {leaf!r}; expected one of {allowed}")
    return leaf


# ---------------------------------------------------------------------------------------------- workers
def worker_token(kind: str, worker: str) -> str:
    return f"{ROOT}/workers/{check_chunk(kind, 'worker kind')}/{check_chunk(worker, 'worker id')}"


def worker_key(kind: str, worker: str, leaf: str) -> str:
    return f"{worker_token(kind, worker)}/{_leaf(leaf, WORKER_LEAVES)}"


#: Liveliness selector for every worker token.
ALL_WORKER_TOKENS = f"{ROOT}/workers/*/*"
#: Selector for every worker's status.
ALL_WORKER_STATUS = f"{ROOT}/workers/*/*/status"


def parse_worker_key(key: str) -> tuple[str, str, str | None]:
    """(kind, worker, leaf or None) of a key under ``studio/workers``."""
    parts = str(key).split("/")
    if len(parts) in (4, 5) and parts[0] == ROOT and parts[1] == "workers":
        kind, worker = check_chunk(parts[2]), check_chunk(parts[3])
        return kind, worker, (parts[4] if len(parts) == 5 else None)
    raise KeyExprError(f"not a worker key: {key!r}")


# ---------------------------------------------------------------------------------------------- teleop sessions
def session_key(worker: str, session: str, leaf: str) -> str:
    return (
        f"{ROOT}/sim/{check_chunk(worker, 'worker id')}/{check_chunk(session, 'session id')}/"
        f"{_leaf(leaf, SESSION_LEAVES)}"
    )


def all_sessions(worker: str, leaf: str) -> str:
    """Selector of one leaf of every session on ``worker``."""
    return f"{ROOT}/sim/{check_chunk(worker, 'worker id')}/*/{_leaf(leaf, SESSION_LEAVES)}"


def parse_session_key(key: str) -> tuple[str, str, str]:
    """(worker, session, leaf) of a key under ``studio/sim``."""
    parts = str(key).split("/")
    if len(parts) == 5 and parts[0] == ROOT and parts[1] == "sim" and parts[4] in SESSION_LEAVES:
        return check_chunk(parts[2]), check_chunk(parts[3]), parts[4]
    raise KeyExprError(f"not a teleop session key: {key!r}")


# ---------------------------------------------------------------------------------------------- jobs
def job_key(job: str, leaf: str) -> str:
    return f"{ROOT}/jobs/{check_chunk(job, 'job id')}/{_leaf(leaf, JOB_LEAVES)}"


def all_jobs(leaf: str) -> str:
    """Selector of one leaf of every job, e.g. ``studio/jobs/*/status`` to list jobs."""
    return f"{ROOT}/jobs/*/{_leaf(leaf, JOB_LEAVES)}"


def parse_job_key(key: str) -> tuple[str, str]:
    """(job, leaf) of a key under ``studio/jobs``."""
    parts = str(key).split("/")
    if len(parts) == 4 and parts[0] == ROOT and parts[1] == "jobs" and parts[3] in JOB_LEAVES:
        return check_chunk(parts[2]), parts[3]
    raise KeyExprError(f"not a job key: {key!r}")


# ---------------------------------------------------------------------------------------------- store
def upload_key(transfer: str) -> str:
    return f"{ROOT}/store/upload/{check_chunk(transfer, 'transfer id')}"


ALL_UPLOADS = f"{ROOT}/store/upload/*"


def parse_upload_key(key: str) -> str:
    parts = str(key).split("/")
    if len(parts) == 4 and parts[:3] == [ROOT, "store", "upload"]:
        return check_chunk(parts[3])
    raise KeyExprError(f"not an upload key: {key!r}")
