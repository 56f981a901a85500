"""The UI host's side of the bus in one object, and ``studio hub`` to run it without the browser UI.

:class:`Hub` opens the router session workers connect to and hosts what exists once per studio: the
worker :class:`~studio.backend.presence.Directory`, the :class:`~studio.backend.job_queue.JobQueue` (with its
journal under ``<data-dir>/jobs/``), the :class:`~studio.backend.episode_transfer.EpisodeSink` that
stores episodes shipped by remote workers, and the :class:`~studio.backend.artifact_transfer.HubArtifacts` that
serve job inputs to, and take job outputs from, workers with their own data dir. ``studio serve`` creates one and,
by default, starts the embedded workers (:func:`studio.backend.embedded.start_embedded_workers`).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Any

from studio.backend import bus
from studio.backend.artifact_transfer import ArtifactJobClient, HubArtifacts
from studio.backend.credentials import EMBEDDED_DIR
from studio.backend.episode_transfer import EpisodeSink
from studio.backend.job_client import JobClient
from studio.backend.job_queue import JobQueue
from studio.backend.presence import Directory
from studio.backend.stopping import StopSignals

JOURNAL_NAME = "jobs/queue.json"


class DataDirError(bus.BusError):
    """The hub cannot use its data directory (missing permission, read-only, full). A :class:`~bus.BusError`, so
    that whatever reports a hub that cannot start (``studio hub``, ``studio serve``) says it in one line."""


def _open_store(data_dir: Path) -> Any:
    """The data dir's episode store, or :class:`DataDirError` saying in one line why it cannot be used."""
    from studio.data.catalog import CatalogError
    from studio.data.store import EpisodeStore, StoreError

    try:
        return EpisodeStore(data_dir)
    except (OSError, CatalogError, StoreError) as e:
        why = e.strerror if isinstance(e, OSError) and e.strerror else bus.one_line(e)
        if not os.access(data_dir if data_dir.exists() else data_dir.parent, os.W_OK):
            why += " (the directory is not writable)"
        raise DataDirError(f"cannot use the data dir {data_dir}: {why}") from None


class Hub:
    """Router session + directory + job queue + episode sink.

    Args:
        config: bus configuration (default: a router on ``tcp/127.0.0.1:7447``).
        data_dir: dataset root of the studio's store (None: ``STUDIO_DATA_DIR`` or the user data dir).
        journal: job-queue journal (default ``<data_dir>/jobs/queue.json``).
        store: an already open :class:`studio.data.store.EpisodeStore` to use instead of opening one.
    """

    def __init__(
        self,
        config: bus.BusConfig | None = None,
        *,
        data_dir: str | Path | None = None,
        journal: str | Path | None = None,
        store: Any = None,
    ):
        from studio.data.paths import resolve_data_dir

        self.config = config or bus.BusConfig.hub()
        self.data_dir = resolve_data_dir(data_dir)
        self._own_store = store is None
        self.store = store if store is not None else _open_store(self.data_dir)
        self.session = bus.open_session(self.config)
        self.directory = Directory(self.session)
        self.jobs = JobQueue(self.session, self.directory, journal=journal or self.data_dir / JOURNAL_NAME)
        self.sink = EpisodeSink(self.session, self.store)
        self.artifacts = HubArtifacts(self.session, self.data_dir, self.store)
        self.job_client: JobClient = ArtifactJobClient(self.session, self.artifacts)

    @property
    def endpoint(self) -> str:
        """The endpoint local workers connect to (the first listen endpoint, on loopback if it is a wildcard)."""
        if not self.config.listen:
            raise bus.BusError("this hub does not listen; workers must be reachable through --connect")
        return bus.local_endpoint(self.config.listen[0])

    def embedded_worker_args(self, kind: str) -> list[str]:
        """The bus options of a worker of ``kind`` this hub starts itself: none on a plain bus; on a bus with
        credentials, the role config ``studio bus credentials`` put beside the hub's (``embedded/<kind>.json5``)."""
        security = self.config.security()
        if security is None or not (security.listen_certificate or security.user):
            return []
        assert self.config.config_file is not None
        path = Path(self.config.config_file).parent / EMBEDDED_DIR / f"{kind}.json5"
        if not path.is_file():
            raise bus.BusError(
                f"the hub's bus config has credentials but {path} is missing, so its own {kind} worker could not "
                "join: use the hub directory `studio bus credentials` wrote, or start with --workers none"
            )
        return ["--bus-config", str(path)]

    def close(self) -> None:
        self.artifacts.close()
        self.sink.close()
        self.jobs.close()
        self.directory.close()
        self.session.close()
        if self._own_store:
            self.store.close()

    def __enter__(self) -> Hub:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    bus.add_bus_arguments(parser, "hub")
    parser.add_argument(
        "--data-dir", default=None, help="dataset root (default: $STUDIO_DATA_DIR or the user data dir)"
    )
    parser.add_argument(
        "--workers",
        choices=("default", "none"),
        default="default",
        help="default: start one sim worker and one trainer here; none: wait for external workers",
    )
    parser.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))


def run(args: argparse.Namespace) -> int:
    """``studio hub``: the studio's bus, job queue and store without the browser UI."""
    from studio.backend.embedded import start_embedded_workers

    logging.basicConfig(level=args.log_level, format="%(asctime)s %(levelname)s hub: %(message)s")
    try:
        config = bus.bus_config_from_args(args, "hub")
    except ValueError as e:
        print(f"studio hub: {e}", file=sys.stderr)
        return 2
    try:
        hub = Hub(config, data_dir=args.data_dir)
    except bus.BusError as e:
        print(f"studio hub: {e}", file=sys.stderr)
        return 1
    signals = StopSignals("studio hub")
    workers = None
    try:
        if args.workers == "default":
            workers = start_embedded_workers(hub)
        print(f"studio hub ready on {', '.join(config.listen)} (data: {hub.data_dir})", flush=True)
        signals.wait_for_stop()
    finally:
        with signals.stopping():
            if workers is not None:
                workers.stop()
            hub.close()
    return 0
