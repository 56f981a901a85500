"""Stopping on SIGTERM: in slices, whatever thread the signal lands on; a second signal or a hang says so."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import pytest

# A command's main loop: wait for the stop, then a shutdown that takes ``SHUTDOWN_S`` (or hangs when negative).
PROGRAM = textwrap.dedent(
    """
    import sys, threading, time
    from studio.backend.stopping import StopSignals

    shutdown_s, dump_after_s = float(sys.argv[1]), float(sys.argv[2])
    signals = StopSignals("probe")
    print("ready", flush=True)
    signals.wait_for_stop()
    print("stopping", flush=True)
    with signals.stopping(dump_after_s=dump_after_s):
        time.sleep(shutdown_s if shutdown_s >= 0 else 3600)
    print("stopped", flush=True)
    """
)


def start(shutdown_s: float, dump_after_s: float = 20.0, program: str = PROGRAM) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-c", program, str(shutdown_s), str(dump_after_s)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stdout.readline() == "ready\n"
    return proc


def test_the_first_signal_stops_in_order():
    proc = start(0.1)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert out.split() == ["stopping", "stopped"]


def test_a_signal_landing_on_another_thread_still_stops_the_command():
    # The kernel may hand a process's signal to any thread; an untimed wait in the main thread would not wake.
    program = PROGRAM.replace(
        'print("ready", flush=True)',
        'print("ready", flush=True)\n'
        "import signal\n"
        "def other():\n"
        "    time.sleep(0.2)\n"
        "    signal.pthread_kill(threading.get_ident(), signal.SIGTERM)\n"
        "    time.sleep(3600)\n"
        "threading.Thread(target=other, daemon=True).start()",
    )
    proc = start(0.0, program=program)
    t0 = time.monotonic()
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert out.split() == ["stopping", "stopped"]
    assert time.monotonic() - t0 < 10


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_hung_shutdown_shows_its_stacks_and_a_second_signal_exits_now(sig):
    proc = start(-1.0, dump_after_s=0.3)
    proc.send_signal(signal.SIGTERM)
    assert proc.stdout is not None and proc.stdout.readline() == "stopping\n"
    time.sleep(1.5)  # past the dump
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130
    assert "stopped" not in out
    assert "Timeout (0:00:00.300000)!" in err and 'File "<string>", line 11' in err  # where it hangs
    assert f"probe: second {sig.name} while stopping: exiting now" in err


def test_a_poll_callback_can_end_the_wait():
    from studio.backend.stopping import StopSignals

    calls = []
    signals = StopSignals("probe", signals=())  # no handlers: this process's own stay as they are
    signals.wait_for_stop(every=lambda: calls.append(1) or len(calls) == 3)
    assert signals.stop.is_set() and len(calls) == 3
