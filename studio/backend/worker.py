"""``studio worker sim|train``: a worker process that joins the bus, announces itself and serves until stopped.

* ``sim`` hosts teleop sessions (:mod:`studio.backend.sim_worker`) and runs ``rollout`` jobs;
* ``train`` runs ``train`` jobs.

Both run the job handlers of :data:`studio.backend.job_runner.JOB_KINDS` for their kind, plus any given
with ``--handler KIND=module:function``. SIGTERM / SIGINT stop the worker cleanly: teleop recordings
being stored are finished, a running job is asked to stop (a training job is then re-queued by the hub
and resumes from its checkpoint elsewhere).

A worker on another machine than the hub, without a shared disk, is started with ``--data-dir DIR --own-data-dir``:
each job's inputs are fetched from the hub into ``DIR`` by content id (and cached there), its outputs are handed
to the hub's data dir, and recorded episodes are shipped to the hub's store
(:mod:`studio.backend.artifact_transfer`, :mod:`studio.backend.episode_transfer`).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

import platformdirs

from studio.backend import bus, keys
from studio.backend.artifact_transfer import WorkerArtifacts
from studio.backend.episode_transfer import EpisodeDestination, EpisodeShipper
from studio.backend.job_runner import JobRunner, resolve_handlers
from studio.backend.presence import WorkerPresence, new_worker_id
from studio.backend.stopping import StopSignals

KINDS = ("sim", "train")


def default_spool_dir(data_dir: str | os.PathLike | None = None) -> Path:
    """Where a worker keeps recordings until the store has them: ``<data-dir>/spool`` for a worker with a data
    dir, else per user (both survive restarts)."""
    if data_dir is not None:
        return Path(data_dir) / "spool"
    return platformdirs.user_data_path("osvi-studio") / "spool"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "kind", choices=KINDS, help="sim: teleop sessions and rollout jobs; train: training jobs"
    )
    bus.add_bus_arguments(parser, "worker")
    parser.add_argument("--id", default=None, help="worker id (default: <kind>-<host>-<random>)")
    parser.add_argument(
        "--data-dir",
        default=None,
        help="dataset root to store recorded episodes in directly (same machine as the hub or a shared "
        "filesystem); without it, episodes are shipped to the hub's store over the bus",
    )
    parser.add_argument(
        "--own-data-dir",
        action="store_true",
        help="--data-dir is this worker's own, not the hub's: fetch each job's inputs from the hub into it (cached by "
        "content id), hand job outputs to the hub's data dir and ship recorded episodes to the hub's store",
    )
    parser.add_argument(
        "--spool-dir",
        default=None,
        help="where episodes wait until the store has them (default: <data-dir>/spool, or without --data-dir "
        f"{default_spool_dir()})",
    )
    parser.add_argument(
        "--handler",
        action="append",
        default=[],
        metavar="KIND=MODULE:FUNCTION",
        help="add or replace a job handler (repeatable)",
    )
    parser.add_argument(
        "--only-handlers",
        action="store_true",
        help="offer only the --handler kinds, not the studio's defaults for this worker kind",
    )
    parser.add_argument(
        "--max-sessions", type=int, default=4, help="most teleop sessions at once (sim; default 4)"
    )
    parser.add_argument("--control-hz", type=float, default=100.0, help="teleop control rate (sim), Hz")
    parser.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="exit when the parent process does (used for the workers `studio serve` starts)",
    )
    parser.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=args.log_level, format=f"%(asctime)s %(levelname)s worker {args.kind}: %(message)s"
    )
    try:
        config = bus.bus_config_from_args(args, "worker")
        worker_id = keys.check_chunk(args.id, "worker id") if args.id else new_worker_id(args.kind)
        handlers, unavailable = resolve_handlers(args.kind, args.handler, defaults=not args.only_handlers)
        if not 1.0 <= args.control_hz <= 500.0:
            raise ValueError(f"--control-hz must be within 1..500, got {args.control_hz}")
        if args.own_data_dir and not args.data_dir:
            raise ValueError(
                "--own-data-dir needs --data-dir (where fetched inputs and job outputs are kept)"
            )
    except ValueError as e:
        print(f"studio worker: {e}", file=sys.stderr)
        return 2
    for kind, reason in unavailable.items():
        logging.warning("job kind %r unavailable: %s", kind, reason)
    try:
        session = bus.open_session(config)
    except bus.BusError as e:
        print(f"studio worker: {e}", file=sys.stderr)
        return 1

    signals = StopSignals("studio worker")
    parent = os.getppid()
    spool_dir = Path(args.spool_dir) if args.spool_dir else default_spool_dir(args.data_dir)
    presence = WorkerPresence(
        session, args.kind, worker_id, job_kinds=sorted(handlers), unavailable=unavailable, announce=False
    )
    artifacts = WorkerArtifacts(session, args.data_dir, worker_id) if args.own_data_dir else None
    runner = JobRunner(
        session,
        presence,
        handlers,
        data_dir=Path(args.data_dir) if args.data_dir else None,
        artifacts=artifacts,
    )
    sim_host = destination = None
    if args.kind == "sim":
        from studio.sim.rendering import preload_llvm_users

        preload_llvm_users()  # before any EGL context: see studio.sim.rendering
        from studio.backend.sim_worker import SimWorker
        from studio.backend.teleop_session import TeleopConfig

        if args.data_dir and not args.own_data_dir:
            destination = EpisodeDestination(data_dir=args.data_dir)
        else:
            destination = EpisodeDestination(shipper=EpisodeShipper(session, spool_dir))
        sim_host = SimWorker(
            session,
            presence,
            destination,
            spool_dir,
            max_sessions=args.max_sessions,
            config=TeleopConfig(control_dt=1.0 / args.control_hz),
            drafts_dir=Path(args.data_dir) if args.data_dir else None,
        )
    presence.announce()
    where = ", ".join(config.connect + config.listen)
    print(f"studio worker {args.kind} {worker_id} ready ({config.mode} on {where})", flush=True)

    def parent_gone() -> bool:
        if args.exit_with_parent and os.getppid() != parent:
            logging.warning("parent process exited; stopping")
            return True
        return False

    try:
        signals.wait_for_stop(every=parent_gone)
    finally:
        with signals.stopping():
            presence.update(state="stopping", activity="shutting down")
            if sim_host is not None:
                sim_host.close()
            runner.shutdown(timeout=5.0)
            presence.close()
            if destination is not None:
                destination.close()
            if artifacts is not None:
                artifacts.close()
            session.close()
    return 0
