"""``studio bench bus``: teleop through the bus and a real sim worker process, as the browser studio uses it.

Starts a Zenoh router in this process and ``studio worker sim`` as a child process on a free loopback
port, opens a teleop session, then measures, one phase after the other:

* ``pose_stream_hz`` — PoseFrames received per second while no command is sent (the worker's own pace);
* ``teleop_rtt_ms_p50`` / ``_p99`` — from publishing an EeTarget to receiving the first PoseFrame that
  applied it (``ack_seq``), commands sent at ``--command-hz`` along a small circle;
* ``image_mb_per_s`` — raw RGB camera frames requested back to back (render + transfer), megabytes of
  payload per second (``image_fps`` alongside).

Targets on a 2-core machine: p50 ≤ 5 ms, p99 ≤ 20 ms, pose stream ≥ 60 Hz.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

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


def measure(args: argparse.Namespace) -> dict:
    port = bus.free_loopback_port()
    endpoint = bus.loopback_endpoint(port)
    session = bus.open_session(bus.BusConfig.hub([endpoint]))
    directory = Directory(session)
    spool = tempfile.TemporaryDirectory(prefix="studio-bench-bus-")
    worker = f"bench-sim-{os.getpid()}"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "studio.cli",
            "worker",
            "sim",
            "--connect",
            endpoint,
            "--id",
            worker,
            "--spool-dir",
            spool.name,
            "--control-hz",
            str(args.control_hz),
            "--log-level",
            "WARNING",
        ],
        stdin=subprocess.DEVNULL,
    )
    client = None
    try:
        if not directory.wait_for(lambda ws: any(w.worker == worker and w.status for w in ws), timeout=60.0):
            raise RuntimeError("the sim worker did not come up within 60 s")
        client = TeleopClient(session, worker)
        info = client.open(args.scene, args.robot, args.task, seed=0)

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
        centre = np.asarray(first.ee_pos)
        period = 1.0 / args.command_hz
        rtts: list[float] = []
        missed = 0
        for i in range(args.commands):
            t_start = time.perf_counter()
            angle = 2 * np.pi * i / 120.0
            target = centre + 0.05 * np.array([np.cos(angle) - 1.0, np.sin(angle), 0.0])
            seq = client.set_target(target.tolist(), 0.0)
            frame = client.wait_ack(seq, timeout=1.0)
            if frame is None:
                missed += 1
            else:
                rtts.append((time.perf_counter() - t_start) * 1000.0)
            time.sleep(max(0.0, period - (time.perf_counter() - t_start)))
        rtt = np.asarray(rtts) if rtts else np.array([float("nan")])

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
        if client is not None:
            client.close()
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        directory.close()
        session.close()
        spool.cleanup()
