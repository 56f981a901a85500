"""``studio bench bus``: teleop through the bus and a real sim worker process, as the browser studio uses it.

Starts a Zenoh router in this process and ``studio worker sim`` as a child process on a free loopback
port, opens a teleop session, then measures, one phase after the other:

* ``pose_stream_hz`` — PoseFrames received per second while no command is sent (the worker's own pace);
* ``teleop_rtt_ms_p50`` / ``_p99`` — from publishing an EeTarget to receiving the first PoseFrame that
  applied it (``ack_seq``), commands sent at ``--command-hz`` along a small circle;
* ``image_mb_per_s`` — raw RGB camera frames requested back to back (render + transfer), megabytes of
  payload per second (``image_fps`` alongside).

* ``teleop_rtt_ms_p50_tcp`` / ``_p99_tcp`` and ``teleop_rtt_ms_p50_tls`` / ``_p99_tls`` (phase ``tls``) — the same
  command round trip over plain loopback TCP and over the authenticated bus (credentials from
  :func:`studio.backend.credentials.generate`: TLS with client certificates, passwords, the hub's access rules),
  one after the other with a fresh worker each, so the difference is what TLS and the rules cost a teleop hop;

* ``job_submit_per_s_at_<n>_queued`` — jobs submitted per second (``JobSubmit`` round trips from a client
  session to the hub's queue, one after the other) when ``n`` = 10, 1,000 and 10,000 jobs are already queued (a
  kind no worker offers, so they stay queued); ``job_queue_idle_cpu`` — the share of a core this process uses
  while the queue holds them all and nothing happens. Flat across the three levels: submitting costs O(log n).

Targets on a 2-core machine: p50 ≤ 5 ms, p99 ≤ 20 ms, pose stream ≥ 60 Hz; job submission within a factor of
2 from 10 to 10,000 queued, an idle queue under 2 % of a core; TLS adding under 1 ms to the p50 round trip.
``--phases jobs`` measures the queue alone, ``--phases tls`` the transport comparison alone.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import zenoh

from studio.backend import bus
from studio.backend.presence import Directory
from studio.backend.teleop_client import TeleopClient


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--seconds", type=float, default=5.0, help="duration of the pose-stream and image phases"
    )
    parser.add_argument("--commands", type=int, default=500, help="teleop commands for the latency phase")
    parser.add_argument("--command-hz", type=float, default=60.0, help="rate of teleop commands")
    parser.add_argument("--scene", default="pick_place")
    parser.add_argument("--robot", default="panda")
    parser.add_argument("--task", default="pick_place/cube->red")
    parser.add_argument("--control-hz", type=float, default=100.0, help="the worker's control rate")
    parser.add_argument(
        "--phases",
        default="teleop,jobs,tls",
        help="comma-separated: teleop (with a sim worker), jobs (the queue alone), tls (teleop round trips over "
        "plain TCP, then over TLS with credentials)",
    )
    parser.add_argument(
        "--queued", default="10,1000,10000", help="queue lengths at which job submission is timed"
    )
    parser.add_argument("--submits", type=int, default=200, help="submissions timed at each queue length")


def measure(args: argparse.Namespace) -> dict:
    phases = {p.strip() for p in args.phases.split(",") if p.strip()}
    unknown = phases - {"teleop", "jobs", "tls"}
    if unknown:
        raise SystemExit(f"studio bench bus: unknown phases {sorted(unknown)}; choose from teleop, jobs, tls")
    out: dict = {}
    if "jobs" in phases:
        out.update(measure_job_queue([int(n) for n in args.queued.split(",")], args.submits))
    if "teleop" in phases:
        out.update(measure_teleop(args))
    if "tls" in phases:
        out.update(measure_tls(args))
    return out


def measure_job_queue(levels: list[int], submits: int) -> dict:
    """Submission rate at each queue length in ``levels`` and the idle cost of the full queue, on a hub queue of
    this process (journal in a temporary directory) with a client in a second session over TCP loopback."""
    from studio.backend.job_client import JobClient
    from studio.backend.job_queue import JobQueue

    port = bus.free_loopback_port()
    endpoint = bus.loopback_endpoint(port)
    session = bus.open_session(bus.BusConfig.hub([endpoint]))
    client_session = bus.open_session(bus.BusConfig.worker([endpoint]))
    directory = Directory(session)
    tmp = tempfile.TemporaryDirectory(prefix="studio-bench-jobs-")
    journal = os.path.join(tmp.name, "queue.json")
    queue = JobQueue(session, directory, journal=journal)
    client = JobClient(client_session)
    out: dict = {}
    queued = 0

    def submit(n: int) -> float:
        nonlocal queued
        t0 = time.perf_counter()
        for _ in range(n):
            client.submit("bench", {"n": queued}, worker_kind="bench")
            queued += 1
        return time.perf_counter() - t0

    try:
        for level in sorted(levels):
            if queued < level:
                submit(level - queued)
            seconds = submit(submits)
            out[f"job_submit_per_s_at_{level}_queued"] = round(submits / seconds, 1)
        time.sleep(1.5)  # the queue settles (pushed positions) before the idle measurement
        cpu0, t0 = os.times(), time.monotonic()
        time.sleep(3.0)
        cpu1 = os.times()
        busy = (cpu1.user + cpu1.system - cpu0.user - cpu0.system) / (time.monotonic() - t0)
        out["job_queue_idle_cpu"] = round(busy, 4)
        out["job_queue_jobs"] = len(queue.jobs())
        out["job_journal_bytes"] = os.path.getsize(journal)
        return out
    finally:
        queue.close()
        directory.close()
        client_session.close()
        session.close()
        tmp.cleanup()


class SimWorkerProcess:
    """``studio worker sim`` as a child process connected to ``endpoint`` (with ``bus_args``, e.g. its credentials),
    and a teleop session opened on it from ``session``, the hub's side."""

    def __init__(
        self,
        session: zenoh.Session,
        endpoint: str,
        args: argparse.Namespace,
        name: str,
        bus_args: list[str] | None = None,
    ):
        self.directory = Directory(session)
        self.spool = tempfile.TemporaryDirectory(prefix="studio-bench-bus-")
        self.worker = f"bench-{name}-{os.getpid()}"
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "studio.cli",
                "worker",
                "sim",
                "--connect",
                endpoint,
                "--id",
                self.worker,
                "--spool-dir",
                self.spool.name,
                "--control-hz",
                str(args.control_hz),
                "--log-level",
                "WARNING",
                *(bus_args or []),
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,  # its "ready" line would break the JSON on stdout; errors go to stderr
        )
        self.client: TeleopClient | None = None
        try:
            worker = self.worker
            if not self.directory.wait_for(
                lambda ws: any(w.worker == worker and w.status for w in ws), timeout=60.0
            ):
                raise RuntimeError(f"the sim worker {worker} did not come up within 60 s")
            self.client = TeleopClient(
                session, worker, timeout=120.0
            )  # building the scene is slow on a busy machine
            self.info = self.client.open(args.scene, args.robot, args.task, seed=0)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
        self.proc.terminate()
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
        self.directory.close()
        self.spool.cleanup()


def command_round_trips(client: TeleopClient, commands: int, command_hz: float) -> tuple[np.ndarray, int]:
    """Milliseconds from publishing an EeTarget (along a small circle) to the first PoseFrame that applied it, at
    ``command_hz``; and how many commands were never acknowledged within 1 s."""
    first = client.poses.wait_until(lambda f: True, 5.0)
    if first is None:
        raise RuntimeError("the teleop session sent no pose within 5 s")
    centre = np.asarray(first.ee_pos)
    period = 1.0 / command_hz
    rtts: list[float] = []
    missed = 0
    for i in range(commands):
        t_start = time.perf_counter()
        angle = 2 * np.pi * i / 120.0
        target = centre + 0.05 * np.array([np.cos(angle) - 1.0, np.sin(angle), 0.0])
        seq = client.set_target(target.tolist(), 0.0)
        if client.wait_ack(seq, timeout=1.0) is None:
            missed += 1
        else:
            rtts.append((time.perf_counter() - t_start) * 1000.0)
        time.sleep(max(0.0, period - (time.perf_counter() - t_start)))
    return (np.asarray(rtts) if rtts else np.array([float("nan")])), missed


def measure_tls(args: argparse.Namespace) -> dict:
    """Teleop command round trips over plain loopback TCP, then over TLS with client certificates, passwords and
    the hub's access rules (fresh credentials in a temporary directory), each with its own sim worker."""
    from studio.backend.credentials import generate

    out: dict = {"tls_commands": args.commands, "tls_command_hz": args.command_hz}
    with tempfile.TemporaryDirectory(prefix="studio-bench-creds-") as tmp:
        t0 = time.perf_counter()
        bundle = generate(tmp, ["localhost"], port=bus.free_loopback_port())
        out["tls_credentials_s"] = round(time.perf_counter() - t0, 2)
        for transport in ("tcp", "tls"):
            port = bus.free_loopback_port()
            if transport == "tcp":
                endpoint = bus.loopback_endpoint(port)
                hub_config, bus_args = bus.BusConfig.hub([endpoint]), []
            else:
                endpoint = f"tls/127.0.0.1:{port}"
                hub_config = bus.BusConfig.from_file(bundle.configs["hub"], listen=[endpoint])
                bus_args = ["--bus-config", str(bundle.configs["sim"])]
            session = bus.open_session(hub_config)
            try:
                worker = SimWorkerProcess(session, endpoint, args, f"{transport}-sim", bus_args)
                try:
                    assert worker.client is not None
                    rtt, missed = command_round_trips(worker.client, args.commands, args.command_hz)
                finally:
                    worker.close()
            finally:
                session.close()
            out[f"teleop_rtt_ms_p50_{transport}"] = round(float(np.percentile(rtt, 50)), 3)
            out[f"teleop_rtt_ms_p99_{transport}"] = round(float(np.percentile(rtt, 99)), 3)
            out[f"teleop_commands_unacknowledged_{transport}"] = missed
    out["tls_transport"] = (
        "hub router in the benchmark process, sim worker as client; tls: mTLS + user/password + ACL"
    )
    return out


def measure_teleop(args: argparse.Namespace) -> dict:
    port = bus.free_loopback_port()
    endpoint = bus.loopback_endpoint(port)
    session = bus.open_session(bus.BusConfig.hub([endpoint]))
    sim = None
    try:
        sim = SimWorkerProcess(session, endpoint, args, "sim")
        client, info = sim.client, sim.info
        assert client is not None

        # -- pose stream, no commands
        client.poses.wait_until(lambda f: True, 5.0)
        first, v0 = client.poses.get()
        t0 = time.perf_counter()
        arrivals: list[float] = []
        version = v0
        while time.perf_counter() - t0 < args.seconds:
            _, v = client.poses.wait_newer(version, 1.0)
            if v > version:
                arrivals.append(time.perf_counter())
                version = v
        last, _ = client.poses.get()
        elapsed = arrivals[-1] - t0 if arrivals else args.seconds
        pose_hz = (last.seq - first.seq) / elapsed if elapsed > 0 else 0.0
        gaps = np.diff(arrivals) * 1000.0 if len(arrivals) > 1 else np.array([0.0])

        # -- command -> acknowledged pose
        rtt, missed = command_round_trips(client, args.commands, args.command_hz)

        # -- camera images (raw RGB), back to back
        client.request_frame(encoding="raw")  # the first render creates the GL context
        n_bytes, n_frames = 0, 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < args.seconds:
            image = client.request_frame(encoding="raw")
            n_bytes += len(image.data)
            n_frames += 1
        img_elapsed = time.perf_counter() - t0
        return {
            "teleop_rtt_ms_p50": round(float(np.percentile(rtt, 50)), 3),
            "teleop_rtt_ms_p99": round(float(np.percentile(rtt, 99)), 3),
            "teleop_commands": args.commands,
            "teleop_commands_unacknowledged": missed,
            "command_hz": args.command_hz,
            "pose_stream_hz": round(pose_hz, 2),
            "pose_gap_ms_p99": round(float(np.percentile(gaps, 99)), 3),
            "pose_frame_bytes": len(last.poses),
            "control_dt_s": info.control_dt,
            "image_mb_per_s": round(n_bytes / img_elapsed / 1e6, 3),
            "image_fps": round(n_frames / img_elapsed, 2),
            "image_size": [info.image_height, info.image_width],
            "image_encoding": "raw",
            "transport": "zenoh tcp loopback, router in the benchmark process, worker as client",
            "scene": args.scene,
            "robot": args.robot,
        }
    finally:
        if sim is not None:
            sim.close()
        session.close()
