"""The ``studio export FORMAT`` command: write the store's episodes in an ecosystem format (LeRobot v3.0).

Also the pieces ``studio import`` shares with it: the format argument and opening the store with its
integrity check reported first.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from studio.data.lerobot import command as lerobot_command
from studio.data.paths import add_data_dir_argument
from studio.data.store import EpisodeStore

FORMATS = ("lerobot",)


def add_format_arguments(
    parser: argparse.ArgumentParser, add_own: Callable[[argparse.ArgumentParser], None]
) -> None:
    """``FORMAT``, the format's own options (``add_own``), then ``--data-dir``."""
    parser.add_argument("format", choices=FORMATS, help="dataset format")
    add_own(parser)
    add_data_dir_argument(parser)


def open_checked_store(data_dir) -> EpisodeStore:
    """The store, after printing what its integrity check found wrong (if anything) to stderr."""
    store = EpisodeStore(data_dir)
    report = store.check()
    if not report.ok:
        print(report.summary(), file=sys.stderr)
    return store


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_format_arguments(parser, lerobot_command.add_export_arguments)


def run(args: argparse.Namespace) -> int:
    return lerobot_command.run_export(args, lambda: open_checked_store(args.data_dir))
