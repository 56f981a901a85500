"""Job lifecycles through a real hub and real worker processes: submit, progress, queue, cancel, faults, restarts."""

from __future__ import annotations

import json
import signal
import threading
import time

import pytest
import zenoh

from studio.backend import bus, keys
from studio.backend import messages as msg
from studio.backend.hub import Hub
from studio.backend.job_client import JobClient
from studio.backend.job_runner import JobRunner
from studio.backend.presence import WorkerPresence

from .conftest import wait_worker
from .job_handlers import count_steps

pytestmark = pytest.mark.timeout(120)


def eventually(predicate, timeout: float = 5.0) -> bool:
    """Poll ``predicate`` (streams on different keys reach different subscribers independently)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.02)
    return True


def count_spec(tmp_path, name: str, steps: int, step_s: float = 0.01, **more) -> dict:
    return {"steps": steps, "step_s": step_s, "run_dir": str(tmp_path / name), **more}


def test_job_runs_with_progress_artifacts_and_result(hub, workers, tmp_path):
    workers.start("train", "t1")
    wait_worker(hub.directory, "t1")
    client = JobClient(hub.session)
    status = client.submit("count", count_spec(tmp_path, "run", steps=12, every=4), worker_kind="train")
    assert status.state == "queued" and status.attempt == 1
    with client.watch(status.job) as watch:
        final = watch.wait(timeout=20)
        assert final.state == "succeeded", final
        assert final.worker == "t1"
        watch.wait(lambda w: w.result is not None, timeout=5)
        assert watch.result.result == {"counted": 12, "resumed_from": 0, "attempt": 1, "worker": "t1"}
        watch.wait(lambda w: w.progress is not None and w.progress.step == 12, timeout=5)
        assert watch.progress.total == 12 and watch.progress.metrics["loss"] == pytest.approx(1 / 12)
        # Streams on different keys arrive independently: wait for the last checkpoint announcement too.
        watch.wait(lambda w: len(w.artifacts) == 3, timeout=5)
        assert [a.step for a in watch.artifacts] == [4, 8, 12]
        assert {s.state for s in watch.history} >= {"running", "succeeded"}
    # The queue lists it and serves its result to anyone who asks later.
    listed = {s.job: s for s in client.list()}
    assert listed[status.job].state == "succeeded"
    # (A query is answered within the client's timeout on a quiet machine; one full-suite run beside a training
    # run saw no answer in 5 s, so ask again for up to 20 s before failing.)
    found: list = []
    assert eventually(lambda: found.append(client.result(status.job)) or found[-1] is not None, timeout=20)
    assert found[-1].result["counted"] == 12
    # The worker is idle again.
    assert hub.directory.wait_for(lambda ws: ws[0].status.state == "idle", 5)


def test_second_job_waits_in_the_queue_while_the_worker_is_busy(hub, workers, tmp_path):
    workers.start("train", "t1")
    wait_worker(hub.directory, "t1")
    client = JobClient(hub.session)
    first = client.submit("count", count_spec(tmp_path, "a", steps=60, step_s=0.02), worker_kind="train")
    with client.watch(first.job) as w1:
        w1.wait(lambda w: w.status.state == "running", timeout=10)
        second = client.submit("count", count_spec(tmp_path, "b", steps=5), worker_kind="train")
        with client.watch(second.job) as w2:
            time.sleep(0.5)
            assert w2.status.state == "queued"
            assert w2.status.queue_position == 0 and "waiting for a free train worker" in w2.status.reason
            done1 = w1.wait(timeout=20)
            done2 = w2.wait(timeout=20)
    assert done1.state == done2.state == "succeeded"
    running2 = next(s for s in w2.history if s.state == "running")
    assert running2.updated_at >= done1.updated_at


def test_cancel_running_and_queued_jobs(hub, workers, tmp_path):
    workers.start("train", "t1")
    wait_worker(hub.directory, "t1")
    client = JobClient(hub.session)
    running = client.submit("count", count_spec(tmp_path, "a", steps=1000, step_s=0.02), worker_kind="train")
    queued = client.submit("count", count_spec(tmp_path, "b", steps=5), worker_kind="train")
    with client.watch(running.job) as w1, client.watch(queued.job) as w2:
        w1.wait(lambda w: w.progress is not None and w.progress.step >= 3, timeout=10)
        cancelled = client.cancel(queued.job, reason="not needed")
        assert cancelled.state == "cancelled" and cancelled.reason == "not needed"
        client.cancel(running.job, reason="user pressed stop")
        final = w1.wait(timeout=10)
        assert final.state == "cancelled" and "user pressed stop" in final.reason
        assert w1.progress.step < 1000
        assert w2.wait(timeout=1).state == "cancelled"
    # Cancelling a finished job is harmless and says how it ended; an unknown job is an error.
    assert client.cancel(running.job).state == "cancelled"
    with pytest.raises(bus.RemoteError, match="not_found"):
        client.cancel("no-such-job")


def test_failing_handler_is_reported_and_worker_keeps_serving(hub, workers, tmp_path):
    workers.start("train", "t1")
    wait_worker(hub.directory, "t1")
    client = JobClient(hub.session)
    bad = client.submit("count", count_spec(tmp_path, "bad", steps=10, fail_at=3), worker_kind="train")
    with client.watch(bad.job) as w:
        final = w.wait(timeout=15)
    assert final.state == "failed" and "asked to fail at step 3" in final.reason
    good = client.submit("count", count_spec(tmp_path, "good", steps=3), worker_kind="train")
    with client.watch(good.job) as w:
        assert w.wait(timeout=15).state == "succeeded"


def test_job_kind_nobody_offers_stays_queued_with_the_reason(hub, workers, tmp_path):
    workers.start("train", "t1")
    wait_worker(hub.directory, "t1")
    client = JobClient(hub.session)
    status = client.submit("paint", {"colour": "red"}, worker_kind="train")
    with client.watch(status.job) as w:
        w.wait(lambda w: "no connected train worker can run 'paint'" in w.status.reason, timeout=5)
        assert w.status.state == "queued"
    with pytest.raises(ValueError, match="worker_kind"):
        client.submit("paint", {})


def test_worker_killed_mid_job_is_reported_failed_within_5_s(hub, workers, tmp_path):
    proc = workers.start("sim", "s1")
    wait_worker(hub.directory, "s1")
    client = JobClient(hub.session)
    # A rollout-like job: not re-queued when its worker dies.
    status = client.submit(
        "count",
        count_spec(tmp_path, "r", steps=1000, step_s=0.02),
        worker_kind="sim",
        requeue_on_worker_loss=False,
    )
    with client.watch(status.job) as w:
        w.wait(lambda w: w.progress is not None and w.progress.step >= 5, timeout=15)
        t_kill = time.monotonic()
        proc.send_signal(signal.SIGKILL)
        final = w.wait(timeout=5)
        elapsed = time.monotonic() - t_kill
    assert final.state == "failed", final
    assert "worker s1 lost" in final.reason and "liveliness" in final.reason
    assert elapsed < 5.0
    assert eventually(lambda: hub.jobs.get(status.job).state == "failed")


def test_killed_trainer_job_is_requeued_and_resumes_from_its_checkpoint(hub, workers, tmp_path):
    first = workers.start("train", "t1")
    wait_worker(hub.directory, "t1")
    client = JobClient(hub.session)
    spec = count_spec(tmp_path, "run", steps=60, step_s=0.03, every=5)
    status = client.submit("count", spec, worker_kind="train", requeue_on_worker_loss=True, max_attempts=3)
    with client.watch(status.job) as w:
        w.wait(lambda w: any(a.step >= 10 for a in w.artifacts), timeout=20)
        first.send_signal(signal.SIGKILL)
        requeued = w.wait(lambda w: w.status.attempt == 2, timeout=5)
        assert requeued.state == "queued" and "worker t1 lost during attempt 1; re-queued" in requeued.reason
        workers.start("train", "t2")  # the next available trainer
        final = w.wait(timeout=30)
        w.wait(lambda w: w.result is not None, timeout=5)
    assert final.state == "succeeded" and final.worker == "t2" and final.attempt == 2
    assert w.result.result["resumed_from"] >= 10
    assert w.result.result["attempt"] == 2
    attempts = (tmp_path / "run" / "attempts.log").read_text().split("\n")
    assert attempts[0].split() == ["1", "t1", "0"] and attempts[1].split()[:2] == ["2", "t2"]
    assert json.loads((tmp_path / "run" / "checkpoint.json").read_text()) == {"step": 60}


def test_restarted_hub_reattaches_to_a_running_job(tmp_path, port, workers):
    endpoint = bus.loopback_endpoint(port)
    journal = tmp_path / "queue.json"
    hub1 = Hub(bus.BusConfig.hub([endpoint]), data_dir=tmp_path / "data", journal=journal)
    try:
        workers.start("train", "t1")
        wait_worker(hub1.directory, "t1")
        status = JobClient(hub1.session).submit(
            "count", count_spec(tmp_path, "run", steps=80, step_s=0.03), worker_kind="train"
        )
        with JobClient(hub1.session).watch(status.job) as w:
            w.wait(lambda w: w.status.state == "running", timeout=10)
    finally:
        hub1.close()  # the UI host goes away; the worker keeps the job running
    time.sleep(0.5)
    hub2 = Hub(bus.BusConfig.hub([endpoint]), data_dir=tmp_path / "data", journal=journal)
    try:
        client = JobClient(hub2.session)
        listed = {s.job: s for s in client.list()}
        assert listed[status.job].state == "running" and listed[status.job].worker == "t1"
        with client.watch(status.job) as w:
            w.wait(lambda w: w.progress is not None, timeout=10)  # progress flows again
            final = w.wait(timeout=20)
        assert final.state == "succeeded" and final.attempt == 1, final.reason
        assert eventually(lambda: hub2.jobs.get(status.job).state == "succeeded")
    finally:
        hub2.close()


def test_restarted_hub_fails_a_job_whose_worker_died_meanwhile(tmp_path, port, workers):
    endpoint = bus.loopback_endpoint(port)
    journal = tmp_path / "queue.json"
    hub1 = Hub(bus.BusConfig.hub([endpoint]), data_dir=tmp_path / "data", journal=journal)
    try:
        proc = workers.start("sim", "s1")
        wait_worker(hub1.directory, "s1")
        status = JobClient(hub1.session).submit(
            "count", count_spec(tmp_path, "run", steps=1000, step_s=0.02), worker_kind="sim"
        )
        with JobClient(hub1.session).watch(status.job) as w:
            w.wait(lambda w: w.status.state == "running", timeout=10)
    finally:
        hub1.close()
    proc.send_signal(signal.SIGKILL)
    proc.wait(10)
    hub2 = Hub(bus.BusConfig.hub([endpoint]), data_dir=tmp_path / "data", journal=journal)
    try:
        with JobClient(hub2.session).watch(status.job) as w:
            final = w.wait(timeout=hub2.jobs.reattach_grace_s + 3)
        assert final.state == "failed" and "worker s1 lost" in final.reason
    finally:
        hub2.close()


def test_malformed_job_requests_get_error_replies_and_nothing_crashes(hub, workers, tmp_path):
    workers.start("train", "t1")
    wait_worker(hub.directory, "t1")
    for key in (keys.job_key("x1", "submit"), keys.worker_key("train", "t1", "assign")):
        replies = list(hub.session.get(key, payload=b"\x01\x93garbage", timeout=3))
        assert len(replies) == 1
        answer = msg.decode(replies[0].ok.payload.to_bytes())
        assert isinstance(answer, msg.ErrorReply) and answer.code == "bad_request"
    # A well-formed message of the wrong type is refused too.
    with pytest.raises(bus.RemoteError, match="bad_request"):
        bus.request(hub.session, keys.job_key("x1", "submit"), msg.Ack(), msg.JobStatus)
    # A submission whose id differs from its key is refused.
    submit = msg.JobSubmit(job="x2", kind="count", worker_kind="train", spec={})
    with pytest.raises(bus.RemoteError, match="bad_request"):
        bus.request(hub.session, keys.job_key("x1", "submit"), submit, msg.JobStatus)
    # Garbage published on the status and report keys is dropped by the queue.
    hub.session.put(keys.job_key("x3", "status"), b"\x00\x01\x02")
    hub.session.put(keys.job_key("x3", "report"), b"\x00\x01\x02")
    status = JobClient(hub.session).submit("count", count_spec(tmp_path, "ok", steps=2), worker_kind="train")
    with JobClient(hub.session).watch(status.job) as w:
        assert w.wait(timeout=15).state == "succeeded"
    assert {s.job for s in JobClient(hub.session).list()} == {status.job}


class _RecordsPuts:
    """A worker's Zenoh session that notes how each publication is sent (then sends it)."""

    def __init__(self, session):
        self.session, self.sent = session, []

    def put(self, key, payload, **kwargs):
        self.sent.append((str(key).rsplit("/", 1)[-1], kwargs.get("congestion_control")))
        self.session.put(key, payload, **kwargs)

    def __getattr__(self, name):
        return getattr(self.session, name)


def test_a_jobs_report_artifacts_and_result_must_arrive_its_progress_may_drop(hub, tmp_path):
    """A lost final report leaves a finished job running in the queue and its watchers waiting: the runner sends
    reports, artifacts and results so that a full queue blocks them; progress, superseded by the next, drops."""
    worker = bus.open_session(bus.BusConfig.worker([hub.endpoint]))
    session = _RecordsPuts(worker)
    presence = WorkerPresence(worker, "train", "t-inproc", job_kinds=("count",), announce=False)
    runner = JobRunner(session, presence, {"count": count_steps})
    presence.announce()
    try:
        wait_worker(hub.directory, "t-inproc")
        client = JobClient(hub.session)
        status = client.submit("count", count_spec(tmp_path, "run", steps=4, every=2), worker_kind="train")
        with client.watch(status.job) as watch:
            assert watch.wait(timeout=20).state == "succeeded"
        how: dict[str, set[str]] = {}
        for leaf, congestion in session.sent:
            how.setdefault(leaf, set()).add(str(congestion))
        assert how["report"] == how["artifacts"] == how["result"] == {str(bus.MUST_ARRIVE)}
        assert how["progress"] == {str(zenoh.CongestionControl.DROP)}
    finally:
        runner.shutdown()
        presence.close()
        worker.close()


def test_a_submission_the_queue_answers_late_is_asked_again_as_the_same_job(port):
    """A hub too busy to answer a JobSubmit in time may still queue it: the client asks again under the same job id
    (a repeated submission is that job, next test) rather than fail the person's click, and gives up only after
    its patience, saying how often it asked."""
    hub_side = bus.open_session(bus.BusConfig.hub([bus.loopback_endpoint(port)]))
    client_side = bus.open_session(bus.BusConfig.worker([bus.loopback_endpoint(port)]))
    asked: list[str] = []
    held: list[zenoh.Query] = []  # kept, so that they time out rather than end unanswered
    late = threading.Event()

    def on_submit(submit: msg.JobSubmit, query: zenoh.Query):
        asked.append(submit.job)
        if len(asked) == 1 or late.is_set():
            held.append(query)
            return bus.DEFERRED  # not answered (the query times out)
        now = time.time()
        return msg.JobStatus(
            job=submit.job, kind=submit.kind, worker_kind=submit.worker_kind, state="queued", attempt=1,
            worker=None, reason="waiting for a worker", submitted_at=now, updated_at=now, spec=submit.spec,
        )  # fmt: skip

    queryable = bus.declare_queryable(hub_side, keys.all_jobs("submit"), on_submit, msg.JobSubmit)
    try:
        time.sleep(0.5)  # the queryable's declaration reaches the client's session
        client = JobClient(client_side, timeout=0.4, patience=3.0)
        status = client.submit("count", {"steps": 1}, worker_kind="train", job="count-late-1")
        assert status.job == "count-late-1" and status.state == "queued"
        assert asked == ["count-late-1", "count-late-1"]
        late.set()
        started = time.monotonic()
        with pytest.raises(bus.RequestTimeout, match=r"asked \d+ times"):
            client.submit("count", {"steps": 1}, worker_kind="train", job="count-late-2")
        assert 2.0 <= time.monotonic() - started < 4.0 and asked.count("count-late-2") >= 5
    finally:
        queryable.undeclare()
        client_side.close()
        hub_side.close()


def test_a_repeated_submission_is_the_job_already_queued(hub, tmp_path):
    """What makes asking again safe: the queue answers a JobSubmit of a job id it holds, with the same spec, with
    that job (one job, its first submission time), and refuses the id with another spec."""
    client = JobClient(hub.session)
    spec = count_spec(tmp_path, "a", steps=1)
    first = client.submit("count", spec, worker_kind="train", job="count-twice-1")
    again = client.submit("count", spec, worker_kind="train", job="count-twice-1")
    assert (again.job, again.submitted_at) == (first.job, first.submitted_at)
    assert [s.job for s in client.list()].count("count-twice-1") == 1
    with pytest.raises(bus.RemoteError, match="conflict"):
        client.submit("count", {**spec, "steps": 2}, worker_kind="train", job="count-twice-1")
