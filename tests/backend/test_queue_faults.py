"""The job queue under forged reports, a journal that cannot be written, and thousands of jobs: it keeps serving,
loses no outcome, prunes what is finished, and costs O(log n) per operation."""

from __future__ import annotations

import errno
import os
import time
from pathlib import Path

import pytest

from studio.backend import bus, job_journal, keys
from studio.backend import messages as msg
from studio.backend.hub import Hub
from studio.backend.job_client import JobClient
from studio.backend.job_queue import JobQueue
from studio.backend.presence import Directory

from .conftest import wait_worker

pytestmark = pytest.mark.timeout(120)


def _forged(
    job: str, state: msg.JobState, worker: str, attempt: int = 1, kind: str = "count"
) -> msg.JobStatus:
    now = time.time()
    return msg.JobStatus(
        job=job,
        kind=kind,
        worker_kind="train",
        state=state,
        attempt=attempt,
        worker=worker,
        reason="forged",
        submitted_at=now,
        updated_at=now,
    )


def test_a_forged_report_neither_blocks_the_queue_nor_ends_a_running_job(hub, workers, tmp_path):
    workers.start("train", "t1")
    wait_worker(hub.directory, "t1")
    attacker = bus.open_session(bus.BusConfig.worker([hub.endpoint]))
    client = JobClient(hub.session)
    try:
        # A ghost job "running" on the real worker: the queue never queued it, so it changes nothing.
        attacker.put(keys.job_key("ghost-1", "report"), msg.encode(_forged("ghost-1", "running", "t1")))
        time.sleep(0.5)
        assert hub.jobs.get("ghost-1") is None
        job = client.submit("count", {"steps": 3, "run_dir": str(tmp_path / "a")}, worker_kind="train")
        with client.watch(job.job) as watch:
            assert watch.wait(timeout=20).state == "succeeded"

        # A running job: "succeeded" from another worker, or for another attempt, is not its end.
        long = client.submit(
            "count", {"steps": 60, "step_s": 0.05, "run_dir": str(tmp_path / "b")}, worker_kind="train"
        )
        with client.watch(long.job) as watch:
            watch.wait(lambda w: w.status is not None and w.status.state == "running", 20)
            submitted = watch.status.submitted_at
            for forged in (
                msgspec_replace(_forged(long.job, "succeeded", "t2"), submitted_at=submitted),
                msgspec_replace(_forged(long.job, "succeeded", "t1", attempt=2), submitted_at=submitted),
                msgspec_replace(_forged(long.job, "failed", "t1", attempt=3), submitted_at=submitted),
            ):
                attacker.put(keys.job_key(long.job, "report"), msg.encode(forged))
            time.sleep(0.5)
            assert hub.jobs.get(long.job).state == "running"
            final = watch.wait(timeout=30)
            watch.wait(lambda w: w.result is not None, 5)
        assert final.state == "succeeded" and final.worker == "t1" and final.attempt == 1
        assert watch.result.result["counted"] == 60
        assert all(s.reason != "forged" for s in watch.history)
    finally:
        attacker.close()


def test_a_job_ends_only_once_the_result_its_worker_sent_before_the_end_is_in(hub, workers, tmp_path):
    """A worker publishes a job's result, then its end; the hub hears the two on different subscribers' threads,
    so the end can be handled first. A watcher that sees the end reads the result next: the queue holds the end
    until the result is in (seen before: `succeeded`, then no result, in one no-shared-disk run in five)."""
    workers.start("train", "t1")
    wait_worker(hub.directory, "t1")
    peer = bus.open_session(bus.BusConfig.worker([hub.endpoint]))
    client = JobClient(hub.session)
    try:
        job = client.submit(
            "count", {"steps": 600, "step_s": 0.05, "run_dir": str(tmp_path / "a")}, worker_kind="train"
        )
        with client.watch(job.job) as watch:
            watch.wait(lambda w: w.status is not None and w.status.state == "running", 20)
            end = msgspec_replace(
                _forged(job.job, "succeeded", "t1"), submitted_at=watch.status.submitted_at, has_result=True
            )
            peer.put(keys.job_key(job.job, "report"), msg.encode(end))  # the end, before its result
            time.sleep(0.5)
            assert hub.jobs.get(job.job).state == "running", "the end is held until its result is in"
            result = msg.JobResult(job=job.job, attempt=1, result={"counted": 7})
            peer.put(keys.job_key(job.job, "result"), msg.encode(result))
            final = watch.wait(timeout=10)
        assert final is not None and final.state == "succeeded"
        found = client.result(job.job)
        assert found is not None and found.result == {"counted": 7}
    finally:
        peer.close()


def test_a_held_end_survives_the_workers_running_answer_arriving_after_it(
    hub, workers, tmp_path, monkeypatch
):
    """A job that ends within a millisecond: its worker's answer to the assignment (``running``) can reach the
    queue after the end, while the end waits for its result. The end must still be applied (seen: a collect job
    with nothing to make stayed ``running`` for good, in a parallel test run)."""
    workers.start("train", "t1")
    wait_worker(hub.directory, "t1")
    peer = bus.open_session(bus.BusConfig.worker([hub.endpoint]))
    client = JobClient(hub.session)
    request = bus.request

    def answer_after_the_end(session, key, message, *args, **kwargs):
        reply = request(session, key, message, *args, **kwargs)
        if key.endswith("/assign") and isinstance(message, msg.JobAssign):
            end = msgspec_replace(
                _forged(message.job, "succeeded", "t1"), submitted_at=message.submitted_at, has_result=True
            )
            peer.put(keys.job_key(message.job, "report"), msg.encode(end))  # the end, before its result
            time.sleep(0.3)  # the end is now held for its result; the assignment's answer arrives after it
        return reply

    monkeypatch.setattr(bus, "request", answer_after_the_end)
    try:
        job = client.submit(
            "count", {"steps": 600, "step_s": 0.05, "run_dir": str(tmp_path / "a")}, worker_kind="train"
        )
        with client.watch(job.job) as watch:
            watch.wait(lambda w: w.status is not None and w.status.state == "running", 20)
            time.sleep(0.3)
            peer.put(
                keys.job_key(job.job, "result"), msg.encode(msg.JobResult(job=job.job, attempt=1, result={}))
            )
            final = watch.wait(timeout=10)
        assert final is not None and final.state == "succeeded"
    finally:
        peer.close()


def msgspec_replace(status: msg.JobStatus, **changes) -> msg.JobStatus:
    import msgspec

    return msgspec.structs.replace(status, **changes)


def _failing_open(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_a_journal_that_cannot_be_written_loses_no_outcome(tmp_path, port, workers, monkeypatch):
    """Disk full: the failed job's status is published anyway, and a hub restarted before the journal could be
    written learns the outcome from the worker instead of running the job again."""
    endpoint = bus.loopback_endpoint(port)
    journal = tmp_path / "queue.json"
    hub = Hub(bus.BusConfig.hub([endpoint]), data_dir=tmp_path / "data", journal=journal)
    client = JobClient(hub.session)
    spec = {"steps": 5, "fail_at": 0, "run_dir": str(tmp_path / "run")}
    job = client.submit("count", spec, worker_kind="train")  # journaled as queued; no worker yet
    monkeypatch.setattr(job_journal, "open", _failing_open, raising=False)
    with client.watch(job.job) as watch:
        workers.start("train", "t1")
        final = watch.wait(timeout=60)
    assert final.state == "failed" and "asked to fail" in final.reason
    hub.close()  # the journal still says "queued"

    monkeypatch.undo()
    hub = Hub(bus.BusConfig.hub([endpoint]), data_dir=tmp_path / "data", journal=journal)
    try:
        client = JobClient(hub.session)
        with client.watch(job.job) as watch:
            final = watch.wait(lambda w: w.status is not None and w.status.terminal, timeout=30)
        assert final.state == "failed" and "asked to fail" in final.reason
        time.sleep(1.5)
        attempts = (tmp_path / "run" / "attempts.log").read_text().splitlines()
        assert len(attempts) == 1, attempts  # not run again
        # Writing works again: the journal catches up with memory.
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and b'"failed"' not in journal.read_bytes():
            time.sleep(0.1)
        assert b'"failed"' in journal.read_bytes()
    finally:
        hub.close()
    log = workers.log("t1")
    assert "asked to fail at step 0" in log and "Traceback" not in log, log  # a failed job is one line


@pytest.fixture
def bare_queue(tmp_path, port):
    """A router session and a queue with a small journal budget, no workers."""
    session = bus.open_session(bus.BusConfig.hub([bus.loopback_endpoint(port)]))
    directory = Directory(session)
    made: list[JobQueue] = []

    def make(**kwargs) -> JobQueue:
        q = JobQueue(session, directory, journal=tmp_path / "jobs" / "queue.json", **kwargs)
        made.append(q)
        return q

    yield session, make
    for q in made:
        q.close()
    directory.close()
    session.close()


def test_finished_jobs_are_pruned_and_the_journal_is_appended_not_rewritten(bare_queue, tmp_path):
    session, make = bare_queue
    queue = make(keep_finished=5)
    client = JobClient(session)
    ids = [client.submit("nobody", {"i": i}, worker_kind="none").job for i in range(3)]
    path = tmp_path / "jobs" / "queue.json"
    inode, size = path.stat().st_ino, path.stat().st_size
    ids += [client.submit("nobody", {"i": i}, worker_kind="none").job for i in range(3, 20)]
    assert path.stat().st_ino == inode and path.stat().st_size > size  # appended to, not replaced
    for job in ids[:15]:
        client.cancel(job)
    assert len(queue.jobs()) == 10  # 5 unfinished + the newest 5 finished
    assert {s.job for s in queue.jobs()} == set(ids[10:])
    listed = [s.job for s in client.list()]
    assert listed == ids[10:]
    assert client.status(ids[17]).queue_position == 2  # 15..19 queued: two ahead of the 18th
    queue.close()
    reloaded = make(keep_finished=5, reattach_grace_s=0.1)
    assert {s.job for s in reloaded.jobs()} == set(ids[10:])


def test_spec_size_and_unknown_kinds_bounds(bare_queue):
    session, make = bare_queue
    make()
    client = JobClient(session)
    with pytest.raises(bus.RemoteError, match=r"bad_request: .*exceeds the 65536 bytes"):
        client.submit("nobody", {"blob": "x" * (70 << 10)}, worker_kind="none")
    with pytest.raises(bus.RemoteError, match="bad_request: request larger than"):
        client.submit("nobody", {"blob": "x" * (300 << 10)}, worker_kind="none")
    with pytest.raises(bus.RemoteError, match="bad_request: train jobs run on train workers"):
        client.submit("train", {"data_dir": "d", "run_dir": "r"}, worker_kind="sim")


def _submit_seconds(client: JobClient, n: int) -> float:
    t0 = time.perf_counter()
    for i in range(n):
        client.submit("nobody", {"i": i}, worker_kind="none")
    return (time.perf_counter() - t0) / n


def test_submitting_stays_flat_with_thousands_queued_and_an_idle_queue_rests(bare_queue):
    session, make = bare_queue
    queue = make()
    client = JobClient(session)
    small = _submit_seconds(client, 100)
    _submit_seconds(client, 2900)  # 3,000 queued
    large = _submit_seconds(client, 100)
    assert large < 3 * small + 0.002, (small, large)
    assert client.status(queue.jobs()[-1].job).queue_position == 3099
    time.sleep(1.5)  # the positions pushed after the burst
    cpu0, wall0 = os.times(), time.monotonic()
    time.sleep(3.0)
    cpu1 = os.times()
    busy = (cpu1.user + cpu1.system - cpu0.user - cpu0.system) / (time.monotonic() - wall0)
    assert busy < 0.05, f"an idle queue of 3,200 jobs used {busy:.0%} of a core"


def test_a_journal_in_the_former_format_is_read(bare_queue, tmp_path):
    _session, make = bare_queue
    now = time.time()
    status = msg.JobStatus(
        job="old-1",
        kind="nobody",
        worker_kind="none",
        state="succeeded",
        attempt=1,
        worker="w",
        reason="",
        submitted_at=now,
        updated_at=now,
    )
    import msgspec

    path = Path(tmp_path / "jobs" / "queue.json")
    path.parent.mkdir(parents=True)
    path.write_bytes(msgspec.json.encode({"version": 1, "jobs": [{"status": status, "result": None}]}))
    queue = make()
    assert queue.get("old-1") is not None and queue.get("old-1").state == "succeeded"
    assert path.read_bytes().startswith(b'{"journal":"studio-jobs","version":2}')
