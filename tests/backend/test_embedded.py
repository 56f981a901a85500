"""The embedded default: one sim worker and one trainer as child processes of the hub, on loopback."""

from __future__ import annotations

import os
import signal
import time

import pytest

from studio.backend import bus
from studio.backend.embedded import start_embedded_workers
from studio.backend.presence import Directory

from .test_hub import start_hub

pytestmark = pytest.mark.timeout(180)


def test_embedded_workers_start_share_the_data_dir_and_stop(hub):
    with start_embedded_workers(hub) as embedded:
        assert embedded.wait_ready(hub.directory, timeout=120), [
            p.log_path.read_text() for p in embedded.processes
        ]
        assert sorted(w.kind for w in hub.directory.workers()) == ["sim", "train"]
        cmd_lines = [p.process.args for p in embedded.processes]
        for args in cmd_lines:
            assert args[args.index("--connect") + 1] == hub.endpoint
            assert args[args.index("--data-dir") + 1] == str(hub.data_dir)
            assert "--exit-with-parent" in args
        train = hub.directory.workers("train")[0].status
        # Training is offered, or its absence explained.
        assert "train" in train.job_kinds or "train" in train.unavailable
        procs = [p.process for p in embedded.processes]
    assert all(p.returncode == 0 for p in procs)
    assert hub.directory.wait_for(lambda ws: not ws, 10)


def test_embedded_workers_exit_when_the_hub_is_killed(tmp_path):
    endpoint = bus.loopback_endpoint(bus.free_loopback_port())
    hub = start_hub(endpoint, tmp_path / "data", "--workers", "default")
    session = bus.open_session(bus.BusConfig.worker([endpoint]))
    pids: list[int] = []
    try:
        directory = Directory(session)
        assert directory.wait_for(lambda ws: len([w for w in ws if w.status]) == 2, 120)
        pids = [w.status.pid for w in directory.workers()]
        directory.close()
        hub.send_signal(signal.SIGKILL)
        hub.wait(10)
        deadline = time.monotonic() + 15
        alive = pids
        while alive and time.monotonic() < deadline:
            time.sleep(0.2)
            alive = [p for p in alive if _alive(p)]
        assert not alive, f"embedded workers {alive} outlived their hub"
    finally:
        session.close()
        if hub.poll() is None:
            hub.kill()
        for pid in pids:  # never leave them behind, even if the assertion failed
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ")[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_a_worker_that_dies_is_started_again_until_it_keeps_dying(hub, monkeypatch):
    import studio.backend.embedded as embedded_module

    monkeypatch.setattr(embedded_module, "MAX_RESTARTS", 1)
    with start_embedded_workers(hub, sim=1, train=0) as embedded:
        assert embedded.wait_ready(hub.directory, timeout=120)
        (first,) = embedded.workers
        embedded.processes[0].process.send_signal(signal.SIGKILL)
        assert hub.directory.wait_for(
            lambda ws: [w.worker for w in ws if w.status is not None] not in ([], [first]), 120
        ), "no new sim worker"
        (second,) = embedded.workers
        assert second != first and [(k, d, n) for _, k, d, n in embedded.restarts] == [("sim", first, second)]
        assert [w.kind for w in hub.directory.workers()] == ["sim"]
        # A second death within the window is a crash loop: the worker is left dead, its log kept.
        embedded.processes[0].process.send_signal(signal.SIGKILL)
        assert hub.directory.wait_for(lambda ws: not ws, 30)
        time.sleep(2.0)
        assert embedded.workers == [second] and len(embedded.restarts) == 1
