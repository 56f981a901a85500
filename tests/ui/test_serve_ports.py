"""A second `studio serve` on the same machine: the default bus port taken is replaced by a free one (and said),
an explicitly requested one that is taken is refused with the flag to pass."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time

import pytest

from studio.backend import bus


@contextlib.contextmanager
def listening(port: int):
    """A listener on 127.0.0.1:``port`` (what another studio's bus router holds), or nothing if one exists."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        try:
            s.bind(("127.0.0.1", port))
            s.listen()
        except OSError:
            pass  # already taken (another studio on this machine): just as good
        yield
    finally:
        s.close()


def test_endpoint_in_use_sees_a_listener():
    port = bus.free_loopback_port()
    assert not bus.endpoint_in_use(bus.loopback_endpoint(port))
    with listening(port):
        assert bus.endpoint_in_use(bus.loopback_endpoint(port))
    assert not bus.endpoint_in_use("tcp/127.0.0.1:0") and not bus.endpoint_in_use("udp/127.0.0.1:7447")


def _serve(*extra: str, tmp_path) -> subprocess.Popen:
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    cmd = [
        sys.executable,
        "-m",
        "studio.cli",
        "serve",
        "--port",
        str(bus.free_loopback_port()),
        "--workers",
        "none",
        "--data-dir",
        str(tmp_path / "data"),
        *extra,
    ]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)


def _first_lines(proc: subprocess.Popen, until: str, seconds: float = 90) -> str:
    out, deadline = "", time.time() + seconds
    while time.time() < deadline:
        line = proc.stdout.readline()
        out += line
        if until in line or (not line and proc.poll() is not None):
            break
    return out


@pytest.mark.slow
def test_a_second_studio_serve_takes_a_free_bus_port_and_says_which(tmp_path):
    with listening(bus.DEFAULT_PORT):
        proc = _serve(tmp_path=tmp_path)
        try:
            out = _first_lines(proc, "OSVI Studio running at")
            assert "OSVI Studio running at" in out, out
            line = next(x for x in out.splitlines() if "running at" in x)
            assert (
                f"port {bus.DEFAULT_PORT} was taken; start other workers with --connect tcp/127.0.0.1:"
                in line
            )
            endpoint = line.split("--connect ")[1].split(";")[0]
            assert endpoint != bus.DEFAULT_HUB_ENDPOINT and bus.endpoint_in_use(endpoint)
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    assert proc.returncode == 0


@pytest.mark.slow
def test_an_explicit_bus_endpoint_in_use_is_refused_with_the_flag_to_pass(tmp_path):
    port = bus.free_loopback_port()
    with listening(port):
        proc = _serve("--listen", bus.loopback_endpoint(port), tmp_path=tmp_path)
        out = _first_lines(proc, "--listen")
        proc.wait(timeout=60)
    assert proc.returncode == 1, out
    assert (
        f"the bus endpoint tcp/127.0.0.1:{port} is already in use" in out
        and "pass a free one, e.g. --listen" in out
    )
    assert "Address already in use" not in out
