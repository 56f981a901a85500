"""How the long-running commands (``studio serve``, ``hub``, ``worker``) stop on SIGTERM or Ctrl+C.

The first signal asks for an orderly shutdown: the command closes its sessions, queues and stores. A second
signal while that is under way exits at once (status 130), for a shutdown that hangs, and a shutdown that takes
longer than :data:`DUMP_AFTER_S` writes every thread's Python stack to stderr, so that the hang says where it is.

The main thread waits for the signal in short slices (:meth:`StopSignals.wait_for_stop`) rather than in one untimed wait:
Python runs handlers only in the main thread between bytecodes, and a signal the kernel hands to one of the
many other threads (zenoh's, torch's) would not wake an untimed lock wait.
"""

from __future__ import annotations

import faulthandler
import io
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

POLL_S = 0.25
DUMP_AFTER_S = 20.0
FORCED_EXIT_STATUS = 130


class StopSignals:
    """SIGTERM and SIGINT handlers for one command; ``stop`` is set by the first signal."""

    def __init__(self, name: str, signals: tuple[int, ...] = (signal.SIGTERM, signal.SIGINT)):
        self.name = name
        self.stop = threading.Event()
        self._stopping = False
        for sig in signals:
            signal.signal(sig, self._on_signal)

    def _on_signal(self, signum: int, _frame: object) -> None:
        if self._stopping:
            print(
                f"{self.name}: second {signal.Signals(signum).name} while stopping: exiting now",
                file=sys.stderr,
            )
            sys.stderr.flush()
            os._exit(FORCED_EXIT_STATUS)
        self.stop.set()

    def wait_for_stop(self, every: Callable[[], bool | None] | None = None) -> None:
        """Block until a signal arrives (or ``every``, called each slice, returns True)."""
        while not self.stop.wait(POLL_S):
            if every is not None and every():
                self.stop.set()

    @contextmanager
    def stopping(self, dump_after_s: float = DUMP_AFTER_S) -> Iterator[None]:
        """Around the shutdown: a second signal exits now; a slow shutdown dumps every thread's stack."""
        self._stopping = True
        try:
            faulthandler.dump_traceback_later(dump_after_s, exit=False, file=sys.stderr)
            armed = True
        except (AttributeError, ValueError, io.UnsupportedOperation):  # stderr is not a file (captured)
            armed = False
        try:
            yield
        finally:
            if armed:
                faulthandler.cancel_dump_traceback_later()
