"""Fixtures for the backend tests: a hub on a fresh loopback port and worker processes that never outlive a test."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from studio.backend import bus
from studio.backend.hub import Hub
from studio.backend.presence import Directory

HERE = Path(__file__).resolve().parent
COUNT_HANDLER = "count=job_handlers:count_steps"


class Workers:
    """Starts ``studio worker`` processes against a hub endpoint; :meth:`close` kills every one of them."""

    def __init__(self, endpoint: str, tmp_path: Path):
        self.endpoint = endpoint
        self.tmp_path = tmp_path
        self.procs: list[subprocess.Popen] = []

    def start(
        self,
        kind: str,
        worker_id: str,
        *args: str,
        handlers: tuple[str, ...] = (COUNT_HANDLER,),
        only_handlers: bool = True,
        connect: str | None = None,
    ) -> subprocess.Popen:
        cmd = [
            sys.executable,
            "-m",
            "studio.cli",
            "worker",
            kind,
            "--connect",
            connect or self.endpoint,
            "--id",
            worker_id,
            "--spool-dir",
            str(self.tmp_path / f"spool-{worker_id}"),
            "--log-level",
            "WARNING",
        ]
        for h in handlers:
            cmd += ["--handler", h]
        if only_handlers:
            cmd.append("--only-handlers")
        cmd += list(args)
        env = {
            **os.environ,
            "PYTHONPATH": os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]),
            "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
        }
        log = open(self.tmp_path / f"{worker_id}.log", "ab")
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)
        log.close()
        self.procs.append(proc)
        return proc

    def log(self, worker_id: str) -> str:
        path = self.tmp_path / f"{worker_id}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def close(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGKILL)
        for p in self.procs:
            p.wait(10)


def wait_worker(directory: Directory, worker_id: str, timeout: float = 60.0) -> None:
    """Wait until ``worker_id`` is in the directory with a status (fails the test otherwise)."""
    ok = directory.wait_for(
        lambda ws: any(w.worker == worker_id and w.status is not None for w in ws), timeout
    )
    assert ok, f"worker {worker_id} did not appear within {timeout} s"


def wait_gone(directory: Directory, worker_id: str, timeout: float) -> float:
    """Seconds until ``worker_id`` left the directory (fails the test after ``timeout``)."""
    t0 = time.monotonic()
    ok = directory.wait_for(lambda ws: all(w.worker != worker_id for w in ws), timeout)
    assert ok, f"worker {worker_id} still listed after {timeout} s"
    return time.monotonic() - t0


@pytest.fixture
def port() -> int:
    return bus.free_loopback_port()


@pytest.fixture
def hub(tmp_path: Path, port: int):
    h = Hub(bus.BusConfig.hub([bus.loopback_endpoint(port)]), data_dir=tmp_path / "data")
    yield h
    h.close()


@pytest.fixture
def workers(tmp_path: Path, port: int):
    w = Workers(bus.loopback_endpoint(port), tmp_path)
    yield w
    w.close()
