"""The ``studio export FORMAT`` command: write the store's episodes in an ecosystem format (LeRobot v3.0)."""

from __future__ import annotations

import argparse
import sys

from studio.data import lerobot
from studio.data.paths import add_data_dir_argument
from studio.data.store import EpisodeStore

FORMATS = ("lerobot",)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("format", choices=FORMATS, help="dataset format")
    lerobot.add_export_arguments(parser)
    add_data_dir_argument(parser)


def run(args: argparse.Namespace) -> int:
    store = EpisodeStore(args.data_dir)
    report = store.check()
    if not report.ok:
        print(report.summary(), file=sys.stderr)
    return lerobot.run_export(args, store)
