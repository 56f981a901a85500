"""The two-machine set-up on one machine: `studio hub` as its own process, workers and a client as separate
client processes; a job runs through the hub's queue and a teleop episode is shipped into the hub's store."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading

import numpy as np
import pytest

from studio.backend import bus
from studio.backend import messages as msg
from studio.backend.job_client import JobClient
from studio.backend.presence import Directory
from studio.backend.teleop_client import TeleopClient
from studio.data.store import EpisodeStore

from .conftest import Workers, wait_worker

pytestmark = pytest.mark.timeout(180)


def start_hub(endpoint: str, data_dir, *extra: str) -> subprocess.Popen:
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "studio.cli",
            "hub",
            "--listen",
            endpoint,
            "--data-dir",
            str(data_dir),
            "--log-level",
            "WARNING",
            *extra,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
        text=True,
    )
    lines: list[str] = []
    ready = threading.Event()

    def read() -> None:
        for line in proc.stdout:
            lines.append(line)
            if "studio hub ready" in line:
                ready.set()

    threading.Thread(target=read, daemon=True).start()
    proc.lines = lines  # type: ignore[attr-defined]  # what it printed, for failure messages
    if not ready.wait(60):
        proc.kill()
        raise AssertionError("studio hub did not start:\n" + "".join(lines))
    return proc


def test_hub_process_with_client_workers_runs_jobs_and_stores_shipped_episodes(tmp_path):
    endpoint = bus.loopback_endpoint(bus.free_loopback_port())
    data_dir = tmp_path / "data"
    hub = start_hub(endpoint, data_dir, "--workers", "none")
    workers = Workers(endpoint, tmp_path)
    session = None
    try:
        workers.start("sim", "box-sim", handlers=())  # no --data-dir: a "remote" worker, ships over the bus
        workers.start("train", "box-gpu")
        session = bus.open_session(bus.BusConfig.worker([endpoint]))  # the UI's side, as another client
        directory = Directory(session)
        wait_worker(directory, "box-sim")
        wait_worker(directory, "box-gpu")

        jobs = JobClient(session)
        job = jobs.submit(
            "count", {"steps": 5, "step_s": 0.01, "run_dir": str(tmp_path / "run")}, worker_kind="train"
        )
        with jobs.watch(job.job) as watch:
            assert watch.wait(timeout=30).state == "succeeded"
        assert [s.job for s in jobs.list()] == [job.job]

        with TeleopClient(session, "box-sim") as client:
            client.open("pick_place", "sawyer", "pick_place/cube->red", seed=2)
            client.start_recording()
            start = np.asarray(client.poses.wait_until(lambda f: True, 5.0).ee_pos)
            for _ in range(25):
                assert client.wait_ack(client.set_target(start + np.array([0.0, 0.0, 0.05]), 0.0)) is not None
            saved = client.stop_recording(timeout=120)
        assert isinstance(saved, msg.EpisodeSaved) and saved.via == "bus" and saved.role == "expert"
        with EpisodeStore(data_dir) as store:
            meta = store.catalog.get_episode(saved.episode)
        assert meta is not None and meta.embodiment == "sawyer" and meta.source == "teleop"
        assert not list((tmp_path / "spool-box-sim").glob("*.payload"))  # delivered, spool emptied
        directory.close()
    finally:
        if session is not None:
            session.close()
        hub.send_signal(signal.SIGTERM)
        try:
            try:
                code = hub.wait(30)
            except subprocess.TimeoutExpired:
                code = None  # a hung shutdown dumps its threads' stacks after 20 s: show them
            assert code == 0, "studio hub did not stop on SIGTERM:\n" + "".join(hub.lines)
        finally:
            if hub.poll() is None:
                hub.kill()
            workers.close()


def test_a_data_dir_that_cannot_be_written_is_one_line_at_startup(tmp_path):
    """/sys refuses new directories even to root: the hub says so in one line and exits."""
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "studio.cli",
            "hub",
            "--data-dir",
            "/sys/kernel/studio-data",
            "--workers",
            "none",
            "--listen",
            bus.loopback_endpoint(bus.free_loopback_port()),
        ],
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    assert out.returncode == 1
    lines = [line for line in (out.stdout + out.stderr).splitlines() if line.strip()]
    assert len(lines) == 1 and "cannot use the data dir /sys/kernel/studio-data" in lines[0], lines
