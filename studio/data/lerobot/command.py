"""The LeRobot format's part of ``studio export lerobot`` / ``studio import lerobot``: its options and runs.

``studio.data.export_command`` / ``import_command`` own the commands (format choice, store opening) and call
these.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from studio.data.lerobot.reader import import_lerobot
from studio.data.lerobot.schema import LeRobotError
from studio.data.lerobot.validate import validate_dataset
from studio.data.lerobot.writer import export_lerobot
from studio.data.store import EpisodeStore


def parse_task_map(items: Sequence[str] | None) -> dict[str, str]:
    """``--task-map`` items ('DATASET TASK=scene/task' pairs or JSON files) as one mapping."""
    out = {}
    for item in items or []:
        if item.endswith(".json") and Path(item).is_file():
            out.update(json.loads(Path(item).read_text()))
            continue
        if "=" not in item:
            raise LeRobotError(
                f"task map entries look like 'DATASET TASK=studio/task' or a JSON file, got {item!r}"
            )
        src, dst = item.rsplit("=", 1)
        out[src] = dst
    return out


def add_export_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, help="new directory for the dataset")
    parser.add_argument("--tasks", nargs="+", default=None, help="only these tasks")
    parser.add_argument("--role", choices=("expert", "agent"), default=None, help="only this role")
    parser.add_argument("--embodiment", default=None, help="only this embodiment (sawyer, panda)")
    parser.add_argument("--source", nargs="+", default=None, help="only these sources")


def run_export(args: argparse.Namespace, store: EpisodeStore) -> int:
    try:
        report = export_lerobot(
            store, args.out, tasks=args.tasks, role=args.role, embodiment=args.embodiment, source=args.source
        )
    except LeRobotError as e:
        print(f"studio export lerobot: {e}", file=sys.stderr)
        return 2
    problems = validate_dataset(args.out)
    print(report.summary() + f" to {args.out}")
    for p in problems:
        print(f"  schema problem: {p}", file=sys.stderr)
    return 1 if problems else 0


def add_import_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("dir", help="LeRobot v3.0 dataset directory")
    parser.add_argument(
        "--task-map",
        nargs="+",
        default=None,
        metavar="MAP",
        help="'DATASET TASK=scene/task' pairs or a JSON file {dataset task: studio task}",
    )
    parser.add_argument(
        "--role", choices=("expert", "agent"), default=None, help="override the role (default: agent)"
    )
    parser.add_argument("--embodiment", default=None, help="override the embodiment")


def run_import(args: argparse.Namespace, store: EpisodeStore) -> int:
    from studio.sim.tasks import list_tasks

    try:
        metas = import_lerobot(
            store,
            args.dir,
            task_map=parse_task_map(args.task_map),
            role=args.role,
            embodiment=args.embodiment,
            known_tasks=list_tasks(),
        )
    except LeRobotError as e:
        print(f"studio import lerobot: {e}", file=sys.stderr)
        return 2
    print(f"imported {len(metas)} episodes from {args.dir}")
    return 0
