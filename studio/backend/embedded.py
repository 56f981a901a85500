"""The embedded default: worker child processes on this machine, connected to the hub over loopback.

``studio serve`` (and ``studio hub``) call :func:`start_embedded_workers` unless ``--workers none``:
one sim worker and one trainer, started as ``python -m studio.cli worker …`` with the hub's endpoint,
the hub's data directory (so episodes are stored directly, no shipping) and ``--exit-with-parent`` (so
they never outlive a hub that was killed). Their output goes to ``<data-dir>/logs/``.

A worker that dies (a crash, the out-of-memory killer, a ``kill``) is started again under a new id, at most
:data:`MAX_RESTARTS` times per :data:`RESTART_WINDOW_S`; the job queue fails or re-queues its job and a
teleop session it hosted reopens on the new worker (a recording continues from its draft).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from studio.backend.presence import Directory, new_worker_id

log = logging.getLogger("studio.embedded")

#: Restarts of one kind of worker allowed within RESTART_WINDOW_S before it is left dead (a crash loop).
MAX_RESTARTS = 3
RESTART_WINDOW_S = 60.0


@dataclass
class WorkerProcess:
    kind: str
    worker: str
    process: subprocess.Popen
    log_path: Path
    _log: IO[bytes]


class EmbeddedWorkers:
    """Worker child processes; :meth:`stop` ends them (SIGTERM, then SIGKILL after a grace period)."""

    def __init__(
        self,
        endpoint: str,
        *,
        data_dir: str | Path | None,
        sim: int = 1,
        train: int = 1,
        log_dir: str | Path,
        extra_args: list[str] | tuple[str, ...] = (),
        env: dict[str, str] | None = None,
        kind_args: dict[str, list[str]] | None = None,
    ):
        self.endpoint = endpoint
        self.kind_args = dict(kind_args or {})  # kind -> its own extra options (its bus credentials)
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.processes: list[WorkerProcess] = []
        self.restarts: list[tuple[float, str, str, str]] = []  # (time, kind, dead worker, its replacement)
        self._args = (data_dir, list(extra_args), env)
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        try:
            for kind, count in (("sim", sim), ("train", train)):
                for _ in range(count):
                    self.processes.append(self._spawn(kind, data_dir, list(extra_args), env))
        except Exception:
            self.stop()
            raise
        self._monitor = threading.Thread(target=self._watch, name="embedded-workers", daemon=True)
        self._monitor.start()

    def _watch(self) -> None:
        """Start a worker that died again (unless it keeps dying: then its log says why)."""
        while not self._stopping.wait(0.5):
            with self._lock:
                for i, p in enumerate(self.processes):
                    code = p.process.poll()
                    if code is None or self._stopping.is_set():
                        continue
                    now = time.monotonic()
                    recent = [
                        t for t, kind, _, _ in self.restarts if kind == p.kind and now - t < RESTART_WINDOW_S
                    ]
                    if len(recent) >= MAX_RESTARTS:
                        continue
                    p._log.close()
                    try:
                        new = self._spawn(p.kind, *self._args)
                    except OSError as e:
                        log.error("could not restart %s worker %s: %s", p.kind, p.worker, e)
                        continue
                    log.warning("%s worker %s exited with %s; started %s", p.kind, p.worker, code, new.worker)
                    self.restarts.append((now, p.kind, p.worker, new.worker))
                    self.processes[i] = new

    def _spawn(
        self, kind: str, data_dir: str | Path | None, extra: list[str], env: dict[str, str] | None
    ) -> WorkerProcess:
        worker = new_worker_id(kind)
        cmd = [
            sys.executable,
            "-m",
            "studio.cli",
            "worker",
            kind,
            "--connect",
            self.endpoint,
            "--id",
            worker,
            "--exit-with-parent",
            *extra,
            *self.kind_args.get(kind, ()),
        ]
        if data_dir is not None:
            cmd += ["--data-dir", str(data_dir)]
        log_path = self.log_dir / f"{worker}.log"
        log = open(log_path, "ab")
        proc = subprocess.Popen(
            cmd,
            stdout=log,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env={**os.environ, **(env or {})},
        )
        return WorkerProcess(kind, worker, proc, log_path, log)

    @property
    def workers(self) -> list[str]:
        with self._lock:
            return [p.worker for p in self.processes]

    def wait_ready(self, directory: Directory, timeout: float = 60.0) -> bool:
        """True once every worker's token is in ``directory``; False on timeout or if one exited."""
        wanted = set(self.workers)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(p.process.poll() is not None for p in self.processes):
                return False
            if directory.wait_for(lambda ws: wanted <= {w.worker for w in ws}, timeout=0.5):
                return True
        return False

    def stop(self, grace_s: float = 15.0) -> None:
        self._stopping.set()
        with self._lock:
            pass  # a restart in progress has finished: self.processes is final
        for p in self.processes:
            if p.process.poll() is None:
                p.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for p in self.processes:
            try:
                p.process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.process.kill()
                p.process.wait(5.0)
            p._log.close()

    def __enter__(self) -> EmbeddedWorkers:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()


def start_embedded_workers(hub: Any, *, sim: int = 1, train: int = 1, **kwargs: Any) -> EmbeddedWorkers:
    """Start the embedded default next to ``hub`` (a :class:`studio.backend.hub.Hub`)."""
    return EmbeddedWorkers(
        hub.endpoint,
        kind_args={kind: hub.embedded_worker_args(kind) for kind, n in (("sim", sim), ("train", train)) if n},
        data_dir=hub.data_dir,
        sim=sim,
        train=train,
        log_dir=kwargs.pop("log_dir", Path(hub.data_dir) / "logs"),
        **kwargs,
    )
