"""Worker discovery and loss: liveliness tokens seen by the hub's directory, in-process and across processes."""

from __future__ import annotations

import signal
import time

import pytest

from studio.backend import bus
from studio.backend.presence import Directory, WorkerPresence, new_worker_id

from .conftest import wait_gone, wait_worker

pytestmark = pytest.mark.timeout(90)


def test_directory_sees_status_changes_and_departure(port):
    hub = bus.open_session(bus.BusConfig.hub([bus.loopback_endpoint(port)]))
    worker = bus.open_session(bus.BusConfig.worker([bus.loopback_endpoint(port)]))
    try:
        presence = WorkerPresence(worker, "train", "t-1", job_kinds=("train",), unavailable={"x": "why"})
        events = []
        directory = Directory(hub)
        directory.add_listener(lambda event, entry: events.append((event, entry.worker)))
        wait_worker(directory, "t-1", timeout=5)
        entry = directory.get("train", "t-1")
        # A lost status would show a worker busy that is idle: it blocks on a full queue instead of dropping.
        assert presence._publisher.congestion_control == bus.MUST_ARRIVE
        assert entry.status.job_kinds == ("train",) and entry.status.unavailable == {"x": "why"}
        presence.update(state="busy", activity="training job j", job="j")
        assert directory.wait_for(lambda ws: ws[0].status.state == "busy" and ws[0].status.job == "j", 5)
        presence.close()
        wait_gone(directory, "t-1", 5)
        assert events[-1] == ("left", "t-1")
        directory.close()
    finally:
        worker.close()
        hub.close()


def test_worker_announced_before_the_directory_exists_is_listed(port):
    hub = bus.open_session(bus.BusConfig.hub([bus.loopback_endpoint(port)]))
    worker = bus.open_session(bus.BusConfig.worker([bus.loopback_endpoint(port)]))
    try:
        WorkerPresence(worker, "sim", "s-early", announce=False).announce()
        time.sleep(0.2)
        directory = Directory(hub)
        wait_worker(directory, "s-early", timeout=5)
        assert directory.get("sim", "s-early").status.kind == "sim"
        directory.close()
    finally:
        worker.close()
        hub.close()


def test_worker_processes_appear_and_disappear(hub, workers):
    proc_a = workers.start("sim", "sim-a")
    proc_b = workers.start("train", "train-b")
    wait_worker(hub.directory, "sim-a")
    wait_worker(hub.directory, "train-b")
    a = hub.directory.get("sim", "sim-a").status
    assert a.kind == "sim" and a.pid == proc_a.pid and a.state == "idle" and "count" in a.job_kinds
    assert [w.worker for w in hub.directory.workers("train")] == ["train-b"]
    # Killed without warning: gone as soon as its connection drops (well within 5 s).
    proc_a.send_signal(signal.SIGKILL)
    assert wait_gone(hub.directory, "sim-a", timeout=5) < 5
    # Asked to stop: withdraws its token and exits cleanly.
    proc_b.send_signal(signal.SIGTERM)
    wait_gone(hub.directory, "train-b", timeout=10)
    assert proc_b.wait(10) == 0


def test_new_worker_ids_are_valid_and_unique():
    ids = {new_worker_id("sim") for _ in range(50)}
    assert len(ids) == 50 and all(i.startswith("sim-") for i in ids)
