"""The job board: one followed object per job, whatever order a tab's refresh and the submission come in."""

from __future__ import annotations

import time
from types import SimpleNamespace

from studio.backend import messages as msg
from studio.ui.job_board import JobBoard


def _status(job: str, state: str = "queued", spec: dict | None = None) -> msg.JobStatus:
    now = time.time()
    return msg.JobStatus(
        job=job,
        kind="train",
        worker_kind="trainer",
        state=state,
        attempt=1,
        worker=None,
        reason="",
        submitted_at=now,
        updated_at=now,
        spec=spec or {},
    )


class _Client:
    """Answers a submission with a queued status and follows nothing over a bus."""

    def __init__(self):
        self.watched: list[str] = []

    def submit(self, kind, spec, *, job=None, **_):
        return _status(job, spec=spec)

    def watch(self, job, **_):
        self.watched.append(job)
        return SimpleNamespace(status=None, result=None, close=lambda: None)


SPEC = {"run_dir": "/data/runs/train-1", "steps": 4}


def test_a_job_followed_before_it_was_submitted_gets_its_spec_at_submission():
    """A tab refreshing between choosing the job id and submitting follows the job with no spec; the curves are
    read from the spec's run directory, so the submission must fill it in (it was left empty, and the Train tab
    drew only the progress messages' total loss)."""
    client = _Client()
    board = JobBoard(client)
    early = board.follow("train-1", "train")
    assert early.spec == {} and early.started_by is None
    tracked = board.submit("train", SPEC, started_by=7, job="train-1")
    assert tracked is early and client.watched == ["train-1"]  # one watch per job
    assert tracked.spec == SPEC and tracked.started_by == 7
    assert tracked.status is not None and tracked.status.state == "queued"


def test_a_status_carrying_the_spec_fills_a_job_followed_without_one():
    """A job another tab started is followed from the job list; its first status brings the spec."""
    board = JobBoard(_Client())
    tracked = board.follow("train-2", "train")
    tracked._on_status(_status("train-2", "running", spec=SPEC))
    assert tracked.spec == SPEC and tracked.state == "running"


def test_a_known_spec_is_not_replaced():
    board = JobBoard(_Client())
    tracked = board.follow("train-3", "train", {"run_dir": "/a"}, started_by=1)
    board.follow("train-3", "train", {"run_dir": "/b"}, started_by=2)
    tracked._on_status(_status("train-3", "running", spec={"run_dir": "/c"}))
    assert tracked.spec == {"run_dir": "/a"} and tracked.started_by == 1
